"""Tests that load DDS (rclpy). They run only inside a loopback-only network namespace with the
loopback Fast DDS profile (``make test-all`` runs them with ``python -m ovamos.shared.dds -- pytest tests/ros2``);
anywhere else they are not even imported, so no DDS process starts in the host's namespace."""

from __future__ import annotations

from ovamos.shared.dds import DdsNetworkError, check_loopback_only

try:
    check_loopback_only()
except DdsNetworkError:
    collect_ignore_glob = ["test_*.py"]
