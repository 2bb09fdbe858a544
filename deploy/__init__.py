"""The deployment files (profiles, service and Zenoh configs, ROS 2 and Foxglove files), read as
package data through :func:`ovamos.resources.deploy_dir` so an installed wheel finds them too."""
