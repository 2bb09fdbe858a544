"""The ``odrive_can`` hardware interface: two ODrive axes over CANSimple (python-can + the DBC).

It only speaks the bus; the policy (limits, ramps, deadman, primitives, the
fault / recover state machine) is the controller's
(:mod:`ovamos.services.base_driver.controller`).

* :meth:`ODriveCanHardware.open` opens the bus (again, after a bus error) and
  sends the enable sequence: Clear_Errors, Set_Limits, velocity control with
  the VEL_RAMP input mode, a zero setpoint, CLOSED_LOOP_CONTROL. It does not
  wait: the controller calls the base enabled once :meth:`feedback` is fresh
  (every axis heard since the open) and reports no fault (every axis in closed
  loop without errors), and faults after ``enable_timeout_s`` otherwise. On a
  bus that is already open, an axis silent for ``feedback_timeout_s`` makes
  ``open`` refuse (:class:`HardwareError`): no re-enabling while an ODrive is
  missing.
* :meth:`set_velocity` sends Set_Input_Vel to both axes; the controller calls
  it every control tick from its own thread (never ``send_periodic``: a hung
  process must stop feeding the ODrives' watchdogs).
* :meth:`feedback`: heartbeats and encoder estimates, decoded by a python-can
  ``Notifier`` thread under this object's lock; the stamp is the oldest of the
  axes' latest heartbeat / encoder estimate, so one silent axis makes the
  feedback stale. Axis errors (and, while the axes should be armed, an axis
  out of closed loop) are faults, named bit by bit, with the disarm reason
  once a Get_Error reply gave it. :meth:`stale_reason` says which axis is silent.
* :meth:`halt` (faults) sends IDLE, :meth:`estop` (the e-stop) Estop + IDLE.
  The controller calls them every tick while halted; they send again only if
  an axis reports itself armed after the last one (it missed the frames).
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field

import can

from ovamos.services.base_driver.config import DriverConfig
from ovamos.services.base_driver.hardware import HardwareDefaults, HardwareError, WheelFeedback
from ovamos.services.base_driver.kinematics import Geometry
from ovamos.services.base_driver.odrive.config import AxisConfig
from ovamos.services.base_driver.odrive.protocol import (
    AxisState,
    CanSimple,
    Cmd,
    ControlMode,
    Frame,
    InputMode,
    ProtocolError,
    error_names,
)

log = logging.getLogger("ovamos.base_driver.odrive")

BusFactory = Callable[[], can.BusABC]
_SEND_TIMEOUT_S = 0.05
_TWO_PI = 2 * math.pi


@dataclass
class _Axis:
    """What is known of one axis, from its heartbeats and encoder estimates on the current bus."""

    name: str
    config: AxisConfig
    state: AxisState | int | None = None
    errors: int = 0
    heartbeat_at: float | None = None
    encoder_at: float | None = None
    pos: float | None = None   # rev, in the wheel's forward direction
    vel: float = 0.0           # rev/s, idem
    disarm: str = ""           # the last Get_Error reply's disarm reason, while errors last
    error_requested: int = 0   # the errors a Get_Error was sent for (once per set of errors)

    @property
    def label(self) -> str:
        return f"{self.name} axis (node {self.config.node_id})"

    def problem(self) -> str:
        state = self.state.name if isinstance(self.state, AxisState) else self.state
        errors = ", ".join(error_names(self.errors)) or "no errors"
        text = f"{self.label} in state {state} ({errors})"
        return f"{text} (disarm reason: {self.disarm})" if self.disarm else text


@dataclass
class _Listener(can.Listener):
    """Feeds frames to the hardware; a receive error marks the bus dead and stops the reader."""

    hardware: ODriveCanHardware
    generation: int
    notifier: can.Notifier | None = field(default=None, repr=False)

    def on_message_received(self, msg: can.Message) -> None:
        self.hardware._on_frame(msg, self.generation)

    def on_error(self, exc: Exception) -> None:
        # Without this the Notifier would retry a dead bus in a tight loop (150k calls in 0.5 s).
        self.hardware._on_bus_error(f"CAN receive failed: {exc}", self.generation)
        if self.notifier is not None:
            self.notifier.stop(timeout=0)  # from its own thread: ends the loop, joins nothing

    def stop(self) -> None:
        pass


class ODriveCanHardware(HardwareDefaults):
    """See the module docstring. ``bus_factory`` defaults to ``can.Bus(**config.odrive.can)``."""

    name = "odrive_can"

    def __init__(self, config: DriverConfig, bus_factory: BusFactory | None = None,
                 clock: Callable[[], float] = time.monotonic, polled: bool = False) -> None:
        """``polled``: no reader thread; :meth:`feedback` takes the frames that have arrived
        (with ``clock``, how it runs in simulated time: :mod:`ovamos.shared.simtime`)."""
        self.config, self.clock, self.polled = config, clock, polled
        od = config.odrive
        self._factory = bus_factory or (lambda: can.Bus(**od.can.bus_kwargs()))
        self.protocol = CanSimple([od.left.node_id, od.right.node_id])
        self.geometry = Geometry(config.wheel_radius_m, config.track_width_m)
        self.axes = [_Axis("left", od.left), _Axis("right", od.right)]
        self._by_node = {a.config.node_id: a for a in self.axes}
        self._counters: Counter[str] = Counter()
        self._lock = threading.Lock()        # the reader thread's state (axes, bus error)
        self._bus: can.BusABC | None = None
        self._notifier: can.Notifier | None = None
        self._generation = 0
        self._bus_error: str | None = None
        self._armed = False                  # the enable sequence was sent and no halt since
        self._halted: str | None = None      # "idle" or "estop": what was sent since the last open
        self._halted_at = -math.inf

    # -- BaseHardware -----------------------------------------------------------------------------
    def open(self) -> None:
        with self._lock:
            healthy = self._bus is not None and self._bus_error is None
        if healthy:
            silent = self.stale_reason(self.clock())
            if silent:
                raise HardwareError(silent)
        else:
            self._reopen()
        self._armed, self._halted = True, None
        c = self.config
        self._send_to_all(Cmd.CLEAR_ERRORS, Identify=0)
        self._send_to_all(Cmd.SET_LIMITS, Velocity_Limit=c.max_wheel_rev_s * 1.1,
                          Current_Limit=c.odrive.current_limit_a)
        self._send_to_all(Cmd.SET_CONTROLLER_MODE, Control_Mode=ControlMode.VELOCITY_CONTROL,
                          Input_Mode=InputMode.VEL_RAMP)
        self._send_to_all(Cmd.SET_INPUT_VEL, Input_Vel=0.0, Input_Torque_FF=0.0)
        self._send_to_all(Cmd.SET_AXIS_STATE, Axis_Requested_State=AxisState.CLOSED_LOOP_CONTROL)
        self._raise_bus_error()

    def set_velocity(self, linear_m_s: float, angular_rad_s: float) -> None:
        self._raise_bus_error()
        left, right = self.geometry.wheels_rev_s(linear_m_s, angular_rad_s)
        for axis, wheel in zip(self.axes, (left, right)):
            self._send(self.protocol.encode(axis.config.node_id, Cmd.SET_INPUT_VEL,
                                            Input_Vel=axis.config.direction * wheel, Input_Torque_FF=0.0))
        self._raise_bus_error()

    def halt(self) -> None:
        self._disarm("idle")

    def estop(self) -> None:
        """The e-stop: Estop (the ODrive latches ESTOP_REQUESTED until Clear_Errors) and IDLE."""
        self._disarm("estop")

    def feedback(self) -> WheelFeedback | None:
        if self.polled:
            self._take_arrived()
        requests = []
        with self._lock:
            left, right = self.axes
            if any(a.heartbeat_at is None or a.encoder_at is None or a.pos is None for a in self.axes):
                return None
            faults = []
            for axis in self.axes:
                if axis.errors or (self._armed and axis.state is not AxisState.CLOSED_LOOP_CONTROL):
                    faults.append(axis.problem())
                if axis.errors and axis.errors != axis.error_requested:
                    axis.error_requested = axis.errors
                    requests.append(axis.config.node_id)
            stamp = min(min(a.heartbeat_at, a.encoder_at) for a in self.axes)  # type: ignore[type-var]
            fb = WheelFeedback(stamp=stamp, left_pos_rad=left.pos * _TWO_PI,  # type: ignore[operator]
                               right_pos_rad=right.pos * _TWO_PI,  # type: ignore[operator]
                               left_vel_rad_s=left.vel * _TWO_PI, right_vel_rad_s=right.vel * _TWO_PI,
                               faults=tuple(faults))
        for node in requests:  # why it disarmed: the reply adds the disarm reason to the fault
            self._send(self.protocol.request(node, Cmd.GET_ERROR))
        return fb

    def stale_reason(self, now: float) -> str:
        """Which axis is silent, and for how long ('' if none is)."""
        limit, problems = self.config.feedback_timeout_s, []
        with self._lock:
            for axis in self.axes:
                for what, at in (("heartbeat", axis.heartbeat_at), ("encoder estimates", axis.encoder_at)):
                    if at is None:
                        problems.append(f"no {what} from the {axis.label}")
                        break
                    if now - at > limit:
                        problems.append(f"no {what} from the {axis.label} for {now - at:.2f} s")
                        break
        return "; ".join(problems)

    def counters(self) -> dict[str, int]:
        return dict(self._counters)

    def close(self) -> None:
        self._send_all_idle()
        with self._lock:
            stale = self._detach()
        _close(*stale)

    # -- the bus ----------------------------------------------------------------------------------
    def _reopen(self) -> None:
        with self._lock:
            stale = self._detach()
        _close(*stale)  # outside the lock: the old reader may be waiting for it
        self._counters["bus_opens"] += 1
        try:
            bus = self._factory()
        except (can.CanError, OSError) as exc:
            raise HardwareError(f"CAN bus unavailable: {type(exc).__name__}: {exc}") from exc
        with self._lock:
            self._generation += 1
            listener = _Listener(self, self._generation)
            self._bus, self._bus_error = bus, None
            for axis in self.axes:  # only what is heard on this bus counts
                axis.heartbeat_at = axis.encoder_at = None
                axis.error_requested = 0
            if not self.polled:
                self._notifier = can.Notifier(bus, [listener], timeout=0.1)
                listener.notifier = self._notifier

    def _take_arrived(self) -> None:
        """Polled: handle the frames waiting on the bus."""
        bus, generation = self._bus, self._generation
        while bus is not None:
            try:
                msg = bus.recv(timeout=0)
            except (can.CanError, OSError) as exc:
                self._on_bus_error(f"CAN receive failed: {exc}", generation)
                return
            if msg is None:
                return
            self._on_frame(msg, generation)

    def _detach(self) -> tuple[can.Notifier | None, can.BusABC | None]:
        """Forget the bus (late frames from it are ignored); the caller closes what this returns
        after releasing the lock, since the reader thread may be waiting for that lock."""
        stale = self._notifier, self._bus
        self._notifier = self._bus = None
        self._generation += 1
        return stale

    def _raise_bus_error(self) -> None:
        with self._lock:
            if self._bus is None:
                raise HardwareError("CAN bus not open")
            if self._bus_error is not None:
                raise HardwareError(self._bus_error)

    def _on_bus_error(self, reason: str, generation: int) -> None:
        with self._lock:
            if generation != self._generation:
                return
            self._counters["reader_errors"] += 1
            if self._bus_error is None:
                self._counters["bus_errors"] += 1
                self._bus_error = reason

    def _send(self, msg: can.Message) -> bool:
        """Send one frame; a CAN error marks the bus dead (and is not raised)."""
        bus = self._bus
        if bus is None or self._bus_error is not None:
            return False
        try:
            bus.send(msg, timeout=_SEND_TIMEOUT_S)
        except (can.CanError, OSError) as exc:
            with self._lock:
                self._counters["bus_errors"] += 1
                if self._bus_error is None:
                    self._bus_error = f"CAN send failed: {type(exc).__name__}: {exc}"
            return False
        self._counters["frames_tx"] += 1
        return True

    def _send_to_all(self, cmd: Cmd, **signals: float) -> None:
        for axis in self.axes:
            self._send(self.protocol.encode(axis.config.node_id, cmd, **signals))

    def _send_all_idle(self) -> None:
        self._send_to_all(Cmd.SET_AXIS_STATE, Axis_Requested_State=AxisState.IDLE)

    def _disarm(self, kind: str) -> None:
        """Send IDLE (and Estop) unless already sent since the last open and no axis re-armed."""
        with self._lock:
            rearmed = any(a.state is AxisState.CLOSED_LOOP_CONTROL and a.heartbeat_at is not None
                          and a.heartbeat_at > self._halted_at for a in self.axes)
        self._armed = False
        if not rearmed and (self._halted == "estop" or self._halted == kind):
            return
        self._halted, self._halted_at = kind, self.clock()
        if kind == "estop":
            self._send_to_all(Cmd.ESTOP)
        self._send_all_idle()

    # -- incoming frames (the Notifier's thread) ------------------------------------------------
    def _on_frame(self, msg: can.Message, generation: int) -> None:
        try:
            frame = self.protocol.decode(msg)
        except ProtocolError as exc:
            n = self._counters[exc.kind] = self._counters[exc.kind] + 1
            if n & (n - 1) == 0:  # log the 1st, 2nd, 4th, 8th... only
                log.warning("ignored %s CAN frame (%d so far): %s", exc.kind, n, exc)
            return
        try:
            with self._lock:
                if generation == self._generation:
                    self._apply(frame, self.clock())
        except Exception:  # must not reach the Notifier: it would treat it as a bus error
            self._counters["handler_errors"] += 1
            log.exception("failed to handle %s", frame)

    def _apply(self, frame: Frame, now: float) -> None:
        self._counters["frames_rx"] += 1
        axis = self._by_node[frame.node_id]
        s, sign = frame.signals, axis.config.direction
        if frame.remote:
            self._counters["unexpected"] += 1  # requests are for the ODrives, not for us
        elif frame.cmd is Cmd.HEARTBEAT:
            state = int(s["Axis_State"])
            axis.state = AxisState(state) if state in AxisState._value2member_map_ else state
            axis.errors, axis.heartbeat_at = int(s["Axis_Error"]), now
            if not axis.errors:
                axis.disarm, axis.error_requested = "", 0
        elif frame.cmd is Cmd.GET_ENCODER_ESTIMATES:
            axis.pos, axis.vel = sign * s["Pos_Estimate"], sign * s["Vel_Estimate"]
            axis.encoder_at = now
        elif frame.cmd is Cmd.GET_ERROR:
            if s["Disarm_Reason"]:
                axis.disarm = ", ".join(error_names(int(s["Disarm_Reason"])))
        else:
            self._counters["unexpected"] += 1  # a command frame from another master on the bus


def _close(notifier: can.Notifier | None, bus: can.BusABC | None) -> None:
    """Stop a detached reader and shut its bus down (errors on a dead bus are expected)."""
    if notifier is not None:
        notifier.stop(timeout=1.0)
    if bus is not None:
        try:
            bus.shutdown()
        except (can.CanError, OSError):
            pass
