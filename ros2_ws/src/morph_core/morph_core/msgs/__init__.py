"""Message contents as plain arrays (no ROS import): joint states and odometry in, policy samples out."""
