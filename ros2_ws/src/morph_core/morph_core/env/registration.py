"""The Gymnasium ids of the project's envs, registered when this module is imported.

The env modules (``env.swimmer_env``, ``env.centipede``) import it, so anything that uses an env registers
both ids; ``import gymnasium; import morph_core.env.registration`` is the way to ``gymnasium.make`` one by
id alone. ``import morph_core`` imports no gymnasium: the policy node imports the core's messages, protocol
and NumPy policy, and a robot that runs only it has no gymnasium installed.
"""

from __future__ import annotations

import gymnasium

from morph_core import CENTIPEDE_ENV_ID, ENV_ID

if ENV_ID not in gymnasium.registry:
    gymnasium.register(
        id=ENV_ID,
        entry_point="morph_core.env.swimmer_env:MorphSwimmerEnv",
        max_episode_steps=1000,
    )
if CENTIPEDE_ENV_ID not in gymnasium.registry:
    gymnasium.register(
        id=CENTIPEDE_ENV_ID,
        entry_point="morph_core.env.centipede:MorphCentipedeEnv",
        max_episode_steps=1000,  # Ant-v5's
    )
