"""The base driver core: two ODrive axes over CANSimple, odometry, commands and safety.

It knows nothing of Zenoh: the service feeds it commands and e-stops and
publishes what :meth:`BaseDriver.state` and :meth:`BaseDriver.odometry` return.

Threads: a python-can ``Notifier`` thread decodes incoming frames; the control
thread (:meth:`BaseDriver.tick`, ``control_hz``) sends the velocity setpoints
itself (never ``send_periodic``: a hung process must stop feeding the
ODrives' watchdogs), integrates odometry, watches heartbeats and recovers from
faults; commands and e-stops come from the caller's threads. One lock guards
everything.

Safety, in order of precedence:

* e-stop: Estop and IDLE to every axis at once, latched until :meth:`clear_estop`;
* faults (CAN errors, missing heartbeats or encoder estimates, axis errors):
  every axis is told IDLE, the active command is aborted; once the cause is
  gone (bus back, heartbeats fresh) the enable sequence is retried every
  ``recover_every_s`` (``auto_recover``);
* limits: body speed and acceleration are clamped, and a wheel never exceeds
  the top linear speed (both wheels scale, keeping the curvature);
* deadman: a velocity command not renewed within ``deadman_s`` ramps to zero.
  Primitives are bounded by their own goal and ``primitive_timeout_s``.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Literal

import can

from services.base_driver.config import AxisConfig, DriverConfig
from services.base_driver.kinematics import Geometry, WheelOdometry, toward
from services.base_driver.primitives import PrimitiveTracker
from services.base_driver.protocol import (AxisState, CanSimple, Cmd, ControlMode, Frame, InputMode,
                                           ProtocolError, error_names)
from shared.messages import DriverMode, DriverState, Odometry, Outcome, PlanCommand
from shared.motion import ActionIds

log = logging.getLogger("ovamos.base_driver")

BusFactory = Callable[[], can.BusABC]
_SEND_TIMEOUT_S = 0.05


@dataclass
class _Axis:
    """What the driver knows of one axis, from its heartbeats and encoder estimates."""

    name: str
    config: AxisConfig
    state: AxisState | int | None = None
    errors: int = 0
    heartbeat_at: float | None = None
    encoder_at: float | None = None
    pos: float | None = None   # rev, in the wheel's forward direction
    vel: float = 0.0           # rev/s, idem

    @property
    def label(self) -> str:
        return f"{self.name} axis (node {self.config.node_id})"


@dataclass
class _Active:
    command: PlanCommand
    received: float
    started: float | None = None         # when execution began (the driver was ready)
    tracker: PrimitiveTracker | None = None


@dataclass
class _Completed:
    action_id: int = 0
    outcome: Outcome | None = None


@dataclass
class _Listener(can.Listener):
    """Feeds frames to the driver; a receive error faults the driver and stops the reader."""

    driver: BaseDriver
    generation: int
    notifier: can.Notifier | None = field(default=None, repr=False)

    def on_message_received(self, msg: can.Message) -> None:
        self.driver._on_frame(msg, self.generation)

    def on_error(self, exc: Exception) -> None:
        # Without this the Notifier would retry a dead bus in a tight loop (150k calls in 0.5 s).
        self.driver.counters["reader_errors"] += 1
        self.driver._on_bus_error(f"CAN receive failed: {exc}", self.generation)
        if self.notifier is not None:
            self.notifier.stop(timeout=0)  # from its own thread: ends the loop, joins nothing

    def stop(self) -> None:
        pass


class BaseDriver:
    """See the module docstring. ``bus_factory`` defaults to ``can.Bus(**config.can)``."""

    def __init__(self, config: DriverConfig, bus_factory: BusFactory | None = None,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.config = config
        self.clock = clock
        self._factory = bus_factory or (lambda: can.Bus(**config.can.bus_kwargs()))
        self.protocol = CanSimple([config.left.node_id, config.right.node_id])
        self.geometry = Geometry(config.wheel_radius_m, config.track_width_m)
        self.axes = [_Axis("left", config.left), _Axis("right", config.right)]
        self._by_node = {a.config.node_id: a for a in self.axes}
        self.counters: Counter[str] = Counter()
        self._lock = threading.RLock()
        self._bus: can.BusABC | None = None
        self._notifier: can.Notifier | None = None
        self._generation = 0
        self._bus_error: str | None = None
        self._phase: Literal["enabling", "ready", "fault"] = "enabling"  # until the bus opens
        self._faults: dict[str, str] = {}
        self._estop: str | None = None       # why it is latched
        self._estop_sent_at = 0.0
        self._enable_started = 0.0
        self._next_recovery = 0.0
        self._v = self._w = 0.0               # the limited body velocity being commanded
        self._last_tick: float | None = None
        self._age_checks_from = -math.inf
        self._active: _Active | None = None
        self._action_ids = ActionIds()
        self._primitives = config.primitives  # advertised in every state
        self._last_command_at = -math.inf
        self._completed = _Completed()
        self._odom = WheelOdometry(self.geometry, config.initial_pose)
        self._odom_seq = 0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    # -- life cycle -------------------------------------------------------------------------------
    def start(self) -> BaseDriver:
        with self._lock:
            self._connect(self.clock())
        self._thread = threading.Thread(target=self._run, name="base-driver", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        """Disarm the axes (best effort) and release the bus and threads."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(5)
        with self._lock:
            self._send_all_idle()
            stale = self._detach()
        _close(*stale)

    def __enter__(self) -> BaseDriver:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _run(self) -> None:
        period = 1.0 / self.config.control_hz
        next_tick = self.clock()
        while not self._stop.is_set():
            try:
                self.tick()
            except Exception:  # a bug must not silently stop the loop (and the watchdog feed)
                self.counters["tick_errors"] += 1
                log.exception("control tick failed")
            next_tick = max(next_tick + period, self.clock())
            self._stop.wait(max(0.0, next_tick - self.clock()))

    # -- the bus ----------------------------------------------------------------------------------
    def _connect(self, now: float) -> None:
        """Open the bus and start reading; on failure stay in fault and retry later."""
        self.counters["bus_opens"] += 1
        try:
            bus = self._factory()
        except (can.CanError, OSError) as exc:
            self._fault("bus", f"CAN bus unavailable: {type(exc).__name__}: {exc}", now)
            return
        self._generation += 1
        listener = _Listener(self, self._generation)
        self._bus, self._bus_error = bus, None
        self._notifier = can.Notifier(bus, [listener], timeout=0.1)
        listener.notifier = self._notifier
        for axis in self.axes:  # only heartbeats heard on this bus count
            axis.heartbeat_at = axis.encoder_at = None
        if self._phase != "fault":
            self._start_enable(now)

    def _detach(self) -> tuple[can.Notifier | None, can.BusABC | None]:
        """Forget the bus (late frames from it are ignored); the caller closes what this returns
        after releasing the lock, since the reader thread may be waiting for that lock."""
        stale = self._notifier, self._bus
        self._notifier = self._bus = None
        self._generation += 1
        return stale

    def _on_bus_error(self, reason: str, generation: int) -> None:
        with self._lock:
            if generation != self._generation or self._bus_error is not None:
                return
            self.counters["bus_errors"] += 1
            self._bus_error = reason
            self._fault("bus", reason, self.clock())

    def _send(self, msg: can.Message) -> bool:
        """Send one frame; a CAN error faults the driver (and is not raised)."""
        if self._bus is None or self._bus_error is not None:
            return False
        try:
            self._bus.send(msg, timeout=_SEND_TIMEOUT_S)
        except (can.CanError, OSError) as exc:
            self.counters["bus_errors"] += 1
            self._bus_error = f"CAN send failed: {type(exc).__name__}: {exc}"
            self._fault("bus", self._bus_error, self.clock())
            return False
        self.counters["frames_tx"] += 1
        return True

    def _send_to_all(self, cmd: Cmd, **signals: float) -> None:
        for axis in self.axes:
            self._send(self.protocol.encode(axis.config.node_id, cmd, **signals))

    def _send_all_idle(self) -> None:
        self._send_to_all(Cmd.SET_AXIS_STATE, Axis_Requested_State=AxisState.IDLE)

    # -- incoming frames --------------------------------------------------------------------------
    def _on_frame(self, msg: can.Message, generation: int) -> None:
        try:
            frame = self.protocol.decode(msg)
        except ProtocolError as exc:
            n = self.counters[exc.kind] = self.counters[exc.kind] + 1
            if n & (n - 1) == 0:  # log the 1st, 2nd, 4th, 8th... only
                log.warning("ignored %s CAN frame (%d so far): %s", exc.kind, n, exc)
            return
        try:
            with self._lock:
                if generation == self._generation:
                    self._apply(frame, self.clock())
        except Exception:  # must not reach the Notifier: it would treat it as a bus error
            self.counters["handler_errors"] += 1
            log.exception("failed to handle %s", frame)

    def _apply(self, frame: Frame, now: float) -> None:
        self.counters["frames_rx"] += 1
        axis = self._by_node[frame.node_id]
        s, sign = frame.signals, axis.config.direction
        if frame.remote:
            self.counters["unexpected"] += 1  # requests are for the ODrives, not for us
        elif frame.cmd is Cmd.HEARTBEAT:
            state = int(s["Axis_State"])
            axis.state = AxisState(state) if state in AxisState._value2member_map_ else state
            axis.errors, axis.heartbeat_at = int(s["Axis_Error"]), now
        elif frame.cmd is Cmd.GET_ENCODER_ESTIMATES:
            axis.pos, axis.vel = sign * s["Pos_Estimate"], sign * s["Vel_Estimate"]
            axis.encoder_at = now
        elif frame.cmd is Cmd.GET_ERROR:
            key = f"axis:{axis.name}"
            if key in self._faults and s["Disarm_Reason"]:
                base = self._faults[key].split(" (disarm reason")[0]
                self._faults[key] = f"{base} (disarm reason: {', '.join(error_names(int(s['Disarm_Reason'])))})"
        else:
            self.counters["unexpected"] += 1  # a command frame from another master on the bus

    # -- commands ---------------------------------------------------------------------------------
    def submit(self, command: PlanCommand) -> Literal["accepted", "duplicate", "rejected"]:
        """Take one command; an action id is executed at most once (re-sent copies are ignored)."""
        with self._lock:
            now = self.clock()
            if not self._action_ids.take(command.action_id):
                self.counters["duplicates"] += 1
                return "duplicate"
            if self._estop is not None or self._phase == "fault":
                self.counters["rejected"] += 1
                self._complete_id(command.action_id, "rejected")
                return "rejected"
            if self._active is not None:  # the newest command wins
                superseded = "done" if self._active.tracker is None and self._active.started else "aborted"
                self._finish(superseded)
            self._active = _Active(command, now)
            self._last_command_at = now
            self.counters["commands"] += 1
            return "accepted"

    def bump(self) -> None:
        """A bumper (the simulator's collision check) hit something: stop the active command."""
        with self._lock:
            if self._active is not None and self._active.started is not None:
                self.counters["bumps"] += 1
                self._finish("blocked")

    def _finish(self, outcome: Outcome) -> None:
        assert self._active is not None
        self._complete_id(self._active.command.action_id, outcome)
        self._active = None

    def _complete_id(self, action_id: int, outcome: Outcome) -> None:
        self._completed = _Completed(action_id, outcome)

    # -- e-stop -----------------------------------------------------------------------------------
    def engage_estop(self, source: str, reason: str = "") -> None:
        """Estop + IDLE to every axis now; latched until :meth:`clear_estop`."""
        with self._lock:
            if self._estop is None:
                log.warning("e-stop engaged by %s: %s", source, reason or "no reason given")
            self._estop = f"e-stop by {source}" + (f": {reason}" if reason else "")
            if self._active is not None:
                self._finish("aborted")
            self._v = self._w = 0.0
            self._send_estop(self.clock())
            self.counters["estops"] += 1

    def clear_estop(self, source: str) -> None:
        """The explicit clear: re-enable the axes (or keep recovering from a fault)."""
        with self._lock:
            if self._estop is None:
                return
            log.warning("e-stop cleared by %s", source)
            self._estop = None
            if self._phase != "fault":
                self._start_enable(self.clock())

    # -- the control loop -------------------------------------------------------------------------
    def tick(self) -> None:
        """One control step (the control thread calls it ``control_hz`` times a second).

        The clock is read once the lock is held: a tick that waited for the lock (the reader or
        anything else stalled it) must see that gap, or it would judge heartbeat ages that the
        blocked reader thread could not refresh.
        """
        with self._lock:
            stale = self._detach() if self._bus_error is not None and self._bus is not None else None
        if stale is not None:
            _close(*stale)
        with self._lock:
            now = self.clock()
            gap = 0.0 if self._last_tick is None else now - self._last_tick
            if gap > self.config.heartbeat_timeout_s / 2:
                # This loop itself was stalled (a slow or suspended host): the reader thread has a
                # backlog of frames to deliver, so heartbeat ages mean nothing until it caught up.
                # Half the timeout, not all of it: an age is the stall plus up to one heartbeat
                # period from before it, so a stall a little shorter than the timeout already
                # makes healthy axes look silent.
                self._age_checks_from = now + self.config.heartbeat_timeout_s
            dt, self._last_tick = min(gap, 0.1), now
            if self._bus is None and now >= self._next_recovery:
                self._next_recovery = now + self.config.recover_every_s
                self._connect(now)
            self._update_odometry()
            if self._estop is not None:
                self._hold_estop(now)
                return
            if self._phase == "enabling":
                self._check_enabled(now)
            elif self._phase == "ready":
                self._check_health(now)
            if self._phase == "fault":
                self._try_recover(now)
            elif self._phase == "ready":
                self._drive(now, dt)
            elif self._phase == "enabling":
                self._send_to_all(Cmd.SET_INPUT_VEL, Input_Vel=0.0, Input_Torque_FF=0.0)

    def _update_odometry(self) -> None:
        left, right = self.axes
        if left.pos is not None and right.pos is not None:
            self._odom.update(left.pos, right.pos)

    def _hold_estop(self, now: float) -> None:
        """An axis reports armed after the e-stop was sent (it missed the frames): repeat them."""
        if any(a.state is AxisState.CLOSED_LOOP_CONTROL and a.heartbeat_at is not None
               and a.heartbeat_at > self._estop_sent_at for a in self.axes):
            self._send_estop(now)

    def _send_estop(self, now: float) -> None:
        self._estop_sent_at = now
        self._send_to_all(Cmd.ESTOP)
        self._send_all_idle()

    def _start_enable(self, now: float) -> None:
        """Clear errors, limits, velocity control with ramp, zero setpoint, closed loop."""
        c = self.config
        self._phase, self._enable_started = "enabling", now
        self._v = self._w = 0.0
        self._send_to_all(Cmd.CLEAR_ERRORS, Identify=0)
        self._send_to_all(Cmd.SET_LIMITS, Velocity_Limit=c.max_wheel_rev_s * 1.1,
                          Current_Limit=c.current_limit_a)
        self._send_to_all(Cmd.SET_CONTROLLER_MODE, Control_Mode=ControlMode.VELOCITY_CONTROL,
                          Input_Mode=InputMode.VEL_RAMP)
        self._send_to_all(Cmd.SET_INPUT_VEL, Input_Vel=0.0, Input_Torque_FF=0.0)
        self._send_to_all(Cmd.SET_AXIS_STATE, Axis_Requested_State=AxisState.CLOSED_LOOP_CONTROL)

    def _check_enabled(self, now: float) -> None:
        armed = [a.heartbeat_at is not None and a.heartbeat_at > self._enable_started
                 and a.state is AxisState.CLOSED_LOOP_CONTROL and not a.errors for a in self.axes]
        if all(armed) and all(a.pos is not None for a in self.axes):
            self._phase = "ready"
            self._faults.clear()
            log.info("axes enabled (closed loop, velocity control)")
        elif now - self._enable_started > self.config.enable_timeout_s:
            why = "; ".join(self._axis_problem(a, now) for a, ok in zip(self.axes, armed) if not ok)
            self._fault("enable", f"enable failed: {why}", now)

    def _axis_problem(self, axis: _Axis, now: float) -> str:
        if axis.heartbeat_at is None:
            return f"no heartbeat from the {axis.label}"
        state = axis.state.name if isinstance(axis.state, AxisState) else axis.state
        errors = ", ".join(error_names(axis.errors)) or "no errors"
        return f"{axis.label} in state {state} ({errors})"

    def _check_health(self, now: float) -> None:
        limit = self.config.heartbeat_timeout_s
        judge_ages = now >= self._age_checks_from
        for axis in self.axes:
            hb_age = math.inf if axis.heartbeat_at is None else now - axis.heartbeat_at
            enc_age = math.inf if axis.encoder_at is None else now - axis.encoder_at
            if not judge_ages:
                hb_age = enc_age = 0.0
            if hb_age > limit:
                self._fault(f"heartbeat:{axis.name}",
                            f"no heartbeat from the {axis.label} for {hb_age:.2f} s", now)
            elif enc_age > limit:
                self._fault(f"encoder:{axis.name}",
                            f"no encoder estimates from the {axis.label} for {enc_age:.2f} s", now)
            elif axis.errors or axis.state is not AxisState.CLOSED_LOOP_CONTROL:
                self._fault(f"axis:{axis.name}", self._axis_problem(axis, now), now)
                self._send(self.protocol.request(axis.config.node_id, Cmd.GET_ERROR))

    def _fault(self, key: str, reason: str, now: float) -> None:
        """Enter (or stay in) the fault state: abort the command, disarm every axis."""
        if self._faults.get(key) != reason.split(" (disarm reason")[0]:
            log.error("fault: %s", reason)
        self._faults[key] = reason
        if self._phase != "fault":
            self._phase = "fault"
            self._next_recovery = max(self._next_recovery, now + self.config.recover_every_s)
            self.counters["faults"] += 1
        if self._active is not None:
            self._finish("aborted")
        self._v = self._w = 0.0
        self._send_all_idle()

    def _try_recover(self, now: float) -> None:
        if not self.config.auto_recover or now < self._next_recovery or self._bus is None:
            return
        limit = self.config.heartbeat_timeout_s
        if all(a.heartbeat_at is not None and now - a.heartbeat_at <= limit for a in self.axes):
            self._next_recovery = now + self.config.recover_every_s
            self.counters["recoveries"] += 1
            log.info("fault cause gone (%s): re-enabling", "; ".join(self._faults.values()))
            self._start_enable(now)

    def _drive(self, now: float, dt: float) -> None:
        linear, angular = self._target(now)
        c = self.config
        linear = max(-c.max_linear_m_s, min(c.max_linear_m_s, linear))
        angular = max(-c.max_angular_rad_s, min(c.max_angular_rad_s, angular))
        self._v = toward(self._v, linear, c.max_linear_accel_m_s2 * dt)
        self._w = toward(self._w, angular, c.max_angular_accel_rad_s2 * dt)
        left, right = self.geometry.wheels_rev_s(self._v, self._w)
        scale = max(1.0, abs(left) / c.max_wheel_rev_s, abs(right) / c.max_wheel_rev_s)
        for axis, wheel in zip(self.axes, (left / scale, right / scale)):
            self._send(self.protocol.encode(axis.config.node_id, Cmd.SET_INPUT_VEL,
                                            Input_Vel=axis.config.direction * wheel, Input_Torque_FF=0.0))

    def _target(self, now: float) -> tuple[float, float]:
        """The body velocity the active command wants now (zero when there is none)."""
        active, c = self._active, self.config
        if active is None:
            return 0.0, 0.0
        cmd = active.command
        if active.started is None:
            active.started = now
            if cmd.action is not None:
                active.tracker = PrimitiveTracker(cmd.action, self._odom.pose, c)
        if active.tracker is None:  # velocity command
            expired = cmd.duration_s > 0 and now - active.started >= cmd.duration_s
            if now - self._last_command_at > c.deadman_s or expired:
                self._finish("done" if expired else "aborted")
                if not expired:
                    self.counters["deadman"] += 1
                return 0.0, 0.0
            return cmd.linear, cmd.angular
        if now - active.started > c.primitive_timeout_s:
            self._finish("aborted")
            return 0.0, 0.0
        request = active.tracker.request(self._odom.pose)
        if request is None:
            if self._v == 0.0 and self._w == 0.0 and all(abs(a.vel) < c.settle_rev_s for a in self.axes):
                self._finish("done")
            return 0.0, 0.0
        return request

    # -- what the service publishes ---------------------------------------------------------------
    def state(self) -> DriverState:
        with self._lock:
            if self._estop is not None:
                mode = DriverMode.ESTOP
            elif self._phase == "fault":
                mode = DriverMode.FAULT
            elif self._phase == "enabling":
                mode = DriverMode.IDLE
            else:
                mode = DriverMode.MOVING if self._active is not None else DriverMode.READY
            faults = tuple(self._faults.values()) + ((self._estop,) if self._estop else ())
            done = self._completed
            return DriverState(stamp=time.time(), mode=mode, faults=faults,
                               estop_latched=self._estop is not None,
                               active_action=self._active.command.action_id if self._active else None,
                               last_completed=done.action_id, last_outcome=done.outcome,
                               primitives=self._primitives)

    def odometry(self) -> Odometry:
        with self._lock:
            pose = self._odom.pose
            left, right = self.axes
            linear, angular = self.geometry.body(left.vel, right.vel)
            self._odom_seq += 1
            return Odometry(seq=self._odom_seq, stamp=time.time(), x=pose.x, y=pose.y, yaw=pose.yaw,
                            linear=linear, angular=angular, after_action=self._completed.action_id)

    def wheel_speeds(self) -> tuple[float, float]:
        """The latest encoder velocity estimates (rev/s, wheel forward positive)."""
        with self._lock:
            return self.axes[0].vel, self.axes[1].vel

    def info(self) -> dict[str, object]:
        with self._lock:
            return {"mode": self.state().mode.value, "faults": list(self._faults.values()),
                    "estop": self._estop, "counters": dict(self.counters)}


def _close(notifier: can.Notifier | None, bus: can.BusABC | None) -> None:
    """Stop a detached reader and shut its bus down (errors on a dead bus are expected)."""
    if notifier is not None:
        notifier.stop(timeout=1.0)
    if bus is not None:
        try:
            bus.shutdown()
        except (can.CanError, OSError):
            pass
