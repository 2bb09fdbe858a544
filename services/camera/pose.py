"""Where the camera was when a frame was captured: odometry interpolated, times the mount.

``camera_pose = world_T_base(t) @ base_T_body @ body_T_optical``:

* ``world_T_base(t)``: the base's odometry pose at the capture time ``t``, linearly
  interpolated between the two odometry messages around ``t`` (x, y, and yaw along
  the shorter arc: odometry at ~50 Hz is 20 ms apart, where a base's motion is a
  straight line to well under a millimetre);
* ``base_T_body``: the mount (:class:`ovamos.services.camera.config.Mount`), measured once;
* ``body_T_optical``: :data:`ovamos.shared.camera.OPTICAL_TO_BODY`, the same constant the
  simulator's camera uses, so a level camera 0.88 m up on the base's axis gives
  exactly :func:`ovamos.shared.camera.camera_pose`.
"""

from __future__ import annotations

import bisect
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from enum import Enum

import numpy as np

from ovamos.services.camera.config import Mount
from ovamos.shared.camera import OPTICAL_TO_BODY
from ovamos.shared.messages import Odometry
from ovamos.shared.sessions import SessionFollower, SessionSwitch

__all__ = ["BasePose", "Miss", "OdometryBuffer", "wrap_angle", "rotation_rpy", "base_T_optical",
           "world_T_base", "camera_pose"]


def wrap_angle(a: float) -> float:
    """``a`` in [-pi, pi)."""
    return (a + math.pi) % (2 * math.pi) - math.pi


