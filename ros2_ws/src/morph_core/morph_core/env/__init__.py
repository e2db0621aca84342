"""The swimmer: its MJCF model for any chain length, the Gymnasium env, the vector env, and the sim a node wraps."""
