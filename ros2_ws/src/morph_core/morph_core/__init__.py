"""morph_core: the ROS-free core of morphology-agnostic control.

The Gymnasium ids of its envs are named here and registered by ``morph_core.env.registration`` when an env
module is imported, not by ``import morph_core``: the nodes import the core, and a robot's policy node has no
gymnasium (``setup.py``: the runtime part, and the ``sim`` and ``learn`` extras).
"""

ENV_ID = "MorphSwimmer-v0"
CENTIPEDE_ENV_ID = "MorphCentipede-v0"

__all__ = ["CENTIPEDE_ENV_ID", "ENV_ID"]
