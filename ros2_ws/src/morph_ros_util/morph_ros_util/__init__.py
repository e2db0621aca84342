"""ROS 2 helpers shared by the project's nodes (kept out of morph_core, which imports no ROS)."""
