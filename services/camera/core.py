"""The robot camera's core: captured frames in, posed and gated :class:`RgbdFrame` s out.

No Zenoh and no SDK here: the service adapter feeds the core from its one thread
(docs/design.md, "One thread per service") and publishes what :meth:`CameraCore.poll` returns; a backend
(:mod:`ovamos.services.camera.capture`) only delivers :class:`CapturedFrame` s. So every
backend is timed, posed, gated and health-checked the same way, and all of it is
tested without a device.

Clocks (every argument says which it is on):

* **host monotonic** (``time.monotonic()`` on the camera's host): frame receipt
  (``CapturedFrame.host_time_s``), driver-state receipt, ``poll(now)``. Capture
  times are mapped onto it from the device clock (:mod:`ovamos.services.camera.clock`);
  lock-step gating, timeouts and rate limits compare times on it only.
* **host wall** (``time.time()`` on the same host): ``Odometry.stamp`` (the base
  driver runs on the robot host too) and the published stamps. A capture time
  becomes wall time with this host's ``time.time() - time.monotonic()``, read at
  the frame's receipt (``wall_offset``, injectable for tests).

What a frame goes through (:meth:`CameraCore.on_frame`):

1. checked: the arrays' shapes and types (else fault "bad frame ..."); depth all zero is
   counted and published unless every frame has been so for ``depth_zero_fault_s`` (then
   fault "depth all zero ..." and not published: a robot facing a wall too near for depth
   must still get the frame that lets the planner turn it away); a good frame clears a
   camera fault (recovery needs no restart);
2. timed: device time -> host monotonic capture time (unknown while a clock jump
   is being confirmed: not published, counted);
3. selected: lock-step publishes, after each completed command, the first frame
   captured after the driver state saying so arrived (``after_action`` = that
   command), and a start-up frame before any (``after_action`` 0); free-running
   publishes every frame (``max_hz`` at most), ``after_action`` = the newest
   completion received before the capture;
4. posed: odometry interpolated at the capture time times the mount
   (:mod:`ovamos.services.camera.pose`). A frame newer than the newest odometry waits for
   the next message (``odometry.wait_s``), then is extrapolated within
   ``odometry.tolerance_s`` or skipped; a frame older than the odometry window, or
   in a gap of it (``odometry.max_gap_s``), is skipped. Skips are counted by reason
   (:attr:`CameraState.skipped`), and frames that stay unposed for
   ``frame_timeout_s`` are a fault (the planner then waits with a reason instead of
   a silent stall). A frame carries the ``odom_session`` of the odometry it was posed
   with; a restarted driver's odometry is never interpolated with the old one's.

Lock-step also re-publishes the latest frame (same seq) every ``republish_s`` while
idle, for late subscribers, as the simulated robot does (services/sim/service.py).
"""

from __future__ import annotations

import math
import time
from collections import Counter, deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from ovamos.services.camera.capture import CapturedFrame
from ovamos.services.camera.clock import make_clock
from ovamos.services.camera.config import CameraConfig
from ovamos.services.camera.pose import BasePose, Miss, OdometryBuffer, base_T_optical, camera_pose
from ovamos.shared.messages import CameraState, DriverMode, DriverState, Odometry, RgbdFrame

__all__ = ["CameraCore", "host_wall_offset", "DEPTH_ALL_ZERO", "CLOCK_JUMP"]

DEPTH_ALL_ZERO = "depth all zero"
CLOCK_JUMP = "device clock jump being confirmed"


def host_wall_offset() -> float:
    """This host's ``time.time() - time.monotonic()``: adds to a monotonic time to give wall time."""
    return time.time() - time.monotonic()


@dataclass(frozen=True)
class _Armed:
    """Lock-step: the completion a frame is owed for, and from when a capture counts."""

    action: int
    not_before: float  # host monotonic


@dataclass(frozen=True)
class _Pending:
    """A selected frame waiting for odometry around its capture time."""

    captured: CapturedFrame
    capture: float       # host monotonic
    capture_wall: float  # host wall
    after_action: int


