"""The simulated robot moved by its wheels: SimRobot + a simulated base + the real base driver.

The base controller and its hardware interface run unchanged: ``odrive`` (CANSimple
frames on a python-can virtual bus, which only works within one process),
``kobuki`` and ``opencr`` (the real pyserial / dynamixel-sdk clients on a
pseudo-terminal, against a simulated device that speaks the protocol byte for
byte). The simulated device's wheel motion drives :meth:`SimRobot.drive`, so the
true pose follows what the motors did, and the driver's odometry comes from the
encoders, as on the robot. A blocked move stalls the wheels and trips the
driver's bumper input.

Given a :class:`~ovamos.shared.simtime.SimClock`, the same parts run in simulated time (the search
benchmark's ``--base``): no thread of their own, the serial bases on a
:class:`~ovamos.shared.simtime.MemoryLine` in place of the pty, the clock running the device's loop at
its period and the controller's tick at ``control_hz``, and :meth:`_WheelDriven.run_command`
running the clock until a command completes.
"""

from __future__ import annotations

import math
import threading
import time
from abc import ABC, abstractmethod
from collections.abc import Callable
from contextlib import ExitStack
from typing import Literal

from ovamos.services.base_driver.config import DriverConfig
from ovamos.services.base_driver.controller import BaseDriver
from ovamos.services.base_driver.kobuki.client import KobukiHardware
from ovamos.services.base_driver.kobuki.sim import SimKobuki
from ovamos.services.base_driver.odrive.client import ODriveCanHardware
from ovamos.services.base_driver.odrive.config import CanConfig, SimAxisConfig
from ovamos.services.base_driver.odrive.sim import SimODrives
from ovamos.services.base_driver.opencr.client import OpenCRHardware
from ovamos.services.base_driver.opencr.sim import SimOpenCR, line_port_handler
from ovamos.services.sim.robot import MotionConfig, SimRobot
from ovamos.shared.messages import DriverMode, PlanCommand
from ovamos.shared.motion import Pose
from ovamos.shared.simtime import SimClock

Motion = Literal["kinematic", "odrive", "kobuki", "opencr"]
CONTINUOUS_BASE: Motion = "kobuki"
"""The simulated robot's wheels where continuous motion is asked of a kinematic one: a TurtleBot 2's."""
"""How the simulated robot moves (the sim service's docstring)."""
ODRIVE_LOOP_S = 0.005  # the simulated ODrives' loop in simulated time (their thread's longest wait)


class _WheelDriven(ABC):
    """The true pose of a robot moved by its simulated wheels, and the driver told of bumps."""

    driver: BaseDriver

    def __init__(self, robot: SimRobot, clock: SimClock | None = None) -> None:
        self.robot = robot
        self.clock = clock  # simulated time, or None: real time with threads
        self._lock = threading.Lock()

    @property
    def _now(self) -> Callable[[], float]:
        return self.clock if self.clock is not None else time.monotonic

    def _schedule_controller(self) -> None:
        assert self.clock is not None
        self.clock.every(1.0 / self.driver.config.control_hz, self.driver.tick)

    def wait_ready(self) -> float:
        """Simulated time: run until the base is enabled; the simulated seconds it took."""
        assert self.clock is not None, "only in simulated time"
        c = self.driver.config
        return self.clock.run_until(lambda: self.driver.state().mode is DriverMode.READY,
                                    c.enable_timeout_s + c.recover_every_s, 1.0 / c.control_hz, "base ready")

    def run_command(self, command: PlanCommand) -> str:
        """Simulated time: submit ``command`` and run until the controller completes it; its outcome
        (``rejected`` when it was not accepted)."""
        assert self.clock is not None, "only in simulated time"
        if self.driver.submit(command) != "accepted":
            return "rejected"
        c = self.driver.config
        self.clock.run_until(lambda: self.driver.state().last_completed >= command.action_id,
                             c.primitive_timeout_s + 1.0, 1.0 / c.control_hz, f"command {command.action_id}")
        return str(self.driver.state().last_outcome)

    @property
    def pose(self) -> Pose:
        """The true pose (what the camera sees from), not the odometry."""
        with self._lock:
            return self.robot.pose

    def odometry(self) -> Pose:
        """Where the driver's odometry (its encoders, integrated) has the robot."""
        odom = self.driver.odometry()
        return Pose(x=odom.x, y=odom.y, yaw=odom.yaw)

    def _move(self, left_rad_s: float, right_rad_s: float, dt: float) -> bool:
        """Move the robot by the wheels' rotation this step; False (a stall) when blocked."""
        with self._lock:
            moved = self.robot.drive(left_rad_s, right_rad_s, dt, stall=True)
        if not moved:
            self.driver.bump(backward=left_rad_s + right_rad_s < 0)
        return moved

    def __enter__(self) -> _WheelDriven:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    @abstractmethod
    def start(self) -> _WheelDriven: ...

    @abstractmethod
    def stop(self) -> None: ...


