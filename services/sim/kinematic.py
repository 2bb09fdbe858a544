"""The simplest base of the simulator: a primitive is executed at once (exactly, unless the robot's odometry errs).

Used for lock-step runs that must be deterministic (same seed, same
trajectory in one process or over Zenoh) and for fast demos; the ``odrive``
motion mode runs the real driver instead. It keeps the driver's contract: an
action id executes once, an e-stop latches until cleared and rejects commands
meanwhile. Velocity (teleop) and path commands need a wheeled mode and are rejected.
"""

from __future__ import annotations

import threading
import time
from collections import Counter, deque

from ovamos.services.sim.robot import SimRobot
from ovamos.shared.messages import DriverMode, DriverState, Odometry, Outcome, PlanCommand, new_odom_session
from ovamos.shared.motion import ActionIds


class KinematicBase:
    """Commands are queued by :meth:`submit` (any thread) and run by :meth:`execute` (the tick)."""

    def __init__(self, robot: SimRobot) -> None:
        self.robot = robot
        self.counters: Counter[str] = Counter()
        self._lock = threading.Lock()
        self._pending: deque[PlanCommand] = deque()
        self._action_ids = ActionIds()
        self._primitives = robot.config.primitives  # advertised in every state
        self._estop: str | None = None
        self._completed: tuple[int, Outcome | None] = (0, None)  # last command that ended, how
        self.odom_session = new_odom_session()  # odometry (the true pose) starts here, once per process
        self._odom_seq = 0

    def submit(self, command: PlanCommand) -> str:
        with self._lock:
            if not self._action_ids.take(command.action_id):
                self.counters["duplicates"] += 1
                return "duplicate"
            if self._estop is not None or command.action is None:
                self.counters["rejected"] += 1
                self._completed = (command.action_id, "rejected")
                return "rejected"
            self._pending.append(command)
            return "accepted"

    def execute(self) -> bool:
        """Run the queued primitives; True when any completed."""
        ran = False
        while True:
            with self._lock:
                if not self._pending or self._estop is not None:
                    return ran
                command = self._pending.popleft()
                assert command.action is not None
                outcome: Outcome = "done" if self.robot.apply(command.action) else "blocked"
                self._completed = (command.action_id, outcome)
                self.counters[outcome] += 1
                ran = True

    def engage_estop(self, source: str, reason: str = "") -> None:
        with self._lock:
            self._estop = f"e-stop by {source}" + (f": {reason}" if reason else "")
            for command in self._pending:
                self._completed = (command.action_id, "aborted")
            self._pending.clear()

    def clear_estop(self, source: str) -> None:
        with self._lock:
            self._estop = None

    def state(self) -> DriverState:
        with self._lock:
            mode = (DriverMode.ESTOP if self._estop else DriverMode.MOVING if self._pending
                    else DriverMode.READY)
            action_id, outcome = self._completed
            return DriverState(stamp=time.time(), mode=mode, odom_session=self.odom_session,
                               faults=(self._estop,) if self._estop else (),
                               estop_latched=self._estop is not None,
                               active_action=self._pending[0].action_id if self._pending else None,
                               last_completed=action_id, last_outcome=outcome,
                               primitives=self._primitives)

    has_pose = True  # an ideal base knows its pose from the start

    def odometry(self) -> Odometry:
        """What the wheels report: the true pose unless the robot's odometry errs."""
        with self._lock:
            p = self.robot.odom
            self._odom_seq += 1
            return Odometry(seq=self._odom_seq, stamp=time.time(), odom_session=self.odom_session,
                            x=p.x, y=p.y, yaw=p.yaw, after_action=self._completed[0])

    def info(self) -> dict[str, object]:
        with self._lock:
            return {"motion": "kinematic", "pending": len(self._pending), "counters": dict(self.counters)}

    def stop(self) -> None:
        pass
