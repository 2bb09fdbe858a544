"""The simulated robot behind ROS 2 topics, as a ROS 2 robot's own bringup would offer it.

For rehearsing a ROS 2 setup (``ovamos sim ros2``, and ``ovamos demo --base ros2``): it takes
velocity on ``cmd_vel`` (``TwistStamped`` as a TurtleBot 3 on Jazzy, or ``Twist`` as a Create 3),
moves the episode's robot by it through the scene's free space, and publishes ``nav_msgs/Odometry``
on ``odom`` and what the robot's camera sees on the ``realsense2_camera`` topics: colour (rgb8),
depth aligned to it (32FC1 metres) and the colour camera's info, plus the simulator's instance-id
image (32SC1, :data:`INSTANCE_IDS_TOPIC`), which the simulated perception backend reads in place of
a detector. The camera images of one frame share one stamp, the time its pose was taken.

The base behaves as a Create 3: velocity is applied at once (the controller ramps it) and held
until commands stop for ``command_timeout_s``, then it stops by itself; a move into an obstacle
leaves the robot where it touched and says so on ``bump`` (``std_msgs/Bool``, as a bridge of a
Create 3's hazard detection would: the driver ends the move blocked). Odometry starts at the true pose
in the scene's frame, so the map and the simulated perception agree on where things are, and is
the true pose unless the robot's odometry errs (``robot.odometry``). When the base names a
localization topic (``base.localization``), the true pose is published there in the ``map`` frame
(the scene's), stamped as the odometry of the same instant: a stand-in for AMCL, without AMCL's
own error.

One process, one ROS node (:func:`ovamos.shared.ros2.node`), loopback-only DDS unless told otherwise. The
renderer owns an OpenGL context, so the loop that moves the robot and renders runs on the main
thread; ROS callbacks only hand the newest command over under a lock.
"""

from __future__ import annotations

import logging
import math
import signal
import threading
import time
from collections import Counter
from collections.abc import Callable
from typing import Any

import numpy as np
from pydantic import Field

from ovamos.services.base_driver.kinematics import Geometry
from ovamos.services.base_driver.ros2.config import Ros2BaseConfig
from ovamos.services.camera.ros2 import Ros2CameraConfig
from ovamos.services.sim.robot import MotionConfig, SimRobot
from ovamos.shared.config import StrictModel
from ovamos.shared.motion import Pose
from ovamos.shared.ros2 import node
from ovamos.world.episodes import make_episode
from ovamos.world.render import SceneRenderer

__all__ = ["INSTANCE_IDS_TOPIC", "MAP_POSE_TOPIC", "Ros2SimRobotConfig", "Ros2SimRobot"]

log = logging.getLogger("ovamos.sim.ros2")
INSTANCE_IDS_TOPIC = "/camera/camera/instance_ids"
"""Where the simulated camera's instance-id image goes (no real camera has one)."""
CAMERA = Ros2CameraConfig(instance_ids=INSTANCE_IDS_TOPIC)  # the topics: realsense2_camera's
BUMP_TOPIC = "bump"
"""Where the simulated robot says it touched something (``Ros2BaseConfig.bump``)."""
MAP_POSE_TOPIC = "amcl_pose"
"""Where the simulated robot's stand-in for AMCL publishes, when asked (``Ros2BaseConfig.localization``)."""
BUMP_EVERY_S = 0.1  # while pushing against an obstacle, the report is repeated this often
FRAME_IDS = {"map": "map", "odom": "odom", "base": "base_link", "camera": "camera_color_optical_frame"}
MAP_POSE_STD_M, MAP_POSE_STD_DEG = 0.05, 2.0  # the covariance its stand-in for AMCL claims


def _header(msg: Any, frame_id: str, stamp: Any) -> Any:
    msg.header.stamp, msg.header.frame_id = stamp, frame_id
    return msg


def _set_pose(msg: Any, pose: Pose) -> None:
    """A planar pose into a ``geometry_msgs/Pose``."""
    msg.position.x, msg.position.y = pose.x, pose.y
    msg.orientation.z, msg.orientation.w = math.sin(pose.yaw / 2), math.cos(pose.yaw / 2)


