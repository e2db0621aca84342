"""morph_core: the ROS-free core of morphology-agnostic swimmer control.

Importing it registers the Gymnasium ids ``MorphSwimmer-v0`` and ``MorphCentipede-v0``.
"""

import gymnasium

ENV_ID = "MorphSwimmer-v0"
CENTIPEDE_ENV_ID = "MorphCentipede-v0"

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

__all__ = ["CENTIPEDE_ENV_ID", "ENV_ID"]
