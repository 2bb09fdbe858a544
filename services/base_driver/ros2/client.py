"""A ROS 2 base behind the controller: velocity out on ``cmd_vel``, the robot's own odometry in.

For a base already run by ROS 2 (TurtleBot 3 on Jazzy: ``turtlebot3_node``; TurtleBot 4: the
Create 3; any nav2 robot), left as it is. The controller keeps primitives, deadman, e-stop
latch, limits, ramps and faults; this interface only carries (v, w) out and the pose in:

* out: ``geometry_msgs/TwistStamped`` (TurtleBot 3 on Jazzy, nav2) or ``Twist`` (the Create 3)
  on ``cmd_vel``, sent at the controller's rate (the Create 3 stops when commands stop coming);
  reliable, depth 10, as the bases subscribe.
* in: ``nav_msgs/Odometry`` on ``odom``, best effort (which matches reliable and best-effort
  publishers alike). Its pose is the robot's pose as it is (:class:`WheelFeedback` ``pose``):
  the base's odometry (wheels, often fused with its IMU) is better than anything re-integrated
  from its velocities here. A message with a non-finite pose or twist is counted and dropped.
* no odometry for the controller's ``feedback_timeout_s``: a stale fault whose reason names the
  topic; it clears when odometry comes again (the controller's recovery).
* optionally, the robot's own localization (AMCL's ``amcl_pose``, slam_toolbox's ``pose``):
  ``geometry_msgs/PoseWithCovarianceStamped``, turned into where the odometry frame lies in its map
  (:mod:`.map_pose`) and passed on with every odometry (``WheelFeedback.map_T_odom``); a pose
  less certain than the configured bound, malformed, or stamped where no odometry was is counted
  and dropped.
* an e-stop a ROS user can press: ``std_msgs/Bool`` true on ``estop`` engages the controller's
  latch, the same as the gateway's E-STOP; false is ignored and counted (a clear comes from the
  laptop, on ``driver/estop/clear``, as for every other e-stop source).

Topic names are relative to ``namespace`` (``/robot1`` makes ``/robot1/cmd_vel``), as ROS
remaps them.
"""

from __future__ import annotations

import math
import threading
import time
from collections import Counter
from collections.abc import Callable
from typing import Any

from ovamos.services.base_driver.hardware import HardwareDefaults, HardwareError, WheelFeedback
from ovamos.services.base_driver.ros2.config import Ros2BaseConfig
from ovamos.services.base_driver.ros2.map_pose import OdomHistory, map_T_odom, planar, std_of
from ovamos.shared.motion import Pose
from ovamos.shared.ros2 import Ros2Unavailable, node, stamp_s

__all__ = ["Ros2Hardware"]