class WheeledSimRobot(_WheelDriven):
    """Owns the simulated axes and the driver for ``robot``; geometry and primitive sizes come
    from the robot's :class:`~ovamos.services.sim.robot.MotionConfig` so both agree."""

    def __init__(self, robot: SimRobot, driver: DriverConfig | None = None,
                 axes: SimAxisConfig | None = None, clock: SimClock | None = None) -> None:
        super().__init__(robot, clock)
        base = driver or DriverConfig()
        od = base.odrive
        self._directions = {od.left.node_id: od.left.direction, od.right.node_id: od.right.direction}
        self._left, self._right = od.left.node_id, od.right.node_id
        self.odrives = SimODrives(self._directions, config=axes, physics=self._physics, clock=self._now)
        m = robot.config
        self.config = base.model_copy(update={
            "odrive": od.model_copy(update={"can": CanConfig(interface="virtual", channel=self.odrives.channel)}),
            "wheel_radius_m": m.wheel_radius_m, "track_width_m": m.track_width_m,
            "forward_m": m.forward_m, "turn_deg": m.turn_deg, "initial_pose": robot.pose})
        hardware = ODriveCanHardware(self.config, self.odrives.open_driver_bus, clock=self._now,
                                     polled=clock is not None)
        self.driver = BaseDriver(self.config, hardware, clock=self._now)

    def start(self) -> WheeledSimRobot:
        if self.clock is None:
            self.odrives.start()
            self.driver.start()
            return self
        self.clock.every(ODRIVE_LOOP_S, self.odrives.tick)
        self._schedule_controller()
        return self

    def stop(self) -> None:
        self.driver.stop()
        self.odrives.stop()

    def _physics(self, dt: float, deltas: dict[int, float]) -> bool:
        if deltas[self._left] == 0.0 and deltas[self._right] == 0.0:
            return True
        left = 2 * math.pi * self._directions[self._left] * deltas[self._left] / dt
        right = 2 * math.pi * self._directions[self._right] * deltas[self._right] / dt
        return self._move(left, right, dt)


TURTLEBOTS = ("kobuki", "opencr")


