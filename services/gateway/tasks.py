"""The task life cycle on the gateway's side: requests and planner events in, TaskSpecs out.

No Zenoh and no bus here: the gateway's adapter (:mod:`ovamos.services.gateway.service`)
feeds planner events to :meth:`TaskManager.on_event` and hands the manager what it sends
with (``publish``, one robot's ``task/current``) and the inbox whose taker owns it.

Per robot: tasks wait in a queue (``queued``), one at a time is ``searching``,
and it ends ``done`` / ``failed`` (reported by the planner) or ``cancelled``
(by a person); then the next queued task starts. The active task's TaskSpec is
re-sent every ``republish_s`` because a single Zenoh put can be lost (a
planner that starts later, or reconnects after a router restart, still gets
it), with the progress the planner last reported (steps, distance, found), from
which a restarted planner goes on; a cancelled one is re-sent for
``cancel_linger_s`` for the same reason.

Planner events for a task that is not the robot's active one (unknown, queued,
already finished, another robot's) are counted and ignored: a late event must
never reopen a finished task. Malformed payloads are counted by the bus.

Threads: one thread owns the task state and makes every change, the taker of
the bus's inbox (:mod:`ovamos.shared.inbox`): the service's main thread under
``ovamos run gateway``, the bus's dispatcher thread when the app was given a
bus of its own. Planner events reach it through the inbox (Zenoh's callback
threads only enqueue them); an HTTP worker thread hands it a submit or cancel
and waits for the answer (never the asyncio event loop: the routes doing so are
plain ``def``); the re-publish timer only enqueues a round. So changes need no
lock and happen in one order, each committed to the store on that thread,
while HTTP reads use the store's read connections and never wait for a commit.
The counters are the only state other threads touch, behind a lock held for
no I/O (the event loop bumps them for refused requests).

Timers are monotonic: the re-publish period runs on the event loop's clock and
a cancelled TaskSpec's linger on ``time.monotonic()``; wall-clock time only
stamps what is stored or shown.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import Counter
from collections.abc import Callable
from concurrent.futures import CancelledError, Future
from typing import Any, TypeVar

from ovamos.services.gateway.config import GatewayConfig
from ovamos.services.gateway.store import TaskRecord, TaskStore
from ovamos.shared.inbox import Inbox
from ovamos.shared.messages import FINAL, Goal, TaskEvent, TaskSpec, TaskStatus

__all__ = ["TaskManager", "TaskConflict", "GatewayBusy"]

Notify = Callable[[TaskRecord], None]
Publish = Callable[[str, TaskSpec], None]
"""Send a robot's TaskSpec (``publish(robot_id, spec)``) on its ``task/current``."""
T = TypeVar("T")

REPUBLISH_CHANNEL = "gateway:republish"  # an inbox channel, not a key: rounds not yet run collapse
OWNER_WAIT_S = 30.0  # an HTTP request waits this long for the owner thread before a 503


class TaskConflict(RuntimeError):
    """An operation the task's state does not allow (e.g. cancelling a finished task)."""


class GatewayBusy(RuntimeError):
    """The owner thread did not take a request in time, or the gateway is stopping; the request
    changed nothing."""


