"""Simulated ODrive axes on a python-can ``virtual`` bus, in the driver's process.

They speak CANSimple frames encoded from the same DBC as the driver, so the
driver under test runs exactly as on a robot. Each axis models what the driver
relies on: the state machine (IDLE / CLOSED_LOOP_CONTROL, refused while errors
are active), velocity control with the ODrive's ramp, encoder integration,
the watchdog (fed by setpoints; expiry disarms the axis and sets
WATCHDOG_TIMER_EXPIRED), Estop, Clear_Errors, and the cyclic messages
(heartbeat every 100 ms, encoder estimates every 10 ms) plus answers to
remote requests.

Faults can be injected: dropped heartbeats, error bits (``sticky`` ones come
back after Clear_Errors, like a hardware fault), and bus off, which makes the
driver's bus (opened with :meth:`SimODrives.open_driver_bus`) fail every
send and receive, and re-opening it fail, until the bus is back.

A ``physics`` hook, called after every integration step with each axis'
position change, lets the simulated robot move with the wheels; it returns
False when the robot is blocked, which stalls the wheels (the step's motion is
undone), as a motor pushing against a wall would.
"""

from __future__ import annotations

import logging
import threading
import time
import uuid
from collections.abc import Callable, Iterable
from typing import Any

import can
from can.interfaces.virtual import VirtualBus

from ovamos.services.base_driver.kinematics import toward
from ovamos.services.base_driver.odrive.config import SimAxisConfig
from ovamos.services.base_driver.odrive.protocol import (
    AxisState,
    CanSimple,
    Cmd,
    ControlMode,
    Frame,
    InputMode,
    ODriveError,
    ProtocolError,
)

log = logging.getLogger("ovamos.odrive_sim")

#: physics(dt_s, {node_id: position change in rev}) -> False when the robot is blocked
Physics = Callable[[float, dict[int, float]], bool]


class BusFaults:
    """The injected state of the wire, shared by the buses it affects."""

    def __init__(self) -> None:
        self.off = False


class FaultableVirtualBus(VirtualBus):
    """python-can's virtual bus, failing like a controller in bus-off while ``faults.off``.

    Receives fail at once (no blocking), which is the worst case for a reader
    loop: a python-can ``Notifier`` would call its listeners' ``on_error`` in a
    tight loop unless they stop it.
    """

    def __init__(self, channel: Any, faults: BusFaults, **kwargs: Any) -> None:
        super().__init__(channel=channel, **kwargs)
        self._faults = faults

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        if self._faults.off:
            raise can.CanOperationError("bus off (injected): frame not sent")
        super().send(msg, timeout)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        if self._faults.off:
            raise can.CanOperationError("bus off (injected): cannot receive")
        return super()._recv_internal(timeout)


class SimAxis:
    """One simulated ODrive axis (see the module docstring); not thread-safe on its own."""

    def __init__(self, node_id: int, config: SimAxisConfig, now: float) -> None:
        self.node_id, self.config = node_id, config
        self.state = AxisState.IDLE
        self.errors = 0
        self.sticky_errors = 0
        self.disarm_reason = 0
        self.control_mode = ControlMode.VELOCITY_CONTROL
        self.input_mode = InputMode.PASSTHROUGH
        self.input_vel = 0.0
        self.vel = 0.0
        self.pos = 0.0
        self.vel_limit = config.vel_limit_rev_s
        self.current_limit = 10.0
        self.last_feed = now
        self.heartbeats = True

    @property
    def armed(self) -> bool:
        return self.state is AxisState.CLOSED_LOOP_CONTROL

    def fail(self, bits: int) -> None:
        """Set error bits and disarm, as the firmware does on any axis error."""
        self.errors |= bits
        self.disarm_reason = self.errors
        self.state = AxisState.IDLE

    def handle(self, frame: Frame, now: float) -> tuple[Cmd, dict[str, float]] | None:
        """Apply one frame addressed to this axis; the reply to send, if any."""
        s = frame.signals
        if frame.remote:
            if frame.cmd is Cmd.GET_ERROR:
                return Cmd.GET_ERROR, {"Active_Errors": self.errors, "Disarm_Reason": self.disarm_reason}
            if frame.cmd is Cmd.GET_ENCODER_ESTIMATES:
                return Cmd.GET_ENCODER_ESTIMATES, self.estimates()
            return None
        if frame.cmd is Cmd.SET_AXIS_STATE:
            requested = int(s["Axis_Requested_State"])
            if requested == AxisState.CLOSED_LOOP_CONTROL and not self.errors:
                self.state, self.last_feed = AxisState.CLOSED_LOOP_CONTROL, now
            elif requested == AxisState.IDLE:
                self.state = AxisState.IDLE
        elif frame.cmd is Cmd.ESTOP:
            self.fail(ODriveError.ESTOP_REQUESTED)
        elif frame.cmd is Cmd.CLEAR_ERRORS:
            self.errors = self.sticky_errors
        elif frame.cmd is Cmd.SET_INPUT_VEL:
            self.input_vel = max(-self.vel_limit, min(self.vel_limit, float(s["Input_Vel"])))
            self.last_feed = now
        elif frame.cmd is Cmd.SET_LIMITS:
            self.vel_limit, self.current_limit = float(s["Velocity_Limit"]), float(s["Current_Limit"])
        elif frame.cmd is Cmd.SET_CONTROLLER_MODE:
            self.control_mode = ControlMode(int(s["Control_Mode"]))
            self.input_mode = InputMode(int(s["Input_Mode"]))
        return None

    def step(self, now: float, dt: float) -> float:
        """Advance ``dt`` seconds; returns the position change (rev)."""
        c = self.config
        if self.armed and c.watchdog_timeout_s > 0 and now - self.last_feed > c.watchdog_timeout_s:
            self.fail(ODriveError.WATCHDOG_TIMER_EXPIRED)
        v0 = self.vel
        if self.armed and self.control_mode is ControlMode.VELOCITY_CONTROL:
            if self.input_mode is InputMode.VEL_RAMP:
                self.vel = toward(v0, self.input_vel, c.vel_ramp_rate_rev_s2 * dt)
            else:
                self.vel = self.input_vel
        else:
            self.vel = toward(v0, 0.0, c.idle_decel_rev_s2 * dt)
        delta = (v0 + self.vel) / 2 * dt
        self.pos += delta
        return delta

    def stall(self, delta: float) -> None:
        """Undo a step's motion: the wheel could not turn."""
        self.pos -= delta
        self.vel = 0.0

    def heartbeat(self) -> dict[str, float]:
        return {"Axis_Error": self.errors, "Axis_State": int(self.state), "Procedure_Result": 0,
                "Trajectory_Done_Flag": 1}

    def estimates(self) -> dict[str, float]:
        return {"Pos_Estimate": self.pos, "Vel_Estimate": self.vel}


