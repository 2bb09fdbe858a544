"""The perception service: frames in, one result per frame (same seq) out, across replicas.

Wiring: ``sensors/rgbd`` frames are decoded on Zenoh's thread, checked for
ownership (:mod:`.replicas`) and handed to one worker thread through a
bounded queue (latest-only by default); the worker runs the backend and
publishes ``perception/result``. ``task/current`` sets the target list, less the
targets ``task/events`` reports found (the in-process episode runner does the same).

Without a task (or once it is cancelled) there are no targets: each frame
still gets a result, with no scores and no detections and without running a
model. The map then fuses the frame at once instead of waiting out its match
timeout, and drops its value layers when a task ends.

A frame no backend can use (wrong size, or a camera frame sent to the sim
backend) is rejected: counted as ``malformed`` on the frame key (as the bus
counts undecodable ones), logged (sampled) and answered with no result.
"""

from __future__ import annotations

import threading
import time
from typing import Any

import zenoh

from services.perception.backend import FrameRejected, PerceptionBackend, load_backend
from services.perception.config import PerceptionServiceConfig
from services.perception.frames import BoundedQueue, frame_problem
from services.perception.replicas import ReplicaSet
from shared import keys
from shared.bus import Bus
from shared.log import fields, sampled
from shared.messages import PerceptionResult, RgbdFrame, TaskEvent, TaskSpec
from shared.service import Service


class PerceptionService(Service):
    name = "perception"
    Config = PerceptionServiceConfig
    config: PerceptionServiceConfig

    def __init__(self, bus: Bus, config: PerceptionServiceConfig,
                 backend: PerceptionBackend | None = None) -> None:
        super().__init__(bus, config)
        self.backend = backend or load_backend(config)
        self.replicas = ReplicaSet(bus.instance)
        self._frame_key = keys.rgbd(bus.robot_id)
        self._lock = threading.Lock()
        self._targets: tuple[str, ...] = ()
        self._spec_targets: tuple[str, ...] = ()
        self._task_id: str | None = None
        self._found: frozenset[str] = frozenset()
        self._processed = self._rejected = 0
        self._last_seq: int | None = None
        self._last_ms: float | None = None
        self._last_rejection = ""
        self._queue: BoundedQueue[RgbdFrame] = BoundedQueue(
            config.queue_frames, lambda _frame: bus.counters.bump(self._frame_key, "dropped"))
        self._worker = threading.Thread(target=self._work, name="perception-worker", daemon=True)
        self._members_sub: Any = None
        self._ready_token: Any = None

    def start(self) -> None:
        robot = self.bus.robot_id
        self.results = self.bus.publisher(keys.perception_result(robot), PerceptionResult)
        self._members_sub = self.bus.session.liveliness().declare_subscriber(
            keys.ready(robot, self.name), self._on_member, history=True)
        self.bus.subscribe(keys.task_current(robot), TaskSpec, self._on_task)
        self.bus.subscribe(keys.task_events(robot), TaskEvent, self._on_event)
        self.bus.subscribe(self._frame_key, RgbdFrame, self._on_frame)
        self._worker.start()
        # Last: the backend is loaded (in __init__) and frames are taken, so the others may now
        # hand this replica its share.
        self._ready_token = self.bus.session.liveliness().declare_token(
            keys.ready(robot, self.name, self.bus.instance))

    # -- inputs (Zenoh threads) ----------------------------------------------------------------
    def _on_member(self, sample: zenoh.Sample) -> None:
        try:
            instance = keys.parse_service_key(str(sample.key_expr)).instance
            if sample.kind == zenoh.SampleKind.PUT:
                self.replicas.join(instance)
            else:
                self.replicas.leave(instance)
            self.log.info("perception replicas now %s", self.replicas.members())
        except Exception:  # a callback's exception would vanish inside Zenoh
            self.bus.record_failure("replicas")

    def _on_task(self, task: TaskSpec) -> None:
        with self._lock:
            if task.task_id != self._task_id:
                self._task_id, self._found = task.task_id, frozenset()
            self._spec_targets = () if task.cancelled else task.targets
            self._targets = tuple(t for t in self._spec_targets if t not in self._found)

    def _on_event(self, event: TaskEvent) -> None:
        """A found target is not looked for any more (its map layer goes with it)."""
        with self._lock:
            if event.task_id == self._task_id:
                self._found = frozenset(f.label for f in event.found)
                self._targets = tuple(t for t in self._spec_targets if t not in self._found)

    def _on_frame(self, frame: RgbdFrame) -> None:
        if self.replicas.owns(frame.seq):
            self._queue.put(frame)

    # -- the worker ----------------------------------------------------------------------------
    def _work(self) -> None:
        while (frame := self._queue.get()) is not None:
            try:
                self._process(frame)
            except Exception:
                self.bus.record_failure(self._frame_key)

    def _process(self, frame: RgbdFrame) -> None:
        with self._lock:
            targets = self._targets
        start = time.perf_counter()
        try:
            problem = frame_problem(frame, self.config.frames)
            if problem is not None:
                raise FrameRejected(problem)
            scores = self.backend.score(frame, targets) if targets else {}
            detections = self.backend.detect(frame, targets) if targets and self.config.detect else []
        except FrameRejected as exc:
            self._reject(frame, str(exc))
            return
        self.results.put(PerceptionResult.build(frame.seq, frame.stamp, scores, detections,
                                                frame.depth.shape))
        with self._lock:
            self._processed += 1
            self._last_seq = frame.seq
            self._last_ms = (time.perf_counter() - start) * 1e3

    def _reject(self, frame: RgbdFrame, reason: str) -> None:
        self.bus.counters.bump(self._frame_key, "malformed")
        with self._lock:
            self._rejected += 1
            self._last_rejection = reason
            n = self._rejected
        if sampled(n):
            self.log.warning("rejected frame %d: %s", frame.seq, reason,
                             extra=fields(key=self._frame_key, count=n))

    # -- status and shutdown -------------------------------------------------------------------
    def info(self) -> dict[str, Any]:
        members = self.replicas.members()
        with self._lock:
            return {"backend": self.backend.name, "targets": list(self._targets),
                    "replicas": members, "replica_index": members.index(self.bus.instance),
                    "processed": self._processed, "rejected": self._rejected,
                    "last_rejection": self._last_rejection, "last_seq": self._last_seq,
                    "last_ms": None if self._last_ms is None else round(self._last_ms, 1)}

    def stop(self) -> None:
        if self._ready_token is not None:
            self._ready_token.undeclare()  # first: the others take over this replica's share
        self._queue.close()
        if self._worker.is_alive():
            self._worker.join(timeout=30)  # a model call in progress finishes first
        if self._members_sub is not None:
            self._members_sub.undeclare()
