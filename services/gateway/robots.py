"""What the gateway knows of each robot right now: its driver state and pose, its planner's latest
decision, and its e-stop.

The operator's page shows the driver state next to the E-STOP button and the robot's pose on
the map whether or not a task runs, so the gateway follows ``driver/state`` and ``odom`` of
every robot it serves (:data:`ovamos.shared.topology.TOPOLOGY`) and keeps the latest of each,
of the robot's driver's odometry session only (:mod:`ovamos.shared.sessions`, as every consumer
of odometry): a forged stream of another session never reaches the page, nor confirms an e-stop.
The page draws the candidates the planner weighed at its latest decision (``plan_trace``), never
a recomputation: a planner with other settings (ovamos-plus) weighs other ones.
No Zenoh and no bus here: the gateway's adapter (:mod:`ovamos.services.gateway.service`)
feeds :meth:`RobotMonitor.on_driver_state` and :meth:`RobotMonitor.on_odom`, and hands the
monitor what it sends e-stop requests with.

The e-stop is a safety function, so a request is not answered "sent" but "confirmed": the
gateway publishes on ``driver/estop`` (a clear on ``driver/estop/clear``) and re-sends every ``estop_resend_s`` (a single Zenoh put
can be lost) until a driver state received after the first send shows the latch as wanted,
for at most ``estop_confirm_s``. A driver that never confirms is an error the person must
see (the robot may still be moving), never a silent success.

Threads: the ``on_*`` inputs run on the bus's inbox taker (the gateway's owner thread); HTTP
worker threads read, and wait for a confirmation, under one condition variable that is held
for no I/O.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Generic, TypeVar

from ovamos.services.gateway.config import GatewayConfig
from ovamos.shared.messages import DecisionTrace, DriverState, EStop, Odometry
from ovamos.shared.sessions import SessionFollower

__all__ = ["RobotMonitor", "Latest", "EStopUnconfirmed"]

ESTOP_SOURCE = "gateway"

M = TypeVar("M")
Send = Callable[[str, EStop], None]
"""Send an e-stop request to a robot (``send(robot_id, request)``)."""


@dataclass(frozen=True)
class Latest(Generic[M]):
    """The newest message of one kind from one robot, when it came (``time.monotonic()``) and how
    many came before it (so a waiter can ask for one received after a given moment)."""

    message: M
    received: float
    count: int

    def age_s(self) -> float:
        return time.monotonic() - self.received


class EStopUnconfirmed(RuntimeError):
    """The driver did not report the wanted e-stop latch in time; the message says what is known."""


class RobotMonitor:
    """The latest driver state, odometry and planner decision of each robot, and its e-stop requests."""

    def __init__(self, config: GatewayConfig, *, estop: Send, estop_clear: Send) -> None:
        """``estop`` sends on the robot's ``driver/estop``, ``estop_clear`` on ``driver/estop/clear``."""
        self.config = config
        self._send_estop, self._send_clear = estop, estop_clear
        self._changed = threading.Condition()
        self._driver: dict[str, Latest[DriverState]] = {}
        self._odom: dict[str, Latest[Odometry]] = {}
        self._traces: dict[str, DecisionTrace] = {}
        self.sessions: dict[str, SessionFollower] = {}  # per robot

    # -- inputs (the owner thread) ----------------------------------------------------------------
    def on_driver_state(self, robot: str, state: DriverState) -> None:
        self._keep(self._driver, robot, state, ("driver_state", state.odom_session, state.stamp))

    def on_odom(self, robot: str, odom: Odometry) -> None:
        self._keep(self._odom, robot, odom, ("odom", odom.odom_session, odom.seq))

    def on_plan_trace(self, robot: str, trace: DecisionTrace) -> None:
        with self._changed:
            self._traces[robot] = trace

    def decision(self, robot: str, task_id: str) -> DecisionTrace | None:
        """The planner's latest decision for task ``task_id`` (None before its first)."""
        with self._changed:
            trace = self._traces.get(robot)
        return trace if trace is not None and trace.task_id == task_id else None

    def _keep(self, table: dict[str, Latest[M]], robot: str, message: M, stream: tuple[str, str, float]) -> None:
        """Keep ``message`` when ``stream`` (its stream, session and order) is of the robot's session."""
        with self._changed:
            follower = self.sessions.get(robot)
            if follower is None:
                follower = self.sessions[robot] = SessionFollower(self.config.session_switch)
            if not follower.observe(*stream):
                return
            before = table.get(robot)
            table[robot] = Latest(message, time.monotonic(), 1 if before is None else before.count + 1)
            self._changed.notify_all()

    def driver(self, robot: str) -> Latest[DriverState] | None:
        with self._changed:
            return self._driver.get(robot)

    def odometry(self, robot: str) -> Latest[Odometry] | None:
        with self._changed:
            return self._odom.get(robot)

    # -- the e-stop (HTTP worker threads: they wait here) -----------------------------------------
    def engage_estop(self, robot: str, reason: str) -> DriverState:
        """Latch the robot's e-stop; the driver state that confirms it. EStopUnconfirmed when the
        driver did not report it latched within ``estop_confirm_s``."""
        return self._estop_until(self._send_estop, robot,
                                 EStop(engage=True, source=ESTOP_SOURCE, reason=reason, stamp=time.time()))

    def clear_estop(self, robot: str) -> DriverState:
        """Release the robot's e-stop latch; the driver state that confirms it (EStopUnconfirmed
        as for :meth:`engage_estop`)."""
        return self._estop_until(self._send_clear, robot,
                                 EStop(engage=False, source=ESTOP_SOURCE, stamp=time.time()))

    def _estop_until(self, send: Send, robot: str, request: EStop) -> DriverState:
        deadline = time.monotonic() + self.config.estop_confirm_s
        with self._changed:
            first = self._driver.get(robot)
        after = 0 if first is None else first.count  # only a state received after the first send
        sends = 0
        while True:
            send(robot, request.model_copy(update={"stamp": time.time()}))
            sends += 1
            resend_at = min(time.monotonic() + self.config.estop_resend_s, deadline)
            with self._changed:
                while True:
                    latest = self._driver.get(robot)
                    if (latest is not None and latest.count > after
                            and latest.message.estop_latched == request.engage):
                        return latest.message
                    left = resend_at - time.monotonic()
                    if left <= 0:
                        break
                    self._changed.wait(left)
            if time.monotonic() >= deadline:
                raise EStopUnconfirmed(self._unconfirmed(robot, request, sends))

    def _unconfirmed(self, robot: str, request: EStop, sends: int) -> str:
        latest = self.driver(robot)
        action = "engage" if request.engage else "clear"
        if latest is None:
            known = "no driver state has ever been received from it"
        else:
            known = (f"its last driver state, {latest.age_s():.1f} s old, says mode "
                     f"{latest.message.mode.value}, e-stop "
                     f"{'latched' if latest.message.estop_latched else 'not latched'}")
        warning = " The robot may still be moving: use its hardware stop." if request.engage else ""
        return (f"e-stop {action} sent to robot {robot!r} {sends} times in "
                f"{self.config.estop_confirm_s:g} s but its driver did not confirm it: {known}.{warning}")
