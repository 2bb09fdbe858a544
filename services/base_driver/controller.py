"""The base controller: commands, primitives, safety and odometry over any base's hardware.

It knows nothing of Zenoh (the service feeds it commands and e-stops and
publishes what :meth:`BaseController.state` and :meth:`BaseController.odometry`
return) nor of any bus: a :class:`~ovamos.services.base_driver.hardware.BaseHardware`
interface sends the body velocity setpoints and reports wheel feedback
(ros2_control's split). :func:`make_hardware` builds the one the config names.

Threads: the control thread (:meth:`BaseController.tick`, ``control_hz``)
reads the feedback, integrates odometry, checks health and sends the setpoint
every tick; commands and e-stops come from the caller's threads. One lock
guards everything, and every call into the hardware is made under it (so they
never overlap); only an e-stop calls the hardware from the caller's thread.

The hardware's life cycle, seen from here: ``open()`` (it may refuse with a
:class:`HardwareError`), then *enabling* until a feedback stamped after the
open reports no fault (``enable_timeout_s``), then *ready*; a fault halts the
wheels and, every ``recover_every_s`` once its cause is gone
(``auto_recover``), ``open()`` is called again. ``halt()`` is called on every
tick while halted (fault or e-stop), so it must be cheap and idempotent.
Optional extensions a hardware interface may offer: ``estop()`` (a stronger
halt for the e-stop; else ``halt()``) and ``stale_reason(now) -> str`` (which
part of the base went silent; else a generic reason).

Commands: the newest wins (the one it replaces completes ``aborted``, a velocity command ``done``),
except that a turn arriving while a turn the same way runs is chained: it turns on from the heading
the running one aims at, which completes ``done``, and the wheels do not stop in between (continuous
motion's look-arounds, counted as ``chained_turns``).

Safety, in order of precedence:

* e-stop: the wheels are halted at once, latched until :meth:`clear_estop`;
* faults: a :class:`HardwareError`, feedback older than ``feedback_timeout_s``,
  faults the device reports, a bumper press or a wheel drop: the wheels are
  halted, the active command is aborted (a MOVE_FORWARD stopped by a bumper
  completes as ``blocked``), the reason is in ``driver/state``; recovery as above;
* stalls: a move driven at walking pace whose odometry does not follow (``stall_s``) is
  stopped as a bump: a base with no bumper against a wall;
* cliffs: no forward motion while a cliff sensor sees a drop (a MOVE_FORWARD
  completes as ``blocked``, turns and reversing stay allowed);
* limits: body speed and acceleration are clamped, and a wheel never exceeds
  the top linear speed (both wheels scale, keeping the curvature);
* deadman: a velocity or path command not renewed within ``deadman_s`` ramps to zero.
  Primitives are bounded by their own goal and ``primitive_timeout_s``, and with
  ``command_timeout_s`` by the planner's keep-alive: a copy of the active command
  (re-sent every ``resend_s``) must come within that time, or the primitive is
  aborted (the link to the planner is down).
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import Counter, deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

from ovamos.services.base_driver.config import DriverConfig
from ovamos.services.base_driver.follower import PathFollower
from ovamos.services.base_driver.hardware import BaseHardware, HardwareError, WheelFeedback
from ovamos.services.base_driver.kinematics import Geometry, WheelOdometry, toward
from ovamos.services.base_driver.primitives import PrimitiveTracker
from ovamos.shared.messages import DriverMode, DriverState, Odometry, Outcome, PlanCommand, new_odom_session
from ovamos.shared.motion import Action, ActionIds, Pose, wrap_angle

log = logging.getLogger("ovamos.base_driver")

_TWO_PI = 2 * math.pi
STALL_SPEED_M_S = 0.05  # slower (the approach to a goal) is not judged for a stall
STALL_FRACTION = 0.25   # of the commanded travel: less progress than this is a stall


def make_hardware(config: DriverConfig, clock: Callable[[], float] = time.monotonic) -> BaseHardware:
    """The hardware interface ``config.hardware`` names (its module imported only when used)."""
    if config.hardware == "odrive_can":
        from ovamos.services.base_driver.odrive.client import ODriveCanHardware
        return ODriveCanHardware(config, clock=clock)
    if config.hardware == "kobuki":
        from ovamos.services.base_driver.kobuki.client import KobukiHardware
        return KobukiHardware(config.kobuki)
    if config.hardware == "opencr":
        from ovamos.services.base_driver.opencr.client import OpenCRHardware
        return OpenCRHardware(config.opencr)
    if config.hardware == "ros2":
        from ovamos.services.base_driver.ros2.client import Ros2Hardware
        return Ros2Hardware(config.ros2, clock=clock)
    raise ValueError(f"unknown base hardware {config.hardware!r}")


@dataclass
class _Active:
    command: PlanCommand
    received: float
    started: float | None = None         # when execution began (the base was ready)
    tracker: PrimitiveTracker | PathFollower | None = None  # None: a velocity command
    outcome: Outcome = "done"            # how it completes when the tracker reaches its goal
    stall: tuple[float, Pose, float] | None = None  # the stall window: since when, from where, travel commanded
    from_yaw: float | None = None        # a chained turn: turned from the heading the turn before it aimed at


@dataclass
class _Completed:
    action_id: int = 0
    outcome: Outcome | None = None


class BaseController:
    """See the module docstring. ``hardware`` defaults to :func:`make_hardware` (``config.hardware``)."""

    def __init__(self, config: DriverConfig, hardware: BaseHardware | None = None,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.config = config
        self.clock = clock
        self.hardware = hardware if hardware is not None else make_hardware(config, clock)
        self.geometry = Geometry(config.wheel_radius_m, config.track_width_m)
        self._counters: Counter[str] = Counter()
        self._lock = threading.RLock()
        self._phase: Literal["closed", "enabling", "ready", "fault"] = "closed"  # until the first open
        self._faults: dict[str, str] = {}
        self._estop: str | None = None       # why it is latched
        self._enable_started = 0.0
        self._next_recovery = 0.0
        self._v = self._w = 0.0               # the limited body velocity being commanded
        self._last_tick: float | None = None
        self._age_checks_from = -math.inf
        self._active: _Active | None = None
        self._bumps: deque[bool] = deque()    # bump() reports, for the next tick
        self._action_ids = ActionIds()
        self._primitives = config.primitives  # advertised in every state
        self._last_command_at = -math.inf
        self._completed = _Completed()
        self._odom = WheelOdometry(self.geometry, config.initial_pose)
        # a hardware with inputs of its own (an e-stop, a contact report) is given their handlers
        self.hardware.bind_estop(self.engage_estop)
        self.hardware.bind_bump(self.bump)
        self.odom_session = new_odom_session()  # the integration starts here, once per process
        self._odom_seq = 0
        self._feedback: WheelFeedback | None = None
        self._wheels = (0.0, 0.0)              # rev/s, wheel forward positive
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    # -- life cycle -------------------------------------------------------------------------------
    def start(self) -> BaseController:
        with self._lock:
            self._open(self.clock())
        self._thread = threading.Thread(target=self._run, name="base-driver", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        """Halt the wheels (best effort) and release the hardware and the thread."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(5)
        with self._lock:
            self.hardware.halt()
            self.hardware.close()

    def __enter__(self) -> BaseController:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _run(self) -> None:
        period = 1.0 / self.config.control_hz
        next_tick = self.clock()
        while not self._stop.is_set():
            try:
                self.tick()
            except Exception:  # a bug must not silently stop the loop (and the setpoint feed)
                self._counters["tick_errors"] += 1
                log.exception("control tick failed")
            next_tick = max(next_tick + period, self.clock())
            self._stop.wait(max(0.0, next_tick - self.clock()))

    @property
    def counters(self) -> Counter[str]:
        """The controller's counts and the hardware's together."""
        with self._lock:
            merged = Counter(self.hardware.counters())
            merged.update(self._counters)
            return merged

    # -- the hardware -----------------------------------------------------------------------------
    def _open(self, now: float) -> bool:
        """(Re-)open the hardware and start enabling; on refusal stay in (or enter) fault."""
        self._counters["opens"] += 1
        try:
            self.hardware.open()
        except HardwareError as exc:
            self._fault("hardware", str(exc), now)
            return False
        self._phase, self._enable_started = "enabling", now
        self._v = self._w = 0.0
        return True

    def _read_feedback(self, now: float) -> WheelFeedback | None:
        try:
            fb = self.hardware.feedback()
        except HardwareError as exc:
            self._fault("hardware", str(exc), now)
            return None
        if fb is not None and fb.pose is not None:  # the base's own odometry (see WheelFeedback)
            prev, self._odom.pose = self._odom.pose, fb.pose
            if fb.body_vel is not None:
                self._wheels = self.geometry.wheels_rev_s(*fb.body_vel)
            elif self._feedback is not None and fb.stamp > self._feedback.stamp:
                dt = fb.stamp - self._feedback.stamp
                forward = (fb.pose.x - prev.x) * math.cos(prev.yaw) + (fb.pose.y - prev.y) * math.sin(prev.yaw)
                self._wheels = self.geometry.wheels_rev_s(forward / dt, wrap_angle(fb.pose.yaw - prev.yaw) / dt)
            self._feedback = fb
        elif fb is not None:
            left, right = fb.left_pos_rad / _TWO_PI, fb.right_pos_rad / _TWO_PI
            last = self._feedback
            self._odom.update(left, right)
            if fb.left_vel_rad_s is not None and fb.right_vel_rad_s is not None:
                self._wheels = (fb.left_vel_rad_s / _TWO_PI, fb.right_vel_rad_s / _TWO_PI)
            elif last is not None and fb.stamp > last.stamp:
                dt = fb.stamp - last.stamp
                self._wheels = ((fb.left_pos_rad - last.left_pos_rad) / _TWO_PI / dt,
                                (fb.right_pos_rad - last.right_pos_rad) / _TWO_PI / dt)
            self._feedback = fb
        return fb

    def _stale_reason(self, now: float, age: float) -> str:
        reason = self.hardware.stale_reason(now)
        if reason:
            return reason
        if age == math.inf:
            return f"no feedback from the {self.hardware.name} base"
        return f"no feedback from the {self.hardware.name} base for {age:.2f} s"

    # -- commands ---------------------------------------------------------------------------------
    def submit(self, command: PlanCommand) -> Literal["accepted", "duplicate", "rejected"]:
        """Take one command; an action id is executed at most once (re-sent copies are ignored)."""
        with self._lock:
            now = self.clock()
            if not self._action_ids.take(command.action_id):
                self._counters["duplicates"] += 1
                if self._active is not None and self._active.command.action_id == command.action_id:
                    self._last_command_at = now  # the sender's keep-alive
                return "duplicate"
            if self._estop is not None or self._phase == "fault":
                self._counters["rejected"] += 1
                self._complete_id(command.action_id, "rejected")
                return "rejected"
            from_yaw = self._chained(command)
            if self._active is not None:  # the newest command wins
                superseded: Literal["done", "aborted"] = ("done" if from_yaw is not None or (
                    self._active.tracker is None and self._active.started) else "aborted")
                self._finish(superseded)
            self._active = _Active(command, now, from_yaw=from_yaw)
            self._last_command_at = now
            self._counters["commands"] += 1
            self._counters["chained_turns"] += from_yaw is not None
            return "accepted"

    def _chained(self, command: PlanCommand) -> float | None:
        """The heading a turn arriving while a turn the same way is under way starts from: the one
        the running turn aims at, so that it carries on turning without stopping in between and
        lands ``turn_deg`` further (the running one completes as done). None for anything else."""
        active = self._active
        tracker = None if active is None else active.tracker
        if (isinstance(tracker, PrimitiveTracker) and tracker.action.turn_sign and command.action is tracker.action
                and active is not None and active.outcome == "done"):
            return tracker.goal_yaw
        return None

    def bump(self, backward: bool = False) -> None:
        """Something outside the hardware's sensors (the simulator's collision check) hit an
        obstacle, the wheels turning ``backward`` or not: the next tick stops the active command
        as blocked, a forward move first driving back to where it started (``back_off_on_bump``).

        Queued, never waiting for the lock: the simulator calls it from a simulated device's
        thread, which the control thread may be waiting on for an answer (the OpenCR's status
        packet) while it holds the lock."""
        self._bumps.append(backward)

    def _take_bumps(self) -> None:
        """Act on the queued :meth:`bump` reports (under the lock, in the tick)."""
        while self._bumps:
            backward = self._bumps.popleft()
            active = self._active
            if active is None or active.started is None:
                continue
            self._counters["bumps"] += 1
            tracker = active.tracker
            if active.outcome == "blocked":  # backing off already
                if backward:  # hit something behind: stop there
                    self._finish("blocked")
                continue  # else the last forward push of wheels still slowing down: keep going
            if isinstance(tracker, PathFollower) and (backward or not self.config.back_off_on_bump):
                self._v = 0.0  # at once: the wheels are against the obstacle
                self._finish("blocked")
            elif self.config.back_off_on_bump and (isinstance(tracker, PathFollower) or (
                    isinstance(tracker, PrimitiveTracker) and tracker.action is Action.MOVE_FORWARD)):
                # a primitive back to where it started, a path back_off_m from the contact
                active.tracker = (PrimitiveTracker(Action.MOVE_FORWARD, tracker.start, self.config, distance_m=0.0)
                                  if isinstance(tracker, PrimitiveTracker) else
                                  PrimitiveTracker(Action.MOVE_FORWARD, self._odom.pose, self.config,
                                                   distance_m=-self.config.follow.back_off_m))
                active.outcome = "blocked"
                self._v = 0.0  # at once: the wheels are against the obstacle
                self._counters["back_offs"] += 1
            else:
                self._finish("blocked")

    def _finish(self, outcome: Outcome) -> None:
        assert self._active is not None
        self._complete_id(self._active.command.action_id, outcome)
        self._active = None

    def _complete_id(self, action_id: int, outcome: Outcome) -> None:
        self._completed = _Completed(action_id, outcome)

    def _moving_forward(self) -> bool:
        a = self._active
        return a is not None and a.started is not None and (a.command.action is Action.MOVE_FORWARD
                                                           or bool(a.command.path))

    # -- e-stop -----------------------------------------------------------------------------------
    def engage_estop(self, source: str, reason: str = "") -> None:
        """Halt the wheels now; latched until :meth:`clear_estop`."""
        with self._lock:
            if self._estop is None:
                log.warning("e-stop engaged by %s: %s", source, reason or "no reason given")
            self._estop = f"e-stop by {source}" + (f": {reason}" if reason else "")
            if self._active is not None:
                self._finish("aborted")
            self._v = self._w = 0.0
            self.hardware.estop()
            self._counters["estops"] += 1

    def clear_estop(self, source: str) -> None:
        """The explicit clear: re-open the hardware (or keep recovering from a fault)."""
        with self._lock:
            if self._estop is None:
                return
            log.warning("e-stop cleared by %s", source)
            self._estop = None
            if self._phase != "fault":
                self._open(self.clock())

    # -- the control loop -------------------------------------------------------------------------
    def tick(self) -> None:
        """One control step (the control thread calls it ``control_hz`` times a second).

        The clock is read once the lock is held: a tick that waited for the lock must see that
        gap, or it would judge feedback ages that could not be refreshed meanwhile.
        """
        with self._lock:
            now = self.clock()
            gap = 0.0 if self._last_tick is None else now - self._last_tick
            if gap > self.config.feedback_timeout_s / 2:
                # This loop itself was stalled (a slow or suspended host): a reader thread has a
                # backlog of feedback to deliver, so ages mean nothing until it caught up. Half the
                # timeout, not all of it: an age is the stall plus up to one feedback period from
                # before it, so a stall a little shorter than the timeout already makes a healthy
                # base look silent.
                self._age_checks_from = now + self.config.feedback_timeout_s
            dt, self._last_tick = min(gap, 0.1), now
            if self._phase == "closed":
                self._open(now)
            fb = self._read_feedback(now)
            self._take_bumps()
            if self._estop is not None:
                self.hardware.estop()  # repeated: cheap, and re-sent if the base did not take it
                return
            if self._phase == "enabling":
                self._check_enabled(fb, now)
            elif self._phase == "ready":
                self._check_health(fb, now)
            if self._phase == "fault":
                self._hold_fault(fb, now)
            elif self._phase == "ready":
                self._drive(fb, now, dt)
            elif self._phase == "enabling":
                self._send(0.0, 0.0, now)

    def _send(self, linear: float, angular: float, now: float) -> None:
        try:
            self.hardware.set_velocity(linear, angular)
        except HardwareError as exc:
            self._fault("hardware", str(exc), now)

    def _check_sensors(self, fb: WheelFeedback | None, now: float) -> None:
        """A bumper press or a wheel drop halts the wheels and is a fault (bumper: MOVE_FORWARD
        completes as blocked)."""
        if fb is None:
            return
        if fb.bumpers:
            self._counters["bumper_presses"] += 1
            if self._moving_forward():
                self._finish("blocked")
            self._fault("bumper", f"bumper {', '.join(fb.bumpers)} pressed", now)
        if fb.wheel_drops:
            self._counters["wheel_drops"] += 1
            self._fault("wheel_drop", f"wheel drop {', '.join(fb.wheel_drops)}", now)

    def _check_enabled(self, fb: WheelFeedback | None, now: float) -> None:
        self._check_sensors(fb, now)
        if self._phase != "enabling":
            return
        if fb is not None and fb.stamp > self._enable_started and not fb.faults:
            self._phase = "ready"
            self._faults.clear()
            log.info("%s base enabled", self.hardware.name)
        elif now - self._enable_started > self.config.enable_timeout_s:
            if fb is not None and fb.faults:
                why = "; ".join(fb.faults)
            else:
                why = self._stale_reason(now, math.inf if fb is None else now - fb.stamp)
            self._fault("enable", f"enable failed: {why}", now)

    def _check_health(self, fb: WheelFeedback | None, now: float) -> None:
        age = math.inf if fb is None else now - fb.stamp
        if now < self._age_checks_from:
            age = 0.0
        if age > self.config.feedback_timeout_s:
            self._fault("stale", self._stale_reason(now, age), now)
        elif fb is not None and fb.faults:
            self._fault("hardware", "; ".join(fb.faults), now)
        else:
            self._check_sensors(fb, now)

    def _fault(self, key: str, reason: str, now: float) -> None:
        """Enter (or stay in) the fault state: abort the command, halt the wheels."""
        if self._faults.get(key) != reason:
            log.error("fault: %s", reason)
        self._faults[key] = reason
        if self._phase != "fault":
            self._phase = "fault"
            self._next_recovery = max(self._next_recovery, now + self.config.recover_every_s)
            self._counters["faults"] += 1
        if self._active is not None:
            self._finish("aborted")
        self._v = self._w = 0.0
        self.hardware.halt()

    def _hold_fault(self, fb: WheelFeedback | None, now: float) -> None:
        """Keep the wheels halted, keep the device's fault text current, re-open when due."""
        self.hardware.halt()
        if fb is not None and fb.faults and "hardware" in self._faults:
            reason = "; ".join(fb.faults)
            if self._faults["hardware"] != reason:
                self._faults["hardware"] = reason
        if not self.config.auto_recover or now < self._next_recovery:
            return
        if fb is not None and (fb.bumpers or fb.wheel_drops):
            return  # the cause is still there
        self._next_recovery = now + self.config.recover_every_s
        causes = "; ".join(self._faults.values())
        if self._open(now):
            self._counters["recoveries"] += 1
            log.info("fault cause gone (%s): re-enabling", causes)

    def _drive(self, fb: WheelFeedback | None, now: float, dt: float) -> None:
        linear, angular = self._target(now)
        c = self.config
        cliff = fb is not None and bool(fb.cliffs)
        if cliff:
            if self._moving_forward():
                self._counters["cliff_stops"] += 1
                self._finish("blocked")
                linear, angular = 0.0, 0.0
            linear = min(linear, 0.0)
            self._v = min(self._v, 0.0)  # at once, not ramped
        linear = max(-c.max_linear_m_s, min(c.max_linear_m_s, linear))
        angular = max(-c.max_angular_rad_s, min(c.max_angular_rad_s, angular))
        self._v = toward(self._v, linear, c.max_linear_accel_m_s2 * dt)
        self._w = toward(self._w, angular, c.max_angular_accel_rad_s2 * dt)
        left, right = self.geometry.wheels_rev_s(self._v, self._w)
        scale = max(1.0, abs(left) / c.max_wheel_rev_s, abs(right) / c.max_wheel_rev_s)
        self._send(self._v / scale, self._w / scale, now)
        self._check_stall(now, dt)

    def _check_stall(self, now: float, dt: float) -> None:
        """A move whose wheels are driven but whose odometry does not follow is blocked (``stall_s``):
        reported as a bump, so a forward move backs off as from a contact."""
        active, limit = self._active, self.config.stall_s
        moving = abs(self._v) >= STALL_SPEED_M_S
        if limit is None or active is None or active.tracker is None or not moving:
            if active is not None:
                active.stall = None
            return
        pose = self._odom.pose
        if active.stall is None:
            active.stall = (now, pose, 0.0)
            return
        since, start, travel = active.stall
        travel += abs(self._v) * dt
        active.stall = (since, start, travel)
        if now - since < limit:
            return
        active.stall = None  # the next window starts here
        moved = math.hypot(pose.x - start.x, pose.y - start.y)
        if moved < STALL_FRACTION * travel:
            self._counters["stalls"] += 1
            log.warning("command %d: moved %.3f m of %.3f m commanded in %.1f s: stalled, stopped as blocked",
                        active.command.action_id, moved, travel, now - since)
            self.bump(backward=self._v < 0)

    def _target(self, now: float) -> tuple[float, float]:
        """The body velocity the active command wants now (zero when there is none)."""
        active, c = self._active, self.config
        if active is None:
            return 0.0, 0.0
        cmd = active.command
        if active.started is None:
            active.started = now
            if cmd.action is not None:
                pose = self._odom.pose
                start = pose if active.from_yaw is None else Pose(x=pose.x, y=pose.y, yaw=active.from_yaw)
                active.tracker = PrimitiveTracker(cmd.action, start, c)
            elif cmd.path:
                active.tracker = PathFollower(cmd.path, c, cmd.obstacles, cmd.speed_m_s)
        if active.tracker is None:  # velocity command
            expired = cmd.duration_s > 0 and now - active.started >= cmd.duration_s
            if now - self._last_command_at > c.deadman_s or expired:
                self._finish("done" if expired else "aborted")
                if not expired:
                    self._counters["deadman"] += 1
                return 0.0, 0.0
            return cmd.linear, cmd.angular
        if isinstance(active.tracker, PathFollower):
            if now - self._last_command_at > c.deadman_s:  # the planner's keep-alive stopped
                self._finish("aborted")
                self._counters["deadman"] += 1
                return 0.0, 0.0
        elif now - active.started > c.primitive_timeout_s:
            self._finish("aborted")
            return 0.0, 0.0
        if c.command_timeout_s is not None and now - self._last_command_at > c.command_timeout_s:
            self._counters["command_timeouts"] += 1
            log.warning("command %d aborted: no copy of it for %.2f s (the link to the planner is down?)",
                        cmd.action_id, now - self._last_command_at)
            self._finish("aborted")
            return 0.0, 0.0
        request = active.tracker.request(self._odom.pose)
        if request is None:
            if self._v == 0.0 and self._w == 0.0 and all(abs(v) < c.settle_rev_s for v in self._wheels):
                self._finish(active.outcome)
            return 0.0, 0.0
        return request

    # -- what the service publishes ---------------------------------------------------------------
    def state(self) -> DriverState:
        with self._lock:
            if self._estop is not None:
                mode = DriverMode.ESTOP
            elif self._phase == "fault":
                mode = DriverMode.FAULT
            elif self._phase in ("closed", "enabling"):
                mode = DriverMode.IDLE
            else:
                mode = DriverMode.MOVING if self._active is not None else DriverMode.READY
            faults = tuple(self._faults.values()) + ((self._estop,) if self._estop else ())
            done = self._completed
            return DriverState(stamp=time.time(), mode=mode, odom_session=self.odom_session,
                               faults=faults, estop_latched=self._estop is not None,
                               active_action=self._active.command.action_id if self._active else None,
                               last_completed=done.action_id, last_outcome=done.outcome,
                               backing_off=self._active is not None and self._active.outcome == "blocked",
                               primitives=self._primitives)

    @property
    def has_pose(self) -> bool:
        """Whether the base has reported feedback yet. Before it the odometry is only where the
        integration starts: for a base that reports its own pose (ROS 2's /odom) a made-up (0, 0)
        that jumps to the robot's pose on the first message, and frames posed with it land in the
        wrong place on the map."""
        with self._lock:
            return self._feedback is not None

    def odometry(self) -> Odometry:
        with self._lock:
            pose = self._odom.pose
            linear, angular = self.geometry.body(*self._wheels)
            self._odom_seq += 1
            return Odometry(seq=self._odom_seq, stamp=time.time(), odom_session=self.odom_session,
                            x=pose.x, y=pose.y, yaw=pose.yaw,
                            linear=linear, angular=angular, after_action=self._completed.action_id,
                            map_T_odom=None if self._feedback is None else self._feedback.map_T_odom)

    def wheel_speeds(self) -> tuple[float, float]:
        """The latest wheel speeds (rev/s, wheel forward positive)."""
        with self._lock:
            return self._wheels

    def info(self) -> dict[str, object]:
        with self._lock:
            return {"hardware": self.hardware.name, "mode": self.state().mode.value,
                    "faults": list(self._faults.values()), "estop": self._estop,
                    "counters": dict(self.counters)}


#: The name the service, the simulator and the tests use.
BaseDriver = BaseController
