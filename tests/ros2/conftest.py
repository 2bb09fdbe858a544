"""Tests that load DDS (rclpy). They run only inside a loopback-only network namespace with the
loopback Fast DDS profile (``make test-all`` runs them with ``python -m ovamos.shared.dds -- pytest tests/ros2``);
anywhere else they are not even imported, so no DDS process starts in the host's namespace."""

from __future__ import annotations

import os

from ovamos.shared.dds import DdsNetworkError, check_loopback_only

# pytest-xdist's workers (gw0, gw1, ...) each on a DDS domain of their own, set before any rclpy starts
# and inherited by the processes the tests start: the tests' topics have fixed names (/odom, /cmd_vel)
_worker = os.environ.get("PYTEST_XDIST_WORKER", "")
if _worker.startswith("gw"):
    os.environ["ROS_DOMAIN_ID"] = str(10 + int(_worker[2:]))

try:
    check_loopback_only()
except DdsNetworkError:
    collect_ignore_glob = ["test_*.py"]
