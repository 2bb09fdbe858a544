"""The simulated robot moved by its wheels: SimRobot + simulated ODrive axes + the real base driver.

The base controller and its ``odrive_can`` hardware interface run unchanged (CANSimple frames on a python-can virtual bus,
which only works within one process); the simulated axes' wheel motion drives
:meth:`SimRobot.drive`, so the true pose follows what the motors did, and the
driver's odometry comes from the encoder estimates, as on the robot. A blocked
move stalls the wheels and trips the driver's bumper input.
"""

from __future__ import annotations

import math
import threading

from services.base_driver.config import CanConfig, DriverConfig
from services.base_driver.controller import BaseDriver
from services.base_driver.odrive_can import ODriveCanHardware
from services.base_driver.odrive_sim import SimAxisConfig, SimODrives
from services.sim.robot import SimRobot
from shared.motion import Pose


class WheeledSimRobot:
    """Owns the simulated axes and the driver for ``robot``; geometry and primitive sizes come
    from the robot's :class:`~services.sim.robot.MotionConfig` so both agree."""

    def __init__(self, robot: SimRobot, driver: DriverConfig | None = None,
                 axes: SimAxisConfig | None = None) -> None:
        self.robot = robot
        self._lock = threading.Lock()
        base = driver or DriverConfig()
        od = base.odrive
        self._directions = {od.left.node_id: od.left.direction, od.right.node_id: od.right.direction}
        self._left, self._right = od.left.node_id, od.right.node_id
        self.odrives = SimODrives(self._directions, config=axes, physics=self._physics)
        m = robot.config
        self.config = base.model_copy(update={
            "odrive": od.model_copy(update={"can": CanConfig(interface="virtual", channel=self.odrives.channel)}),
            "wheel_radius_m": m.wheel_radius_m, "track_width_m": m.track_width_m,
            "forward_m": m.forward_m, "turn_deg": m.turn_deg, "initial_pose": robot.pose})
        self.driver = BaseDriver(self.config, ODriveCanHardware(self.config, self.odrives.open_driver_bus))

    def start(self) -> WheeledSimRobot:
        self.odrives.start()
        self.driver.start()
        return self

    def stop(self) -> None:
        self.driver.stop()
        self.odrives.stop()

    def __enter__(self) -> WheeledSimRobot:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    @property
    def pose(self) -> Pose:
        """The true pose (what the camera sees from), not the odometry."""
        with self._lock:
            return self.robot.pose

    def _physics(self, dt: float, deltas: dict[int, float]) -> bool:
        """Move the robot by the wheels' rotation this step; False (a stall) when blocked."""
        if deltas[self._left] == 0.0 and deltas[self._right] == 0.0:
            return True
        left = 2 * math.pi * self._directions[self._left] * deltas[self._left] / dt
        right = 2 * math.pi * self._directions[self._right] * deltas[self._right] / dt
        with self._lock:
            before = self.robot.pose
            moved = self.robot.drive(left, right, dt)
            if not moved:
                self.robot.pose = before
        if not moved:
            self.driver.bump()
        return moved