def _check(c: CapturedFrame) -> str | None:
    """Why a backend's frame cannot be published, or None (a backend bug, not a camera fault:
    said plainly so that it is fixed where it is)."""
    d, rgb = c.depth, c.rgb
    if d.ndim != 2 or d.dtype != np.uint16:
        return f"depth must be an H x W uint16 array, got {d.ndim}-d {d.dtype}"
    if rgb.shape != (*d.shape, 3) or rgb.dtype != np.uint8:
        return (f"rgb must be {d.shape[0]} x {d.shape[1]} x 3 uint8 (aligned to depth), "
                f"got {rgb.shape} {rgb.dtype}")
    ids = c.instance_ids
    if ids is not None and (ids.shape != d.shape or ids.dtype.kind != "i"):
        return f"instance_ids must be {d.shape[0]} x {d.shape[1]} integers, got {ids.shape} {ids.dtype}"
    if not (math.isfinite(c.depth_scale) and c.depth_scale > 0):
        return f"depth_scale must be a positive number, got {c.depth_scale}"
    if not (math.isfinite(c.device_time_s) and math.isfinite(c.host_time_s)):
        return "frame times must be finite"
    return None


class CameraCore:
    """Turns a backend's frames into posed :class:`RgbdFrame` s and a :class:`CameraState`.

    Called from one thread (the service's), never concurrently: ``on_odom``, ``on_driver``,
    ``on_frame`` and ``on_error`` as events come, and ``poll`` after each of them and on every
    tick; ``poll`` returns what to publish. The core owns the frames' ``seq`` (0, 1, ... over
    the process's life, across backend restarts; a re-published frame keeps its seq).

    The arrays of a :class:`CapturedFrame` are published as they are, without a copy, and
    the latest published frame is kept for re-publishing: a backend must hand over arrays it
    will not write again.
    """

    def __init__(self, config: CameraConfig, now: float, *,
                 wall_offset: Callable[[], float] = host_wall_offset) -> None:
        """``now``: host monotonic start time (the no-frame timeout counts from it);
        ``wall_offset``: returns ``time.time() - time.monotonic()`` of this host."""
        self.config = c = config
        self._wall_offset = wall_offset
        self._clock = make_clock(c.clock)
        self._odom = OdometryBuffer(c.odometry.window_s, c.odometry.tolerance_s, c.odometry.max_gap_s,
                                    c.odometry.session_switch)
        self._mount = base_T_optical(c.mount)
        # selection
        self._armed: _Armed | None = _Armed(0, -math.inf)  # the start-up frame
        self._served = -1                  # lock-step: newest completion a frame was published for
        self._driver_completed: int | None = None
        self._completions: deque[tuple[float, int]] = deque()  # free-running: (receipt, completed)
        self._due = -math.inf              # free-running: capture time the next frame may have
        self._pending: deque[_Pending] = deque()
        # output
        self._seq = 0
        self._outbox: list[RgbdFrame] = []
        self._latest: RgbdFrame | None = None
        self._published_at = -math.inf
        # health
        self._started = now
        self._last_frame_at: float | None = None
        self._error = ""                   # the backend's last CameraError, until a good frame
        self._frame_fault = ""             # depth all zero / bad frame, until a good frame
        self._zero_depth_since: float | None = None  # receipt of the first of the all-zero frames in a row
        self._unposed_since: float | None = None  # first of the frames skipped since one was posed
        self._unposed_reason = ""
        self._state_fault: str | None = None
        self._state_at = -math.inf
        # counts (the adapter's stats)
        self.received = 0
        self.published = 0
        self.republished = 0
        self.rate_limited = 0
        self.skipped: Counter[str] = Counter()   # selected frames not published: no pose
        self.rejected: Counter[str] = Counter()  # frames refused: depth all zero, bad arrays, untimed
        self.zero_depth = 0                      # frames with no depth at all (published or not)

    # -- inputs ------------------------------------------------------------------------------

    def on_odom(self, msg: Odometry) -> None:
        """An ``odom`` message (its ``stamp`` is the robot host's wall clock). Frames waiting for
        odometry after their capture time are posed as soon as it comes."""
        self._odom.add(msg)
        self._resolve(None)

    def on_driver(self, msg: DriverState, host_time: float) -> None:
        """A ``driver/state`` message and when it was received (host monotonic; take it in the
        Zenoh callback if you can: a later time only makes the gate wait for a later frame).

        Lock-step: when ``last_completed`` grows and the base is not moving, the next frame
        captured after ``host_time`` (+ ``settle_s``) is owed, with ``after_action`` =
        ``last_completed``. A ``last_completed`` that goes down is a restarted driver: its ids
        start again, so the gate starts again too.
        """
        completed = msg.last_completed
        if self._driver_completed is not None and completed < self._driver_completed:
            self._served, self._armed = -1, None
        self._driver_completed = completed
        if not self._completions or self._completions[-1][1] != completed:
            self._completions.append((host_time, completed))
        while len(self._completions) > 1 and \
                self._completions[1][0] < host_time - self.config.odometry.window_s:
            self._completions.popleft()
        moving = msg.mode == DriverMode.MOVING or msg.active_action is not None
        owed = max(self._served, self._armed.action if self._armed else -1)
        if not moving and completed > owed:
            self._armed = _Armed(completed, host_time + self.config.settle_s)

    def on_error(self, message: str | BaseException) -> None:
        """The backend failed (a :class:`CameraError`, or the adapter's words). Reported as the
        fault until a good frame comes; the adapter restarts the backend, and since a restarted
        device may have restarted its clock, the clock estimate starts again."""
        self._error = f"camera error: {message}" if str(message) else "camera error"
        self._clock.reset()

    def on_frame(self, captured: CapturedFrame) -> None:
        """A frame from the backend (``device_time_s`` its clock, ``host_time_s`` host monotonic
        at receipt). Whatever it yields comes out of :meth:`poll`."""
        now = captured.host_time_s
        self.received += 1
        self._last_frame_at = now if self._last_frame_at is None else max(self._last_frame_at, now)
        bad = _check(captured)
        if bad is not None:
            self.rejected["bad frame"] += 1
            self._frame_fault = f"bad frame from the backend: {bad}"
            return
        if not captured.depth.any():
            self.zero_depth += 1
            since = self._zero_depth_since = now if self._zero_depth_since is None else self._zero_depth_since
            limit = self.config.depth_zero_fault_s
            if now - since >= limit:
                self.rejected[DEPTH_ALL_ZERO] += 1
                self._frame_fault = (f"{DEPTH_ALL_ZERO} for {limit:g} s: is the depth stream on and the lens "
                                     f"clear?" if limit else DEPTH_ALL_ZERO)
                return
        else:
            self._zero_depth_since = None
        self._frame_fault = self._error = ""  # frames are back: recovered
        capture = self._clock.to_host(captured.device_time_s, now)
        if capture is None:  # not counted as skipped: it may not have been selected anyway
            self.rejected[CLOCK_JUMP] += 1
            return
        capture = min(capture, now)  # never after its own receipt (a host-stamped backend may say so)
        after_action = self._select(capture)
        if after_action is None:
            return
        if len(self._pending) >= self.config.odometry.max_pending:
            self._pending.popleft()
            self._skip(Miss.TOO_NEW.value, now)
        self._pending.append(_Pending(captured, capture, capture + self._wall_offset(), after_action))
        self._resolve(None)

    # -- output ------------------------------------------------------------------------------

    def poll(self, now: float) -> tuple[list[RgbdFrame], CameraState | None]:
        """What to publish now (``now`` host monotonic): new frames in seq order (or, in lock-step
        while idle, the latest one again every ``republish_s``), and a :class:`CameraState` when
        the fault changed or ``1 / state_hz`` passed. Call it after every event and on ticks:
        frames waiting for odometry are decided here once their wait is over."""
        self._resolve(now)
        frames, self._outbox = self._outbox, []
        if frames:
            self._published_at = now
        elif self.config.lock_step and self._latest is not None and \
                now - self._published_at >= self.config.republish_s:
            frames = [self._latest]
            self._published_at = now
            self.republished += 1
        fault = self.fault(now)
        state = None
        if fault != self._state_fault or now - self._state_at >= 1.0 / self.config.state_hz:
            state = self.state(now)
            self._state_fault, self._state_at = fault, now
        return frames, state

    @property
    def pending(self) -> int:
        """Frames selected and waiting for odometry (``odometry.max_pending`` at most: beyond it
        the oldest is skipped)."""
        return len(self._pending)

    def fault(self, now: float) -> str:
        """Why the camera is not delivering posed frames (``now`` host monotonic), or "".

        In order: the backend's error, no frames for ``frame_timeout_s``, a bad or empty frame,
        frames that could not be posed for ``frame_timeout_s``."""
        timeout = self.config.frame_timeout_s
        if self._error:
            return self._error
        last = self._started if self._last_frame_at is None else self._last_frame_at
        if now - last > timeout:
            return f"no camera frames for over {timeout:g} s"
        if self._frame_fault:
            return self._frame_fault
        if self._unposed_since is not None and now - self._unposed_since >= timeout:
            return f"frames not posed for over {timeout:g} s: {self._unposed_reason}"
        return ""

    def state(self, now: float) -> CameraState:
        """The camera's health as a message (``stamp``: host wall time of ``now``)."""
        return CameraState(stamp=now + self._wall_offset(), backend=self.config.backend,
                           fault=self.fault(now), frames=self.published,
                           skipped=sum(self.skipped.values()),
                           last_seq=None if self._latest is None else self._latest.seq)

    def info(self) -> dict[str, Any]:
        """Counters and estimates for the service's stats (``ovamos status``)."""
        clock = self._clock
        return {"received": self.received, "published": self.published,
                "republished": self.republished, "rate_limited": self.rate_limited,
                "skipped": dict(self.skipped), "rejected": dict(self.rejected), "zero_depth": self.zero_depth,
                "pending": self.pending, "odometry": len(self._odom),
                "odometry_dropped": self._odom.dropped, "odometry_stray": self._odom.stray, "clock_resets": clock.resets,
                "clock_offset_s": getattr(clock, "offset", None),
                "lock_step_owed": None if self._armed is None else self._armed.action}

    # -- internals ---------------------------------------------------------------------------

    def _select(self, capture: float) -> int | None:
        """The frame's ``after_action`` if it is to be published, else None (not an error:
        lock-step publishes one frame per completion)."""
        if self.config.lock_step:
            armed = self._armed
            if armed is None or capture < armed.not_before:
                return None
            return armed.action
        completed = 0
        for received, value in reversed(self._completions):
            if received <= capture:
                completed = value
                break
        return completed

    def _resolve(self, now: float | None) -> None:
        """Pose the waiting frames, oldest first, as far as odometry allows; with ``now`` (host
        monotonic), a frame whose wait for newer odometry is over is extrapolated or skipped."""
        while self._pending:
            p = self._pending[0]
            if self.config.lock_step and p.after_action <= self._served:
                self._pending.popleft()  # its completion already got a frame
                continue
            pose = self._odom.pose_at(p.capture_wall)
            if pose is Miss.TOO_NEW or pose is Miss.NO_ODOMETRY:  # odometry may still come
                if now is None or now - p.captured.host_time_s < self.config.odometry.wait_s:
                    return
                pose = self._odom.extrapolate(p.capture_wall)
            self._pending.popleft()
            if isinstance(pose, Miss):
                self._skip(pose.value, p.captured.host_time_s)
            else:
                self._publish(p, pose)

    def _skip(self, reason: str, received: float) -> None:
        self.skipped[reason] += 1
        if self._unposed_since is None:
            self._unposed_since = received
        self._unposed_reason = reason

    def _publish(self, p: _Pending, pose: BasePose) -> None:
        self._unposed_since = None
        if not self.config.lock_step and self.config.max_hz is not None:
            if p.capture < self._due:
                self.rate_limited += 1
                return
            period = 1.0 / self.config.max_hz
            # the next slot one period on (an average of max_hz despite jitter), or one period
            # after this frame if frames stopped for longer than that
            self._due = self._due + period if p.capture - self._due < period else p.capture + period
        c = p.captured
        frame = RgbdFrame(seq=self._seq, stamp=p.capture_wall, after_action=p.after_action,
                          odom_session=self._odom.session, intrinsics=c.intrinsics,
                          camera_pose=camera_pose(pose, self._mount),
                          depth_scale=c.depth_scale, rgb=np.ascontiguousarray(c.rgb),
                          depth=np.ascontiguousarray(c.depth, dtype="<u2"),
                          instance_ids=None if c.instance_ids is None else np.ascontiguousarray(c.instance_ids, "<i4"))
        self._seq += 1
        self.published += 1
        self._latest = frame
        self._outbox.append(frame)
        if self.config.lock_step:
            self._served = max(self._served, p.after_action)
            if self._armed is not None and self._armed.action <= self._served:
                self._armed = None