class TaskManager:
    """Owns the per-robot queues; every change is stored first, then published and notified."""

    wait_s = OWNER_WAIT_S

    def __init__(self, store: TaskStore, config: GatewayConfig, *, inbox: Inbox, publish: Publish,
                 notify: Notify, log: logging.Logger, record_failure: Callable[[str], None],
                 malformed_events: Callable[[], int]) -> None:
        """``inbox``: its taker is the owner thread. ``record_failure(what)`` logs and counts the
        exception being handled; ``malformed_events()`` counts the planner events the bus could not
        decode (both the bus's, which keeps those counters)."""
        self.store, self.config = store, config
        self._inbox, self._publish, self._log = inbox, publish, log
        self._record_failure, self._malformed_events = record_failure, malformed_events
        self._notify = notify  # called on the owner thread after each committed change
        self._counters_lock = threading.Lock()
        self._counters: Counter[str] = Counter()
        # robot -> (cancelled spec, re-send until on time.monotonic())
        self._cancelled: dict[str, tuple[TaskSpec, float]] = {}
        self._waiting_lock = threading.Lock()
        self._waiting: set[Future[Any]] = set()  # requests handed to the owner thread, not answered
        self._closed = False
        # robot -> (task id, the planner's goal in its latest event): live state, not stored (the
        # event's odometry session is, with the position); replaced whole on the owner thread,
        # read by HTTP threads (one dict item, no lock needed)
        self._live: dict[str, tuple[str, Goal | None]] = {}

    def start(self) -> None:
        """Queue the resume (queued tasks start where no task is active); called before planner
        events are subscribed to, so it runs ahead of every event and request."""
        self._inbox.put(self._guarded(self._resume, "resume"), None)

    def close(self) -> None:
        """Refuse further requests and release those still waiting for the owner thread (they
        get GatewayBusy; what the owner already runs completes). Any thread."""
        with self._waiting_lock:
            self._closed = True
            waiting = list(self._waiting)
        for future in waiting:
            future.cancel()

    def _resume(self) -> None:
        for robot in self.config.robots:
            if self.store.active(robot) is None:
                self._start_next(robot)

    # -- requests (HTTP worker threads: the change runs on the owner thread, they wait) ----------
    def submit(self, robot_id: str, targets: list[str], max_steps: int) -> TaskRecord:
        """Queue a task (it starts at once when the robot is idle); committed when this returns."""
        return self._on_owner(self._submit, robot_id, targets, max_steps)

    def cancel(self, task_id: str) -> TaskRecord | None:
        """Cancel a queued or searching task; None if unknown, TaskConflict if already over."""
        return self._on_owner(self._cancel, task_id)

    def request_republish(self) -> None:
        """Queue a re-publish round (any thread, never blocks; rounds the owner has not reached
        yet collapse into one)."""
        self._inbox.put(self._guarded(self.republish, "republish"), None,
                        channel=REPUBLISH_CHANNEL, keep=1)

    def _on_owner(self, fn: Callable[..., T], *args: Any) -> T:
        """``fn(*args)`` run on the owner thread; its result or exception, once it ran.

        GatewayBusy when the owner did not take it within ``wait_s`` or the gateway
        stops first; then it never runs, so the caller may safely say nothing changed.
        """
        if threading.get_ident() == self._inbox.owner:
            return fn(*args)  # already on the owner: waiting for ourselves would never end
        future: Future[T] = Future()

        def run(_: object) -> None:
            if not future.set_running_or_notify_cancel():
                return  # given up by the caller or by close(): must not run
            try:
                future.set_result(fn(*args))
            except BaseException as exc:  # the caller re-raises it (TaskConflict, a store error)
                future.set_exception(exc)

        with self._waiting_lock:
            if self._closed or self._inbox.closed:
                raise GatewayBusy("the gateway is shutting down")
            self._waiting.add(future)
        try:
            self._inbox.put(run, None, on_drop=future.cancel)
            try:
                return future.result(self.wait_s)
            except TimeoutError:
                if future.cancel():
                    raise GatewayBusy(f"the gateway did not get to the request within {self.wait_s} s; "
                                      "nothing was changed, try again") from None
                return future.result()  # it started in the meantime: it finishes
        except CancelledError:
            raise GatewayBusy("the gateway is shutting down; nothing was changed") from None
        finally:
            with self._waiting_lock:
                self._waiting.discard(future)

    # -- state changes (owner thread) ----------------------------------------------------------
    def _submit(self, robot_id: str, targets: list[str], max_steps: int) -> TaskRecord:
        record = self.store.add(robot_id, targets, max_steps)
        if self.store.active(robot_id) is None:
            self._start_next(robot_id)
        return self._get(record.id)

    def _cancel(self, task_id: str) -> TaskRecord | None:
        record = self.store.get(task_id)
        if record is None:
            return None
        if record.status in FINAL:
            raise TaskConflict(f"task {task_id} is already {record.status.value}")
        self.store.finish(task_id, TaskStatus.CANCELLED, "cancelled by request")
        if record.status is TaskStatus.SEARCHING:
            spec = _spec(record, cancelled=True)
            self._cancelled[record.robot_id] = (spec, time.monotonic() + self.config.cancel_linger_s)
            self._publish(record.robot_id, spec)
        self._changed(task_id)
        if record.status is TaskStatus.SEARCHING:
            self._start_next(record.robot_id)
        else:
            self._notify_queue(record.robot_id)
        return self._get(task_id)

    # -- planner events (owner thread) ----------------------------------------------------------
    def on_event(self, robot_id: str, event: TaskEvent) -> None:
        """Apply a planner report to the robot's active task (others are counted and ignored)."""
        record = self.store.get(event.task_id)
        if record is None:
            self._count("events_unknown_task")
            return
        if record.status in FINAL:
            self._count("events_finished_task")
            return
        if record.robot_id != robot_id or record.status is not TaskStatus.SEARCHING:
            self._count("events_not_active")
            return
        position = (event.x, event.y) if event.x is not None and event.y is not None else None
        self.store.progress(record.id, found=event.found, steps=event.steps, distance_m=event.distance_m,
                            message=event.message, position=position, odom_session=event.odom_session,
                            misses=event.misses, last_action=event.last_action)
        self._count("events_applied")
        self._live[robot_id] = (record.id, event.goal)
        if event.status in FINAL:
            self.store.finish(record.id, event.status)
            self._changed(record.id)
            self._start_next(robot_id)
        else:
            self._changed(record.id)

    def goal(self, robot_id: str, task_id: str) -> Goal | None:
        """Where the planner last said it takes the robot for ``task_id`` (any thread)."""
        entry = self._live.get(robot_id)
        return entry[1] if entry is not None and entry[0] == task_id else None

    # -- periodic (owner thread) ---------------------------------------------------------------
    def republish(self) -> None:
        """Re-send each robot's current TaskSpec (and a recently cancelled one)."""
        now = time.monotonic()
        for robot in self.config.robots:
            if robot in self._cancelled:
                spec, until = self._cancelled[robot]
                if now <= until:
                    self._publish(robot, spec.model_copy(update={"stamp": time.time()}))
                else:
                    del self._cancelled[robot]
            active = self.store.active(robot)
            if active is not None:
                self._publish(robot, _spec(active))

    # -- counters (any thread, the event loop included: the lock is held for no I/O) -----------
    def count_rejected_request(self, status_code: int) -> None:
        self._count(f"http_{status_code}")

    def _count(self, name: str) -> None:
        with self._counters_lock:
            self._counters[name] += 1

    def counters(self) -> dict[str, int]:
        """Event bookkeeping, malformed payloads the bus dropped on ``task/events``, and refused
        HTTP requests by status (``http_422``: 1, ...)."""
        with self._counters_lock:
            out = {name: self._counters[name] for name in
                   ("events_applied", "events_unknown_task", "events_finished_task", "events_not_active")}
            out.update(sorted((k, n) for k, n in self._counters.items() if k.startswith("http_")))
        out["events_malformed"] = self._malformed_events()
        return out

    # -- internals (owner thread) --------------------------------------------------------------
    def _guarded(self, fn: Callable[[], None], what: str) -> Callable[[object], None]:
        """``fn`` as an inbox handler whose failure is logged and counted (``record_failure``)."""
        def run(_: object) -> None:
            try:
                fn()
            except Exception:
                self._record_failure(what)
        return run

    def _start_next(self, robot_id: str) -> None:
        record = self.store.next_queued(robot_id)
        if record is not None:
            self.store.start(record.id)
            record = self._get(record.id)
            self._publish(robot_id, _spec(record))
            self._log.info("task %s started on %s: %s", record.id, robot_id, ", ".join(record.targets))
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
    """The task with the progress the planner last reported: a planner restarted mid-task
    resumes its count, distance and found targets from it instead of starting over."""
    x, y = record.position or (None, None)
    return TaskSpec(task_id=record.id, targets=tuple(record.targets), max_steps=record.max_steps,
                    cancelled=cancelled, stamp=time.time(), steps=record.steps,
                    distance_m=record.distance_m, found=tuple(record.found), last_action=record.last_action,
                    x=x, y=y, odom_session=record.odom_session or "")