class SerialSimRobot(_WheelDriven):
    """A TurtleBot base simulated on a pseudo-terminal (a Kobuki or an OpenCR board) driven by the
    real controller through its real serial client. ``robot``'s geometry must be the base's
    (``DriverConfig.fixed_wheels``): the sim service sets it."""

    def __init__(self, robot: SimRobot, hardware: str, driver: DriverConfig | None = None,
                 clock: SimClock | None = None) -> None:
        super().__init__(robot, clock)
        self.hardware = hardware
        m = robot.config
        base = driver or DriverConfig()
        if hardware == "kobuki":
            self.device: SimKobuki | SimOpenCR = SimKobuki(wheel_radius_m=m.wheel_radius_m,
                                                           wheel_base_m=m.track_width_m,
                                                           physics=self._metres, clock=self._now)
        else:
            self.device = SimOpenCR(base.opencr.model, physics=self._radians, clock=self._now)
        self._base = base
        self._device_open = ExitStack()
        self.driver = None  # type: ignore[assignment]  # built in start(): the port exists then
        self.config: DriverConfig | None = None

    def start(self) -> SerialSimRobot:
        if self.clock is None:
            self._device_open.enter_context(self.device)  # started now, stopped by stop()
            port = self.device.port if isinstance(self.device, SimKobuki) else self.device.path
        else:
            line = self.device.memory_line()
            port = line.name
        m, base = self.robot.config, self._base
        section = {"kobuki": base.kobuki, "opencr": base.opencr}[self.hardware].model_copy(update={"port": port})
        # validated (model_copy is not): the wheels must be the hardware's
        self.config = DriverConfig.model_validate({
            **base.model_dump(), "hardware": self.hardware, self.hardware: section.model_dump(),
            "wheel_radius_m": m.wheel_radius_m, "track_width_m": m.track_width_m,
            "forward_m": m.forward_m, "turn_deg": m.turn_deg, "initial_pose": self.robot.pose.model_dump()})
        if self.clock is None:
            self.driver = BaseDriver(self.config).start()
            return self
        clock = self.clock
        if isinstance(self.device, SimKobuki):
            hardware: KobukiHardware | OpenCRHardware = KobukiHardware(
                self.config.kobuki, clock=clock, sleep=clock.sleep, open_port=lambda: line)
            clock.every(self.device.period_s, self.device.firmware_tick)
        else:
            hardware = OpenCRHardware(self.config.opencr, clock=clock, port_handler=line_port_handler(line))
            device = self.device
            clock.every(device.step_s, lambda: device.step(device.step_s, clock()))
        self.driver = BaseDriver(self.config, hardware, clock=clock)
        self._schedule_controller()
        return self

    def stop(self) -> None:
        if self.driver is not None:
            self.driver.stop()
        self._device_open.close()

    def _metres(self, dt: float, left_m: float, right_m: float) -> bool:
        r = self.robot.config.wheel_radius_m
        return self._move(left_m / r / dt, right_m / r / dt, dt)

    def _radians(self, dt: float, left_rad: float, right_rad: float) -> bool:
        return self._move(left_rad / dt, right_rad / dt, dt)


def base_motion(motion: MotionConfig, base: str, driver: DriverConfig) -> MotionConfig:
    """``motion`` with the wheels a TurtleBot ``base`` fixes (a Kobuki's, the configured TurtleBot 3
    model's), so the simulated robot and the driver agree; as it is for any other base."""
    if base not in TURTLEBOTS:
        return motion
    fixed = driver.model_copy(update={"hardware": base}).fixed_wheels()
    assert fixed is not None
    radius, track, _ = fixed
    return motion.model_copy(update={"wheel_radius_m": radius, "track_width_m": track})


def frame_pose(robot: SimRobot, wheels: _WheelDriven | None) -> Pose:
    """Where the simulated camera poses a frame: by odometry, as a camera service does (the
    kinematic base's, or the driver's of a wheeled one). With ``ideal`` odometry errors at the true
    pose, which odometry then is: a wheeled driver's encoder ticks would round it, and runs from
    before odometry errors existed stay as they were."""
    return robot.odom if wheels is None or robot.slip is None else wheels.odometry()


def wheeled(robot: SimRobot, base: str, driver: DriverConfig | None = None, axes: SimAxisConfig | None = None,
            clock: SimClock | None = None) -> SerialSimRobot | WheeledSimRobot:
    """What moves ``robot`` on the wheeled ``base`` (not started; ``axes``: the ODrives' only)."""
    if base in TURTLEBOTS:
        return SerialSimRobot(robot, base, driver, clock)
    return WheeledSimRobot(robot, driver, axes, clock)

