"""The perception service: frames in, one result per frame (same seq) out, across replicas.

Wiring (:data:`shared.topology.TOPOLOGY`, ``perception``): ``sensors/rgbd``
frames, ``task/current`` and ``task/events`` in, ``perception/result`` out.
Everything runs on the service's one thread (:func:`shared.service.run_service`):
Zenoh's callbacks only enqueue on the bus's inbox, the handlers below and the
model calls run one at a time, and :meth:`PerceptionService.info` is read by
that thread too (the loop copies it for stats queries), so the state needs no lock.

Frames: while the model works on one frame, only the newest ``queue_frames``
frames wait in the inbox (default 1: a newer frame replaces the waiting one,
counted as ``dropped`` on the frame key), so a slow model never works on stale
frames or lets memory grow. Task messages are never dropped and keep their
order. Each frame taken is checked for ownership (:mod:`.replicas`); an owned
one runs the backend and gets exactly one ``perception/result`` with its seq.
The newest-only rule applies before the ownership check, so with n replicas a
replica whose newest waiting frame belongs to another skips it and takes the
next (at most n - 1 frame intervals later for consecutive seqs).

Targets: ``task/current`` sets the target list, less the targets
``task/events`` reports found for that task (the in-process episode runner does
the same). Without a task (or once it is cancelled) there are no targets: each
frame still gets a result, with no scores and no detections and without running
a model. The map then fuses the frame at once instead of waiting out its match
timeout, and drops its value layers when a task ends. When the list gains a
target (a task starts, targets are added), the latest frame this replica
processed is scored again for the new list and gets a second result: the view
in front of a robot standing still is not lost for the new targets (the map
fuses only the values of targets it had not fused that frame for).

A frame no backend can use (wrong size, or a camera frame sent to the sim
backend) is rejected: counted as ``malformed`` on the frame key (as the bus
counts undecodable ones), logged (sampled) and answered with no result.

Replicas: membership is the set of ``ready`` liveliness tokens (watched through
the inbox like messages); this replica declares its own once the backend is
loaded and its inputs are wired, and withdraws it first when it stops.
"""

from __future__ import annotations

import time
from typing import Any

from services.perception.backend import PerceptionBackend, load_backend
from services.perception.config import PerceptionServiceConfig
from services.perception.errors import FrameRejected
from services.perception.frames import frame_problem
from services.perception.replicas import ReplicaSet
from shared import keys
from shared.bus import BusCore
from shared.log import fields, sampled
from shared.messages import PerceptionResult, RgbdFrame, TaskEvent, TaskSpec
from shared.service import Service


class PerceptionService(Service):
    name = "perception"
    Config = PerceptionServiceConfig
    config: PerceptionServiceConfig
    def __init__(self, bus: BusCore, config: PerceptionServiceConfig,
                 backend: PerceptionBackend | None = None) -> None:
        super().__init__(bus, config)
        self.backend = backend or load_backend(config)
        self.replicas = ReplicaSet(bus.instance)
        self._frame_key = keys.rgbd(bus.robot_id)
        self._spec_targets: tuple[str, ...] = ()
        self._targets: tuple[str, ...] = ()
        self._task_id: str | None = None
        self._found: frozenset[str] = frozenset()
        self._processed = self._rejected = 0
        self._last_seq: int | None = None
        self._latest: RgbdFrame | None = None  # the newest frame processed: re-scored on new targets
        self._rescored = 0
        self._last_ms: float | None = None
        self._last_rejection = ""
        self._ready: Any = None

    def start(self) -> None:
        robot = self.bus.robot_id
        self.wire({"task_current": self._on_task, "task_events": self._on_event, "rgbd": self._on_frame},
                  keep={"rgbd": self.config.queue_frames})
        self.bus.watch_liveliness(keys.ready(robot, self.name), self._on_member)
        # Last: the backend is loaded (in __init__) and frames are taken, so the others may now
        # hand this replica its share.
        self._ready = self.bus.declare_token(keys.ready(robot, self.name, self.bus.instance))

    # -- inputs --------------------------------------------------------------------------------
    def _on_member(self, key: str, alive: bool) -> None:
        instance = keys.parse_service_key(key).instance
        if alive:
            self.replicas.join(instance)
        else:
            self.replicas.leave(instance)
        self.log.info("perception replicas now %s", self.replicas.members())

    def _on_task(self, task: TaskSpec) -> None:
        if task.task_id != self._task_id:
            self._task_id, self._found = task.task_id, frozenset()
        self._spec_targets = () if task.cancelled else task.targets
        self._retarget()

    def _on_event(self, event: TaskEvent) -> None:
        """A found target is not looked for any more (its map layer goes with it)."""
        if event.task_id == self._task_id:
            self._found = frozenset(f.label for f in event.found)
            self._retarget()

    def _retarget(self) -> None:
        before = self._targets
        self._targets = tuple(t for t in self._spec_targets if t not in self._found)
        if self._latest is not None and set(self._targets) - set(before):
            self._rescored += 1
            self._process(self._latest)

    def _on_frame(self, frame: RgbdFrame) -> None:
        if self.replicas.owns(frame.seq):
            self._process(frame)

    # -- the model -----------------------------------------------------------------------------
    def _process(self, frame: RgbdFrame) -> None:
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
        self.out["perception_result"].put(PerceptionResult.build(
            frame.seq, frame.stamp, scores, detections, frame.depth.shape, frame.odom_session))
        self._latest = frame
        self._processed += 1
        self._last_seq = frame.seq
        self._last_ms = (time.perf_counter() - start) * 1e3

    def _reject(self, frame: RgbdFrame, reason: str) -> None:
        self.bus.counters.bump(self._frame_key, "malformed")
        self._rejected += 1
        self._last_rejection = reason
        if sampled(self._rejected):
            self.log.warning("rejected frame %d: %s", frame.seq, reason,
                             extra=fields(key=self._frame_key, count=self._rejected))

    # -- status and shutdown -------------------------------------------------------------------
    def info(self) -> dict[str, Any]:
        members = self.replicas.members()
        return {"backend": self.backend.name, "targets": list(self._targets),
                "replicas": members, "replica_index": members.index(self.bus.instance),
                "processed": self._processed, "rescored": self._rescored, "rejected": self._rejected,
                "last_rejection": self._last_rejection, "last_seq": self._last_seq,
                "last_ms": None if self._last_ms is None else round(self._last_ms, 1)}

    def stop(self) -> None:
        """Withdraw the ``ready`` token first: the others take over this replica's share at once
        (the loop has ended, so no frame is in progress; the bus closes the rest)."""
        if self._ready is not None:
            token, self._ready = self._ready, None
            token.undeclare()