def rotation_rpy(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """Rz(yaw) @ Ry(pitch) @ Rx(roll), radians (REP-103 / URDF fixed-axis roll, pitch, yaw)."""
    cr, sr = math.cos(roll), math.sin(roll)
    cp, sp = math.cos(pitch), math.sin(pitch)
    cy, sy = math.cos(yaw), math.sin(yaw)
    rz = np.array([[cy, -sy, 0.0], [sy, cy, 0.0], [0.0, 0.0, 1.0]])
    ry = np.array([[cp, 0.0, sp], [0.0, 1.0, 0.0], [-sp, 0.0, cp]])
    rx = np.array([[1.0, 0.0, 0.0], [0.0, cr, -sr], [0.0, sr, cr]])
    return rz @ ry @ rx


def base_T_optical(mount: Mount) -> np.ndarray:
    """4x4 pose of the optical camera frame (x right, y down, z forward) in the base frame."""
    pose = np.eye(4)
    pose[:3, :3] = rotation_rpy(*(math.radians(a) for a in (mount.roll, mount.pitch, mount.yaw))
                                ) @ OPTICAL_TO_BODY
    pose[:3, 3] = (mount.x, mount.y, mount.z)
    return pose


def world_T_base(x: float, y: float, yaw: float) -> np.ndarray:
    """4x4 pose of the base (on the floor, REP-103) in the world (odometry) frame."""
    c, s = math.cos(yaw), math.sin(yaw)
    pose = np.eye(4)
    pose[:2, :2] = ((c, -s), (s, c))
    pose[:2, 3] = (x, y)
    return pose


def camera_pose(base: BasePose, mount_pose: np.ndarray) -> tuple[float, ...]:
    """world_T_camera (row-major 16 numbers, as :attr:`RgbdFrame.camera_pose`) of a camera
    mounted at ``mount_pose`` (:func:`base_T_optical`) on a base at ``base``."""
    return tuple(float(v) for v in (world_T_base(base.x, base.y, base.yaw) @ mount_pose).ravel())


@dataclass(frozen=True)
class BasePose:
    """The base's pose in the odometry (world) frame: metres, radians."""

    x: float
    y: float
    yaw: float


class Miss(str, Enum):
    """Why a time has no pose (the words counted and shown as skip reasons)."""

    NO_ODOMETRY = "no odometry"
    TOO_OLD = "older than the odometry window"
    TOO_NEW = "newer than the newest odometry"
    GAP = "in a gap of the odometry"


class OdometryBuffer:
    """The last ``window_s`` seconds of odometry, and the base's pose at any time inside it.

    Times are the robot host's wall clock (``Odometry.stamp``, ``time.time()`` when the pose was
    measured). Messages arriving out of order are put in place; a message older than the window
    or repeating a stamp is dropped (counted). A driver that restarts (a new ``odom_session``
    followed on evidence, ``switch``: see :mod:`ovamos.shared.sessions`; or, from a driver that says
    none, its ``seq`` starting again at a later stamp) starts the buffer again: poses from before
    and after a restart are in different odometry frames and must not be interpolated. A message
    of a session not followed is dropped (counted in ``stray``).
    """

    def __init__(self, window_s: float, tolerance_s: float, max_gap_s: float = math.inf,
                 switch: SessionSwitch | None = None, clock: Callable[[], float] = time.monotonic) -> None:
        """``clock``: receipt time for the session evidence (host monotonic)."""
        if window_s <= 0 or tolerance_s < 0 or max_gap_s <= 0:
            raise ValueError("OdometryBuffer needs window_s > 0, tolerance_s >= 0, max_gap_s > 0")
        self.window_s, self.tolerance_s, self.max_gap_s = window_s, tolerance_s, max_gap_s
        self.sessions = SessionFollower(switch or SessionSwitch(), clock=clock)
        self._stamps: list[float] = []
        self._msgs: list[Odometry] = []
        self.dropped = 0    # out of the window, or a repeated stamp
        self.restarts = 0   # the driver's seq started again, or its session changed

    def __len__(self) -> int:
        return len(self._msgs)

    @property
    def newest(self) -> float | None:
        return self._stamps[-1] if self._stamps else None

    @property
    def oldest(self) -> float | None:
        return self._stamps[0] if self._stamps else None

    @property
    def session(self) -> str:
        """The odometry session of the poses held ('' when none is held or the driver says none)."""
        return self._msgs[-1].odom_session if self._msgs else ""

    @property
    def stray(self) -> int:
        """Messages of a session not followed (forged, replayed, or late from before a restart)."""
        return self.sessions.stray["odom"]

    def add(self, msg: Odometry) -> bool:
        """Keep one message; False when it was dropped."""
        if not self.sessions.observe("odom", msg.odom_session, msg.seq):
            return False
        if self._msgs:
            last = self._msgs[-1]
            if msg.odom_session != last.odom_session or (msg.seq < last.seq and msg.stamp > self._stamps[-1]):
                self._stamps.clear()
                self._msgs.clear()
                self.restarts += 1
        newest = self.newest
        if newest is not None and msg.stamp < newest - self.window_s:
            self.dropped += 1
            return False
        i = bisect.bisect_left(self._stamps, msg.stamp)
        if i < len(self._stamps) and self._stamps[i] == msg.stamp:
            self.dropped += 1
            return False
        self._stamps.insert(i, msg.stamp)
        self._msgs.insert(i, msg)
        cut = bisect.bisect_left(self._stamps, self._stamps[-1] - self.window_s)
        if cut:
            del self._stamps[:cut], self._msgs[:cut]
        return True

    def pose_at(self, t: float) -> BasePose | Miss:
        """The pose at wall time ``t`` interpolated between the messages around it (unless they
        are more than ``max_gap_s`` apart), or why not (``TOO_NEW`` may still change when more
        odometry comes; the others will not)."""
        if not self._stamps:
            return Miss.NO_ODOMETRY
        if t < self._stamps[0]:
            return Miss.TOO_OLD
        if t > self._stamps[-1]:
            return Miss.TOO_NEW
        i = bisect.bisect_left(self._stamps, t)
        b = self._msgs[i]
        if self._stamps[i] == t:
            return BasePose(b.x, b.y, wrap_angle(b.yaw))
        a, ta, tb = self._msgs[i - 1], self._stamps[i - 1], self._stamps[i]
        if tb - ta > self.max_gap_s:
            return Miss.GAP
        f = (t - ta) / (tb - ta)
        return BasePose(a.x + f * (b.x - a.x), a.y + f * (b.y - a.y),
                        wrap_angle(a.yaw + f * wrap_angle(b.yaw - a.yaw)))

    def extrapolate(self, t: float) -> BasePose | Miss:
        """The pose at a time after the newest message, by at most ``tolerance_s``: the newest
        pose moved on with its velocities (constant-twist, exact for an arc), for a frame whose
        odometry did not come in time. Further ahead is ``TOO_NEW``."""
        pose = self.pose_at(t)
        if pose is not Miss.TOO_NEW:
            return pose
        newest = self._msgs[-1]
        dt = t - self._stamps[-1]
        if dt > self.tolerance_s:
            return Miss.TOO_NEW
        v, w, yaw = newest.linear, newest.angular, newest.yaw
        if abs(w) < 1e-9:
            dx, dy = v * dt * math.cos(yaw), v * dt * math.sin(yaw)
        else:
            dx = v / w * (math.sin(yaw + w * dt) - math.sin(yaw))
            dy = -v / w * (math.cos(yaw + w * dt) - math.cos(yaw))
        return BasePose(newest.x + dx, newest.y + dy, wrap_angle(yaw + w * dt))
