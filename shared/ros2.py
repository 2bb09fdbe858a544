"""The process's one ROS 2 node: the only module of the project that imports rclpy.

One rclpy context, one node and one executor spinning on a daemon thread, made on first use and
shared by whatever in the process talks ROS (the ros2 base today). rclpy callbacks run on that
thread and only hand data over under the user's own lock, as Zenoh's do. rclpy is initialised
without its signal handlers: SIGINT and SIGTERM stay the service's (:mod:`ovamos.shared.service`).

``network`` says where DDS may go. ``"loopback"`` (the default; tests, CI, the demo) refuses to
start unless :func:`ovamos.shared.dds.check_loopback_only` passes. ``"host"`` is for a robot, whose ROS
graph spans its own computers (a TurtleBot 4's Create 3 is another host): the robot's own ROS
environment then applies as it is, and the service logs that it chose it.
"""

from __future__ import annotations

import logging
import os
import threading
from typing import Any, Literal

from pydantic import Field

from ovamos.shared.dds import check_loopback_only

__all__ = ["Network", "NETWORK_FIELD", "Ros2Unavailable", "node", "stamp_s"]

Network = Literal["loopback", "host"]
NETWORK_FIELD: Any = Field(default="loopback", description="'loopback': DDS only in a loopback-only "
                           "network namespace (tests, demo); 'host': this host's ROS network (a robot)")
"""The ``network`` setting of every config that talks ROS 2 (see the module)."""
log = logging.getLogger("ovamos.ros2")
_lock = threading.Lock()
_node: Any = None


class Ros2Unavailable(RuntimeError):
    """ROS 2 cannot start here: rclpy missing, or DDS refused by the network check."""


def node(network: Network = "loopback") -> Any:
    """The process's rclpy node (``rclpy.node.Node``), spinning; raises :class:`Ros2Unavailable`."""
    global _node
    with _lock:
        if _node is not None:
            return _node
        if network == "loopback":
            try:
                check_loopback_only()
            except RuntimeError as exc:
                raise Ros2Unavailable(str(exc)) from None
        else:
            log.warning("ROS 2 on the host's network (network = 'host'): DDS discovers by the robot's "
                        "own ROS settings (ROS_DOMAIN_ID %s, ROS_AUTOMATIC_DISCOVERY_RANGE %s)",
                        os.environ.get("ROS_DOMAIN_ID", "0"), os.environ.get("ROS_AUTOMATIC_DISCOVERY_RANGE", "SUBNET"))
        try:
            import rclpy
            from rclpy.executors import SingleThreadedExecutor
            from rclpy.signals import SignalHandlerOptions
        except ImportError as exc:
            raise Ros2Unavailable(f"rclpy is not installed ({exc}): pip install '.[ros2]', or on a robot "
                                  "a venv with --system-site-packages beside /opt/ros/jazzy") from None
        context = rclpy.Context()
        rclpy.init(context=context, signal_handler_options=SignalHandlerOptions.NO)
        made = rclpy.create_node(f"ovamos_{os.getpid()}", context=context)
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(made)
        threading.Thread(target=_spin, args=(executor,), name="ros2-executor", daemon=True).start()
        _node = made
        return made


def _spin(executor: Any) -> None:
    """Run the executor until the context shuts down (at process exit)."""
    from rclpy.executors import ExternalShutdownException
    try:
        executor.spin()
    except ExternalShutdownException:
        log.debug("ROS 2 executor stopped: the context shut down")


def stamp_s(msg: Any) -> float:
    """A stamped message's ``header.stamp`` in seconds (the publisher's clock)."""
    return msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9
