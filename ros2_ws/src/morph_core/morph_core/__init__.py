"""morph_core: the ROS-free core of morphology-agnostic swimmer control.

Importing it registers the Gymnasium id ``MorphSwimmer-v0``.
"""

import gymnasium

ENV_ID = "MorphSwimmer-v0"

if ENV_ID not in gymnasium.registry:
    gymnasium.register(
        id=ENV_ID,
        entry_point="morph_core.env.swimmer_env:MorphSwimmerEnv",
        max_episode_steps=1000,
    )

__all__ = ["ENV_ID"]
