"""ROS 2 node wrapping morph_core.sim.SwimmerSim."""
