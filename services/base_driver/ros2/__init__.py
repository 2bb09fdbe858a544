"""A base run by ROS 2: the hardware interface that carries cmd_vel out and its odometry in."""
