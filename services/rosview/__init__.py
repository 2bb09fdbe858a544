"""What the search shows to ROS 2 (RViz, ros2 bag): the map, the path, the goal, found objects."""