class Ros2SimRobotConfig(StrictModel):
    """Which episode's robot, and how it talks ROS."""

    episode_seed: int = 0
    episode_index: int = Field(default=0, ge=0)
    width: int = Field(default=320, ge=16)
    height: int = Field(default=240, ge=16)
    frame_hz: float = Field(default=10.0, gt=0, description="camera frames a second")
    odom_hz: float = Field(default=50.0, gt=0, description="odometry messages a second")
    localization_hz: float = Field(default=2.0, gt=0, description="poses a second on the base's localization "
                                   "topic (when it has one): the true pose, as a stand-in for AMCL")
    physics_hz: float = Field(default=100.0, gt=0, description="motion integration steps a second")
    command_timeout_s: float = Field(default=0.5, gt=0, description="no command for this long: it stops "
                                     "(a Create 3's own timeout)")
    base: Ros2BaseConfig = Field(default_factory=lambda: Ros2BaseConfig(bump=BUMP_TOPIC),
                                 description="the base's topics, as the ros2 base driver is told them "
                                 "(with bump: where contact is reported)")
    robot: MotionConfig = Field(default_factory=MotionConfig, description="wheel geometry and how its "
                                "odometry errs (odometry.odometry: ideal, realistic, hard)")


class Ros2SimRobot:
    """The loop of :mod:`ovamos.services.sim.ros2_robot`: built on the main thread, :meth:`run` until
    :meth:`stop`."""

    def __init__(self, config: Ros2SimRobotConfig) -> None:
        self.config = config
        spec, scene, truth = make_episode(config.episode_seed, config.episode_index)
        self.robot = SimRobot(spec.start, truth.is_free, config.robot)
        self.geometry = Geometry(self.robot.config.wheel_radius_m, self.robot.config.track_width_m)
        self.renderer = SceneRenderer(scene, config.width, config.height)
        self._lock = threading.Lock()
        self._command = (0.0, 0.0, -math.inf)  # linear, angular, when (monotonic)
        self._stop = threading.Event()
        self.counters: Counter[str] = Counter()
        self._ros: Any = None
        self._say_bump: Callable[[], None] | None = None
        self._bumped_at = -math.inf
        self._map_pose: Any = None

    # -- ROS ---------------------------------------------------------------------------------
    def open(self) -> None:
        from geometry_msgs.msg import Twist, TwistStamped
        from nav_msgs.msg import Odometry
        from rclpy.qos import qos_profile_sensor_data
        from sensor_msgs.msg import CameraInfo, Image

        base = self.config.base
        ros = self._ros = node(base.network)
        ros.create_subscription(TwistStamped if base.stamped else Twist, base.topic(base.cmd_vel), self._on_cmd, 10)
        self._odom = ros.create_publisher(Odometry, base.topic(base.odom), 10)
        self._images = {topic: ros.create_publisher(Image, topic, qos_profile_sensor_data)
                        for topic in (CAMERA.color, CAMERA.depth, INSTANCE_IDS_TOPIC)}
        self._info = ros.create_publisher(CameraInfo, CAMERA.info, qos_profile_sensor_data)
        if base.bump is not None:
            from std_msgs.msg import Bool
            bump = ros.create_publisher(Bool, base.topic(base.bump), 10)
            self._say_bump = lambda: bump.publish(Bool(data=True))
        if base.localization is not None:
            from geometry_msgs.msg import PoseWithCovarianceStamped
            self._map_pose = ros.create_publisher(PoseWithCovarianceStamped, base.topic(base.localization), 10)

    def _on_cmd(self, msg: Any) -> None:
        twist = msg.twist if self.config.base.stamped else msg
        linear, angular = float(twist.linear.x), float(twist.angular.z)
        if not (math.isfinite(linear) and math.isfinite(angular)):
            self.counters["cmd_vel_malformed"] += 1
            return
        with self._lock:
            self._command = (linear, angular, time.monotonic())
        self.counters["cmd_vel"] += 1

    # -- the loop ----------------------------------------------------------------------------
    def run(self) -> None:
        """Move, publish odometry and frames at their rates until :meth:`stop`."""
        c = self.config
        step, next_odom, next_frame, next_located = 1.0 / c.physics_hz, 0.0, 0.0, 0.0
        last = time.monotonic()
        while not self._stop.is_set():
            now = time.monotonic()
            self._move(now, now - last)
            last = now
            if now >= next_odom:
                localized = now >= next_located
                self._publish_odom(localized)
                next_odom = now + 1.0 / c.odom_hz
                next_located = now + 1.0 / c.localization_hz if localized else next_located
            if now >= next_frame:
                self._publish_frame()
                next_frame = now + 1.0 / c.frame_hz
            self._stop.wait(max(0.0, step - (time.monotonic() - now)))

    def stop(self, *_: object) -> None:
        self._stop.set()

    def _velocity(self, now: float) -> tuple[float, float]:
        with self._lock:
            linear, angular, at = self._command
        if now - at > self.config.command_timeout_s:
            if linear or angular:
                log.info("no cmd_vel for %.1f s: stopping", self.config.command_timeout_s)
                with self._lock:
                    self._command = (0.0, 0.0, at)
                self.counters["command_timeouts"] += 1
            return 0.0, 0.0
        return linear, angular

    def _move(self, now: float, dt: float) -> None:
        linear, angular = self._velocity(now)
        if not (linear or angular) or dt <= 0:
            return
        left, right = (2 * math.pi * w for w in self.geometry.wheels_rev_s(linear, angular))
        with self._lock:
            moved = self.robot.drive(left, right, min(dt, 0.1))  # a stalled loop does not jump
        if moved:
            return
        self.counters["blocked"] += 1
        if self._say_bump is not None and now - self._bumped_at >= BUMP_EVERY_S:
            self._say_bump()
            self._bumped_at = now

    def pose(self) -> tuple[Pose, float, float]:
        """The true pose, with the velocity it moves at."""
        linear, angular = self._velocity(time.monotonic())
        with self._lock:
            return self.robot.pose, linear, angular

    def _publish_odom(self, localized: bool) -> None:
        """Odometry; with ``localized``, the true pose on the localization topic too, with the same
        stamp (as AMCL stamps its pose with the scan it matched)."""
        from nav_msgs.msg import Odometry

        _, linear, angular = self.pose()
        with self._lock:
            pose, true = self.robot.odom, self.robot.pose  # what the wheels report, where it is
        stamp = self._ros.get_clock().now().to_msg()
        msg = _header(Odometry(), FRAME_IDS["odom"], stamp)
        msg.child_frame_id = FRAME_IDS["base"]
        _set_pose(msg.pose.pose, pose)
        msg.twist.twist.linear.x, msg.twist.twist.angular.z = linear, angular
        self._odom.publish(msg)
        if localized and self._map_pose is not None:
            from geometry_msgs.msg import PoseWithCovarianceStamped

            located = _header(PoseWithCovarianceStamped(), FRAME_IDS["map"], stamp)
            _set_pose(located.pose.pose, true)
            located.pose.covariance[0] = located.pose.covariance[7] = MAP_POSE_STD_M ** 2
            located.pose.covariance[35] = math.radians(MAP_POSE_STD_DEG) ** 2
            self._map_pose.publish(located)

    def _publish_frame(self) -> None:
        from sensor_msgs.msg import CameraInfo, Image

        stamp = self._ros.get_clock().now().to_msg()
        pose, _, _ = self.pose()  # taken with the stamp: the camera core poses the frame at it
        frame = self.renderer.render(pose.x, pose.y, pose.yaw)
        h, w = frame.depth.shape
        layers = {CAMERA.color: ("rgb8", frame.rgb), CAMERA.depth: ("32FC1", frame.depth.astype("<f4")),
                  INSTANCE_IDS_TOPIC: ("32SC1", frame.instance_ids.astype("<i4"))}
        for topic, (encoding, pixels) in layers.items():
            data = np.ascontiguousarray(pixels)
            self._images[topic].publish(_header(
                Image(height=h, width=w, encoding=encoding, step=data.nbytes // h, data=data.tobytes()),
                FRAME_IDS["camera"], stamp))
        k = frame.intrinsics
        info = CameraInfo(height=h, width=w, distortion_model="plumb_bob", d=[0.0] * 5,
                          k=[k.fx, 0.0, k.cx, 0.0, k.fy, k.cy, 0.0, 0.0, 1.0],
                          p=[k.fx, 0.0, k.cx, 0.0, 0.0, k.fy, k.cy, 0.0, 0.0, 0.0, 1.0, 0.0])
        self._info.publish(_header(info, FRAME_IDS["camera"], stamp))
        self.counters["frames"] += 1

    def close(self) -> None:
        self.renderer.close()


def main(config: Ros2SimRobotConfig) -> None:
    """Run the simulated robot until SIGINT / SIGTERM (``ovamos sim ros2``)."""
    robot = Ros2SimRobot(config)
    signal.signal(signal.SIGTERM, robot.stop)
    signal.signal(signal.SIGINT, robot.stop)
    try:
        robot.open()
        start = robot.robot.pose
        base = config.base
        log.info("episode %d-%d: the robot at (%.2f, %.2f, %.0f deg); %s (%s) in, %s and the camera on %s out",
                 config.episode_seed, config.episode_index, start.x, start.y, math.degrees(start.yaw),
                 base.topic(base.cmd_vel), "TwistStamped" if base.stamped else "Twist", base.topic(base.odom),
                 CAMERA.color.rsplit("/", 2)[0])
        robot.run()
    finally:
        log.info("stopped: %s", dict(robot.counters))
        robot.close()

