"""ROS 2 node running the morphology-agnostic GNN policy on JointState messages."""
