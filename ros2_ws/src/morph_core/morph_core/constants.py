"""The numbers every layer of the core shares: the bottom of its layers (``docs/design.md``, "The core's
layers"), so that any module may read them without importing a layer above its own.

Only plain constants live here, no code: a body's size limits, the widths of the policy's inputs, the
longest joint name. What belongs to one layer stays in that layer (a swimmer's segment length in
``env.model``, a checkpoint's limits in ``policy.config``).
"""

MIN_JOINTS = 1
"""fewest actuated joints of a body (a chain of one joint is a swimmer too)"""
MAX_JOINTS = 64
"""most actuated joints of a body: the env's models, a robot description, a joint state and a recording"""
MAX_NAME_CHARS = 256
"""longest joint name taken (URDF names are short; a megabyte-long one is a fault, not a robot)"""
NUM_EDGE_FEATURES = 2
"""per joint: angle, angular velocity; a policy with joint descriptions reads ``PolicyConfig.edge_features`` =
2 + ``joint_features``"""
NUM_GLOBAL_FEATURES = 4
"""the swimmer's global input: the torso's yaw, yaw rate, vx, vy; the default of
``PolicyConfig.global_features``"""
LEGGED_GLOBAL_FEATURES = 12
"""a body in 3-D (``env.centipede.GLOBAL_FEATURES``; ``msgs.joint_state.legged_global_features``): a policy
whose ``global_features`` is 12 reads these"""
