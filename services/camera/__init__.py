"""The robot's camera service: RGB-D frames from a real SDK (or a recording) on ``sensors/rgbd``."""
