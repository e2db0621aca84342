"""ROS 2 node wrapping morph_core.env.sim.SwimmerSim."""
