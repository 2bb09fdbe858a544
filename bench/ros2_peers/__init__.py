"""Mock ROS 2 peers (a base, an RGB-D camera, a viewer), each a script run as its own process in
a loopback-only namespace, for the ros2 tests and ``ovamos bench ros2``: they stand in for
``turtlebot3_node`` / a Create 3, ``realsense2_camera`` and RViz. :class:`nodes.MockNode` starts
one and collects what it prints."""