class Ros2Hardware(HardwareDefaults):
    """The :class:`~ovamos.services.base_driver.hardware.BaseHardware` of a ROS 2 base (module docstring)."""

    name = "ros2"

    def __init__(self, config: Ros2BaseConfig, clock: Callable[[], float] = time.monotonic) -> None:
        self.config, self._clock = config, clock
        self._lock = threading.Lock()
        self._feedback: WheelFeedback | None = None
        self._counts: Counter[str] = Counter()
        self._pub: Any = None
        self._sub: Any = None
        self._make_twist: Callable[[float, float], Any] | None = None
        self._engage: Callable[[str, str], None] | None = None
        self._estop_sub: Any = None
        self._bump: Callable[[bool], None] | None = None
        self._bump_sub: Any = None
        self._linear = 0.0  # the last velocity sent: a bump while reversing is one behind
        self._history = OdomHistory()  # the base's odometry by its stamps, for the localization's
        self._map_T_odom: Pose | None = None
        self._map_pose_sub: Any = None

    def bind_estop(self, engage: Callable[[str, str], None]) -> None:
        """The controller's ``engage_estop(source, reason)``, for the ROS e-stop topic (the
        controller's optional hook)."""
        self._engage = engage

    def bind_bump(self, bump: Callable[[bool], None]) -> None:
        """The controller's ``bump(backward)``, for the ``bump`` topic (an optional hook)."""
        self._bump = bump

    def open(self) -> None:
        if self._pub is not None:
            return
        try:
            ros = node(self.config.network)
        except Ros2Unavailable as exc:
            raise HardwareError(str(exc)) from None
        from geometry_msgs.msg import Twist, TwistStamped
        from nav_msgs.msg import Odometry
        from rclpy.qos import qos_profile_sensor_data

        cfg = self.config
        if cfg.stamped:
            def make(linear: float, angular: float) -> Any:
                msg = TwistStamped()
                msg.header.stamp = ros.get_clock().now().to_msg()
                msg.header.frame_id = cfg.frame_id
                msg.twist.linear.x, msg.twist.angular.z = linear, angular
                return msg
        else:
            def make(linear: float, angular: float) -> Any:
                msg = Twist()
                msg.linear.x, msg.angular.z = linear, angular
                return msg
        self._make_twist = make
        self._pub = ros.create_publisher(TwistStamped if cfg.stamped else Twist, cfg.topic(cfg.cmd_vel), 10)
        self._sub = ros.create_subscription(Odometry, cfg.topic(cfg.odom), self._on_odom, qos_profile_sensor_data)
        if cfg.estop is not None and self._estop_sub is None:  # kept across re-opens: never deaf to it
            from std_msgs.msg import Bool
            self._estop_sub = ros.create_subscription(Bool, cfg.topic(cfg.estop), self._on_estop, 10)
        if cfg.bump is not None:
            from std_msgs.msg import Bool
            self._bump_sub = ros.create_subscription(Bool, cfg.topic(cfg.bump), self._on_bump, 10)
        if cfg.localization is not None:  # reliable, volatile: matches AMCL's latched and slam_toolbox's
            from geometry_msgs.msg import PoseWithCovarianceStamped
            self._map_pose_sub = ros.create_subscription(PoseWithCovarianceStamped, cfg.topic(cfg.localization),
                                                         self._on_map_pose, 10)

    def _on_estop(self, msg: Any) -> None:
        """On the executor's thread: the controller's latch is thread-safe and halts at once."""
        with self._lock:
            self._counts["ros2_estop" if msg.data else "ros2_estop_false_ignored"] += 1
        if msg.data and self._engage is not None:
            self._engage("ros2", f"std_msgs/Bool true on {self.config.topic(self.config.estop or '')}")

    def _on_bump(self, msg: Any) -> None:
        """On the executor's thread: the controller queues bumps without waiting."""
        if msg.data and self._bump is not None:
            with self._lock:
                self._counts["ros2_bumps"] += 1
                backward = self._linear < 0
            self._bump(backward)

    def _on_odom(self, msg: Any) -> None:
        """On the executor's thread: the newest odometry, handed over under the lock."""
        pose, t = planar(msg.pose.pose), msg.twist.twist
        if pose is None or not (math.isfinite(t.linear.x) and math.isfinite(t.angular.z)):
            with self._lock:
                self._counts["ros2_odom_malformed"] += 1
            return
        with self._lock:
            self._history.add(stamp_s(msg), pose)
            self._feedback = WheelFeedback(stamp=self._clock(), left_pos_rad=0.0, right_pos_rad=0.0, pose=pose,
                                           body_vel=(t.linear.x, t.angular.z), map_T_odom=self._map_T_odom)
            self._counts["ros2_odom"] += 1

    def _on_map_pose(self, msg: Any) -> None:
        """On the executor's thread: the robot's own localization, as ``map_T_odom`` from the
        odometry at its stamp (:mod:`.map_pose`); an uncertain one, or one the odometry history
        does not reach, is counted and not passed on."""
        cfg, pose = self.config, planar(msg.pose.pose)
        cov = msg.pose.covariance
        if pose is None or len(cov) != 36 or not all(math.isfinite(v) for v in (cov[0], cov[7], cov[35])):
            verdict = "malformed"
        elif (max(std_of(cov[0]), std_of(cov[7])) > cfg.localization_max_std_m
              or math.degrees(std_of(cov[35])) > cfg.localization_max_std_deg):
            verdict = "uncertain"
        else:
            with self._lock:
                odom = self._history.at(stamp_s(msg))
                if odom is not None:
                    self._map_T_odom = map_T_odom(pose, odom)
            verdict = "used" if odom is not None else "unmatched"
        with self._lock:
            self._counts[f"ros2_map_pose_{verdict}"] += 1

    def set_velocity(self, linear_m_s: float, angular_rad_s: float) -> None:
        if self._pub is None or self._make_twist is None:
            raise HardwareError("the ros2 base is not open")
        self._pub.publish(self._make_twist(linear_m_s, angular_rad_s))
        with self._lock:
            self._counts["ros2_cmd"] += 1
            self._linear = linear_m_s

    def halt(self) -> None:
        """A zero command, every cycle while halted (a base restarted meanwhile gets one too; a
        TurtleBot 3 keeps its last command for ever)."""
        if self._pub is None or self._make_twist is None:
            return
        self._pub.publish(self._make_twist(0.0, 0.0))
        with self._lock:
            self._counts["ros2_cmd"] += 1
            self._linear = 0.0

    def cmd_vel_subscribers(self) -> int:
        """How many subscribe to ``cmd_vel`` (the base's driver: none means commands go nowhere)."""
        return 0 if self._pub is None else int(self._pub.get_subscription_count())

    def feedback(self) -> WheelFeedback | None:
        with self._lock:
            return self._feedback

    def stale_reason(self, now: float) -> str:
        topic = self.config.topic(self.config.odom)
        with self._lock:
            fb = self._feedback
        if fb is None:
            return (f"no nav_msgs/Odometry on {topic} yet: is the robot's ROS driver up, with the same "
                    "ROS_DOMAIN_ID and namespace?")
        return f"no nav_msgs/Odometry on {topic} for {now - fb.stamp:.2f} s"

    def counters(self) -> dict[str, int]:
        with self._lock:
            return dict(self._counts)

    def close(self) -> None:
        """Drop the velocity publisher and the odometry and bump subscriptions; the e-stop
        subscription stays, so the ROS e-stop works while the controller recovers."""
        ros, self._make_twist = None, None
        for entity in (self._pub, self._sub, self._bump_sub, self._map_pose_sub):
            if entity is not None:
                ros = ros or node(self.config.network)
                (ros.destroy_publisher if entity is self._pub else ros.destroy_subscription)(entity)
        self._pub = self._sub = self._bump_sub = self._map_pose_sub = None
