"""The task life cycle on the gateway's side, and its Zenoh wiring (``task/current``, ``task/events``).

Per robot: tasks wait in a queue (``queued``), one at a time is ``searching``,
and it ends ``done`` / ``failed`` (reported by the planner) or ``cancelled``
(by a person); then the next queued task starts. The active task's TaskSpec is
re-sent every ``republish_s`` because a single Zenoh put can be lost (a
planner that starts later, or reconnects after a router restart, still gets
it); a cancelled one is re-sent for ``cancel_linger_s`` for the same reason.

Planner events for a task that is not the robot's active one (unknown, queued,
already finished, another robot's) are counted and ignored: a late event must
never reopen a finished task. Malformed payloads are counted by the bus.

Thread safety: called from HTTP worker threads, Zenoh callback threads and the
re-publisher; one lock serialises every state change.
"""

from __future__ import annotations

import threading
import time
from collections import Counter
from collections.abc import Callable

from services.gateway.config import GatewayConfig
from services.gateway.store import TaskRecord, TaskStore
from shared import keys
from shared.bus import Bus, Publisher
from shared.messages import TaskEvent, TaskSpec, TaskStatus

FINAL = (TaskStatus.DONE, TaskStatus.FAILED, TaskStatus.CANCELLED)

Notify = Callable[[TaskRecord], None]


class TaskConflict(RuntimeError):
    """An operation the task's state does not allow (e.g. cancelling a finished task)."""


class TaskManager:
    """Owns the per-robot queues; every change is stored first, then published and notified."""

    def __init__(self, bus: Bus, store: TaskStore, config: GatewayConfig,
                 notify: Notify = lambda _record: None) -> None:
        self.bus, self.store, self.config = bus, store, config
        self._notify = notify
        self._lock = threading.RLock()
        self._counters: Counter[str] = Counter()
        self._publishers: dict[str, Publisher[TaskSpec]] = {}
        self._cancelled: dict[str, tuple[TaskSpec, float]] = {}  # robot -> (spec, re-send until)

    def start(self) -> None:
        """Declare the keys, then resume: start queued tasks where no task is active."""
        for robot in self.config.robots:
            self._publishers[robot] = self.bus.publisher(keys.task_current(robot), TaskSpec)
            self.bus.subscribe(keys.task_events(robot), TaskEvent,
                               lambda event, robot=robot: self.on_event(robot, event))
        with self._lock:
            for robot in self.config.robots:
                if self.store.active(robot) is None:
                    self._start_next(robot)

    # -- requests ------------------------------------------------------------------------------
    def submit(self, robot_id: str, targets: list[str], max_steps: int) -> TaskRecord:
        with self._lock:
            record = self.store.add(robot_id, targets, max_steps)
            if self.store.active(robot_id) is None:
                self._start_next(robot_id)
            return self._get(record.id)

    def cancel(self, task_id: str) -> TaskRecord | None:
        """Cancel a queued or searching task; None if unknown, TaskConflict if already over."""
        with self._lock:
            record = self.store.get(task_id)
            if record is None:
                return None
            if record.status in FINAL:
                raise TaskConflict(f"task {task_id} is already {record.status.value}")
            self.store.finish(task_id, TaskStatus.CANCELLED, "cancelled by request")
            if record.status is TaskStatus.SEARCHING:
                spec = _spec(record, cancelled=True)
                self._cancelled[record.robot_id] = (spec, time.monotonic() + self.config.cancel_linger_s)
                self._publishers[record.robot_id].put(spec)
            self._changed(task_id)
            if record.status is TaskStatus.SEARCHING:
                self._start_next(record.robot_id)
            else:
                self._notify_queue(record.robot_id)
            return self._get(task_id)

    # -- planner events ------------------------------------------------------------------------
    def on_event(self, robot_id: str, event: TaskEvent) -> None:
        """Apply a planner report to the robot's active task (others are counted and ignored)."""
        with self._lock:
            record = self.store.get(event.task_id)
            if record is None:
                self._counters["events_unknown_task"] += 1
                return
            if record.status in FINAL:
                self._counters["events_finished_task"] += 1
                return
            if record.robot_id != robot_id or record.status is not TaskStatus.SEARCHING:
                self._counters["events_not_active"] += 1
                return
            position = (event.x, event.y) if event.x is not None and event.y is not None else None
            self.store.progress(record.id, found=event.found, steps=event.steps,
                                distance_m=event.distance_m, message=event.message, position=position)
            self._counters["events_applied"] += 1
            if event.status in FINAL:
                self.store.finish(record.id, event.status)
                self._changed(record.id)
                self._start_next(robot_id)
            else:
                self._changed(record.id)

    # -- periodic ------------------------------------------------------------------------------
    def republish(self) -> None:
        """Re-send each robot's current TaskSpec (and a recently cancelled one)."""
        now = time.monotonic()
        with self._lock:
            for robot, publisher in self._publishers.items():
                if robot in self._cancelled:
                    spec, until = self._cancelled[robot]
                    if now <= until:
                        publisher.put(spec.model_copy(update={"stamp": time.time()}))
                    else:
                        del self._cancelled[robot]
                active = self.store.active(robot)
                if active is not None:
                    publisher.put(_spec(active))

    def count_rejected_request(self, status_code: int) -> None:
        with self._lock:
            self._counters[f"http_{status_code}"] += 1

    def counters(self) -> dict[str, int]:
        """Event bookkeeping, malformed payloads the bus dropped on ``task/events``, and refused
        HTTP requests by status (``http_422``: 1, ...)."""
        with self._lock:
            out = {name: self._counters[name] for name in
                   ("events_applied", "events_unknown_task", "events_finished_task", "events_not_active")}
            out.update(sorted((k, n) for k, n in self._counters.items() if k.startswith("http_")))
        bus_counters = self.bus.counters.snapshot()
        out["events_malformed"] = sum(bus_counters[k].malformed for k in bus_counters
                                      if k in {keys.task_events(r) for r in self.config.robots})
        return out

    # -- internals (caller holds the lock) -----------------------------------------------------
    def _start_next(self, robot_id: str) -> None:
        record = self.store.next_queued(robot_id)
        if record is not None:
            self.store.start(record.id)
            record = self._get(record.id)
            self._publishers[robot_id].put(_spec(record))
            self.bus.log.info("task %s started on %s: %s", record.id, robot_id, ", ".join(record.targets))
            self._notify(record)
        self._notify_queue(robot_id)

    def _notify_queue(self, robot_id: str) -> None:
        """Queued tasks moved up: their watchers see the new queue position."""
        for record in self.store.list(robot_id, TaskStatus.QUEUED, limit=1000):
            self._notify(record)

    def _changed(self, task_id: str) -> None:
        self._notify(self._get(task_id))

    def _get(self, task_id: str) -> TaskRecord:
        record = self.store.get(task_id)
        assert record is not None, task_id
        return record


def _spec(record: TaskRecord, cancelled: bool = False) -> TaskSpec:
    return TaskSpec(task_id=record.id, targets=tuple(record.targets), max_steps=record.max_steps,
                    cancelled=cancelled, stamp=time.time())
