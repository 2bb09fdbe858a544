"""What the base controller needs of a base's hardware, whatever bus it is on (ros2_control's split).

A hardware interface sends body velocity setpoints and reports encoders, health
and safety sensors; it keeps no policy. Everything that is not about a bus
(primitives closed-loop on odometry, deadman, e-stop latch, limits and ramps,
the fault / recover state machine, odometry, ``driver/state``) is the
controller's, so every base gets it the same way: ODrive CANSimple over
python-can (a custom CAN base), Kobuki over serial (TurtleBot 2), OpenCR over
Dynamixel Protocol 2.0 (TurtleBot 3).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Protocol

from ovamos.shared.motion import Pose

__all__ = ["HardwareError", "WheelFeedback", "BaseHardware"]


class HardwareError(RuntimeError):
    """The base cannot be reached or refuses (port missing, unplugged, no answer)."""


@dataclass(frozen=True)
class WheelFeedback:
    """One feedback message of the base, in SI units, wheel forward positive.

    Positions are cumulative (unwrapped: a 16-bit tick counter's wrap is the
    interface's to undo). ``stamp`` is this host's ``time.monotonic()`` when the
    feedback arrived: the controller calls feedback older than its limit stale.

    A base that keeps its own odometry and reports no wheel positions (a ROS 2 base's
    ``nav_msgs/Odometry``, fused with its IMU) sets ``pose`` (in its odometry frame) and
    ``body_vel`` (m/s, rad/s) instead: the controller then takes that pose as the robot's, as
    it is, and integrates nothing (wheel positions are ignored: pass 0.0), since integrating
    the base's velocities again would only add error to a pose the base already has.
    """

    stamp: float
    left_pos_rad: float
    right_pos_rad: float
    left_vel_rad_s: float | None = None   # None: the base does not report it (derived from positions)
    right_vel_rad_s: float | None = None
    bumpers: tuple[str, ...] = ()         # pressed now: e.g. "left", "centre", "right"
    wheel_drops: tuple[str, ...] = ()     # wheels off the ground now: "left", "right"
    cliffs: tuple[str, ...] = ()          # cliff sensors seeing a drop now: "left", "centre", "right"
    faults: tuple[str, ...] = ()          # errors the device itself reports
    extra: dict[str, float] = field(default_factory=dict)  # e.g. battery voltage, for status
    pose: Pose | None = None              # the base's own odometry, when it keeps one (see above)
    body_vel: tuple[float, float] | None = None  # with ``pose``: its velocity, m/s and rad/s
    map_T_odom: Pose | None = None        # the base's own localization of its odometry frame (AMCL)


class BaseHardware(Protocol):
    """A base's bus. The controller serialises its calls under its own lock (its control thread;
    an e-stop calls :meth:`halt` from the caller's thread so it happens at once); an interface
    that reads on a thread of its own hands over the newest feedback under its own lock.
    :meth:`halt` is called every control cycle while the base is halted: keep it cheap. Positions
    must stay continuous across a re-open (the controller's odometry does not re-baseline).

    The capabilities not every base has (:meth:`estop`, :meth:`stale_reason`, :meth:`bind_estop`,
    :meth:`bind_bump`) are part of the interface too: an implementation states what it has by
    overriding :class:`HardwareDefaults`' answers for a base without them, rather than the
    controller probing it for methods."""

    name: str

    def open(self) -> None:
        """Connect (again, after a failure). Raises :class:`HardwareError`."""

    def set_velocity(self, linear_m_s: float, angular_rad_s: float) -> None:
        """Body velocity setpoint (already limited and ramped by the controller). Raises
        :class:`HardwareError` when it cannot be sent."""

    def halt(self) -> None:
        """Stop the wheels at once and let them go (motors off / idle where the base can):
        e-stop and faults. Never raises; best effort on a dead bus."""

    def feedback(self) -> WheelFeedback | None:
        """The newest feedback, or None before the first."""

    def counters(self) -> dict[str, int]:
        """What the interface counted: e.g. malformed packets skipped, resynchronisations."""

    def close(self) -> None:
        """Release the port or bus (idempotent)."""

    def estop(self) -> None:
        """An e-stop: stronger than :meth:`halt` where the base has one (the ODrive's Estop message)."""

    def stale_reason(self, now: float) -> str:
        """Why feedback is late, in the interface's words ("" when it has none to give)."""

    def bind_estop(self, engage: Callable[[str, str], None]) -> None:
        """An interface with an e-stop input of its own (a ROS topic) is given the controller's
        ``engage_estop(source, reason)``."""

    def bind_bump(self, bump: Callable[[bool], None]) -> None:
        """An interface with a contact input that is not a bumper fault is given the controller's
        ``bump(backward)`` (the move ends blocked)."""


class HardwareDefaults:
    """The answers of a base without the optional capabilities: its e-stop is :meth:`halt`, it says
    nothing of late feedback, it has no e-stop or contact input of its own. Every implementation
    derives from it and overrides what its base has."""

    def halt(self) -> None:
        raise NotImplementedError

    def estop(self) -> None:
        self.halt()

    def stale_reason(self, now: float) -> str:
        return ""

    def bind_estop(self, engage: Callable[[str, str], None]) -> None:
        return None

    def bind_bump(self, bump: Callable[[bool], None]) -> None:
        return None