class SimODrives:
    """Simulated axes answering on one virtual CAN channel, run by one thread."""

    def __init__(self, node_ids: Iterable[int], channel: str | None = None,
                 config: SimAxisConfig | None = None, physics: Physics | None = None,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.config = config or SimAxisConfig()
        self.channel = channel or f"ovamos-sim-{uuid.uuid4().hex[:8]}"
        self.physics, self.clock = physics, clock
        now = clock()
        self.axes = {n: SimAxis(n, self.config, now) for n in node_ids}
        self.protocol = CanSimple(self.axes)
        self.faults = BusFaults()
        self.lock = threading.Lock()
        self.frames_in = 0
        self._bus = VirtualBus(channel=self.channel)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"odrive-sim:{self.channel}", daemon=True)
        self._reset_schedule()

    # -- life cycle -----------------------------------------------------------------------------
    def start(self) -> SimODrives:
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(5)
        self._bus.shutdown()

    def __enter__(self) -> SimODrives:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def open_driver_bus(self) -> can.BusABC:
        """A bus on this channel for the driver; fails while the bus is off (injected)."""
        if self.faults.off:
            raise can.CanInitializationError("bus off (injected): cannot open the CAN interface")
        return FaultableVirtualBus(self.channel, self.faults)

    # -- fault injection --------------------------------------------------------------------------
    def set_bus_off(self, off: bool) -> None:
        self.faults.off = off

    def drop_heartbeats(self, node_id: int, drop: bool = True) -> None:
        with self.lock:
            self.axes[node_id].heartbeats = not drop

    def inject_error(self, node_id: int, bits: int, *, sticky: bool = False) -> None:
        with self.lock:
            axis = self.axes[node_id]
            if sticky:
                axis.sticky_errors |= bits
            axis.fail(bits)

    def clear_injected(self, node_id: int) -> None:
        """The hardware fault is repaired: sticky errors go at the next Clear_Errors."""
        with self.lock:
            self.axes[node_id].sticky_errors = 0

    # -- the simulation thread --------------------------------------------------------------------
    def _run(self) -> None:
        self._reset_schedule()
        while not self._stop.is_set():
            wait = max(0.0, min(*self._due_enc.values(), *self._due_hb.values()) - self.clock())
            msg = self._bus.recv(timeout=min(wait, 0.005))
            if msg is not None:
                self._receive(msg)
            self.tick()

    def _reset_schedule(self) -> None:
        now = self._last = self.clock()
        self._due_enc = {n: now for n in self.axes}
        self._due_hb = {n: now for n in self.axes}

    def tick(self) -> None:
        """Answer what has arrived, move the axes up to now, send the estimates and heartbeats
        that are due (the thread's loop; in simulated time the benchmark calls it)."""
        c = self.config
        msg = self._bus.recv(timeout=0)
        while msg is not None:
            self._receive(msg)
            msg = self._bus.recv(timeout=0)
        now = self.clock()
        with self.lock:
            self._step(now, now - self._last)
            self._last = now
            out: list[can.Message] = []
            for n, axis in self.axes.items():
                if now >= self._due_enc[n]:
                    out.append(self.protocol.encode(n, Cmd.GET_ENCODER_ESTIMATES, **axis.estimates()))
                    self._due_enc[n] = max(self._due_enc[n] + c.encoder_period_s, now)
                if now >= self._due_hb[n]:
                    if axis.heartbeats:
                        out.append(self.protocol.encode(n, Cmd.HEARTBEAT, **axis.heartbeat()))
                    self._due_hb[n] = max(self._due_hb[n] + c.heartbeat_period_s, now)
        for frame in out:
            self._bus.send(frame)

    def _step(self, now: float, dt: float) -> None:
        if dt <= 0:
            return
        deltas = {n: axis.step(now, dt) for n, axis in self.axes.items()}
        if self.physics is not None and not self.physics(dt, deltas):
            for n, axis in self.axes.items():
                axis.stall(deltas[n])

    def _receive(self, msg: can.Message) -> None:
        try:
            frame = self.protocol.decode(msg)
        except ProtocolError:
            return  # frames for other nodes (or garbage): a real ODrive ignores them too
        self.frames_in += 1
        with self.lock:
            reply = self.axes[frame.node_id].handle(frame, self.clock())
        if reply is not None:
            self._bus.send(self.protocol.encode(frame.node_id, reply[0], **reply[1]))
