"""The simulated robot service ("sim"): camera frames from the true pose, and a base that moves.

Frames are posed by odometry, as a camera service poses them; the robot's odometry errs as
``robot.odometry`` says (ideal by default: odometry is the true pose).

It stands in for the robot's camera and base driver at once, speaking the
base driver's keys (it *is* a :class:`BaseDriverService` whose base is
simulated): ``plan/command`` and ``driver/estop`` in, ``odom``,
``driver/state`` and ``sensors/rgbd`` out. The scene is a scene file or an
episode's (``make_episode(seed, index)``, the same one the simulated
perception backend reads).

``motion``:

* ``kinematic``: ideal, a primitive is executed exactly and completes at once
  (deterministic lock-step runs, fast demos); odometry is the true pose;
* ``odrive``: the real driver core with simulated ODrive axes on a virtual CAN
  bus in this process; the wheels move the robot, odometry comes from the
  encoders (it starts at the start pose, so it shares the map's world frame);
* ``kobuki`` / ``opencr``: the same with a TurtleBot 2 / TurtleBot 3 base: the
  real pyserial / dynamixel-sdk client on a pseudo-terminal against a simulated
  Kobuki / OpenCR board; the robot takes that base's wheels and track.

Every frame carries the base's odometry session (a restarted sim starts a new
one, its robot back at the start pose) and ``after_action``, the last command
completed when it was rendered (the state is read *before* the frame is
rendered, so a frame never claims a completion it does not show). Lock-step (default): after each
completed command one frame is rendered and published, so the planner's wait
for a map with ``after_action`` >= its command ends with exactly that frame.
A frame is published at start-up too, and the latest one is re-published
(same seq) every ``republish_s`` while idle, for a subscriber that joined
late. Free-running: a new frame every ``1 / frame_hz`` s.

The renderer owns an OpenGL context, so it is created and used only on the
service's main thread (``start`` and ``tick``).
"""

from __future__ import annotations

import math
import time
from typing import Any

from ovamos.services.base_driver.service import Base, BaseDriverService
from ovamos.services.sim.config import SimServiceConfig
from ovamos.services.sim.kinematic import KinematicBase
from ovamos.services.sim.robot import SimRobot
from ovamos.services.sim.wheels import SerialSimRobot, WheeledSimRobot, base_motion, frame_pose, wheeled
from ovamos.shared.bus import BusCore
from ovamos.shared.messages import RgbdFrame
from ovamos.shared.motion import Pose
from ovamos.world.render import SceneRenderer


class SimRobotService(BaseDriverService):
    name = "sim"
    Config = SimServiceConfig
    config: SimServiceConfig

    def __init__(self, bus: BusCore, config: SimServiceConfig) -> None:
        super().__init__(bus, config)
        self._wheels: WheeledSimRobot | SerialSimRobot | None = None
        self._kinematic: KinematicBase | None = None
        self._frame: RgbdFrame | None = None
        self._frame_at = -float("inf")
        self._next_seq = 0

    def make_base(self) -> Base:
        c = self.config
        if c.scene_file is not None:
            from ovamos.world.evaluator import GroundTruth
            from ovamos.world.scene import Scene
            scene = Scene.load(c.scene_file)
            truth, start = GroundTruth(scene), c.start
        else:
            from ovamos.world.episodes import make_episode
            spec, scene, truth = make_episode(c.episode_seed, c.episode_index)
            start = c.start or spec.start
        assert start is not None
        self.renderer = SceneRenderer(scene, c.width, c.height)
        robot = SimRobot(start, truth.is_free, base_motion(c.robot, c.motion, c.driver))
        if c.motion == "kinematic":
            self._kinematic = KinematicBase(robot)
            return self._kinematic
        self._wheels = wheeled(robot, c.motion, c.driver, c.odrive).start()
        return self._wheels.driver

    def start(self) -> None:
        super().start()
        self._publish_frame(self._render(self.base.state().last_completed))

    def _pose(self) -> Pose:
        return self._wheels.pose if self._wheels is not None else self.base_robot.pose

    @property
    def base_robot(self) -> SimRobot:
        assert self._kinematic is not None
        return self._kinematic.robot

    def _render(self, after_action: int) -> RgbdFrame:
        """A frame from where the robot truly is, posed where its odometry says it is."""
        p = self._pose()
        robot = self._wheels.robot if self._wheels is not None else self.base_robot
        frame = self.renderer.render(p.x, p.y, p.yaw, seq=self._next_seq, stamp=time.time(),
                                     after_action=after_action, odom_session=self.base.odom_session,
                                     posed_at=frame_pose(robot, self._wheels))
        self._next_seq += 1
        return frame

    def _publish_frame(self, frame: RgbdFrame) -> None:
        self.out["rgbd"].put(frame)
        self._frame, self._frame_at = frame, time.monotonic()

    def tick(self) -> None:
        if self._kinematic is not None:
            self._kinematic.execute()
        state = self.base.state()  # before rendering: the frame is then newer than its completion
        now = time.monotonic()
        assert self._frame is not None
        if not self.config.lock_step:
            if now - self._frame_at >= 1.0 / self.config.frame_hz:
                self._publish_frame(self._render(state.last_completed))
        elif state.last_completed > self._frame.after_action:
            self._log_drift(state.last_completed)
            self._publish_frame(self._render(state.last_completed))
        elif now - self._frame_at >= self.config.republish_s:
            self._publish_frame(self._frame)  # same seq, for late subscribers
        self.publish(state)

    def _log_drift(self, action_id: int) -> None:
        """Where the simulator has the robot after a command, and where its odometry does: what a
        rehearsal with odometry errors drifted by (only the simulator knows the first)."""
        robot = self._wheels.robot if self._wheels is not None else self.base_robot
        if robot.slip is None:
            return
        true, odom = self._pose(), frame_pose(robot, self._wheels)
        self.log.info("after command %d: truly at (%.3f, %.3f, %.1f deg), odometry says (%.3f, %.3f, %.1f deg)",
                      action_id, true.x, true.y, math.degrees(true.yaw), odom.x, odom.y, math.degrees(odom.yaw))

    def info(self) -> dict[str, Any]:
        info = dict(super().info())
        info.update(motion=self.config.motion, frame_seq=None if self._frame is None else self._frame.seq)
        return info

    def release(self) -> None:
        if self._wheels is not None:
            self._wheels.stop()
        if hasattr(self, "renderer"):
            self.renderer.close()

