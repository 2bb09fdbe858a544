"""The perception service: frames in, one result per frame (same seq) out, for one robot or a fleet.

Wiring (:data:`ovamos.shared.topology.TOPOLOGY`, ``perception``): ``sensors/rgbd``
frames, ``task/current`` and ``task/events`` in, ``perception/result`` out, for
each robot in ``robots`` (default: its own ``--robot-id``; ``["*"]``: every
robot on the network), each result on its frame's robot's key. Everything runs
on the service's one thread (:func:`ovamos.shared.service.run_service`): Zenoh's
callbacks only enqueue on the bus's inbox, the handlers below and the model
calls run one at a time, and :meth:`PerceptionService.info` is read by that
thread too (the loop copies it for stats queries), so the state needs no lock.

Frames: while the model works, only the newest ``queue_frames`` frames of each
robot wait in the inbox (default 1: a newer frame replaces the waiting one,
counted as ``dropped`` on that robot's frame key), so a slow model never works
on stale frames or lets memory grow. Task messages are never dropped and keep
their order. Each frame taken is checked for ownership (:mod:`.replicas`); an
owned one goes to its robot's slot (:class:`~.fleet.FrameSlots`), and a batch
of up to ``batch_size`` frames, one per robot, round robin, runs once it is full
or its oldest frame has waited ``batch_wait_ms`` (the default, 1 and 0 ms, runs
each frame at once, as a single-robot service should). Each frame of the batch
gets exactly one ``perception/result`` with its seq on its robot's key.

Targets are per robot (:class:`~.fleet.RobotTargets`): its ``task/current``,
less the targets its ``task/events`` report found. Without a task (or once it
is cancelled) there are no targets: each frame still gets a result, with no
scores and no detections and without running a model. The map then fuses the
frame at once instead of waiting out its match timeout, and drops its value
layers when a task ends. When a robot's list gains a target (a task starts,
targets are added), the latest frame this replica processed of that robot goes
back into its slot, unless a newer one waits there, and is scored again for the
new list: the view in front of a robot standing still is not lost for the new
targets (the map fuses only the values of targets it had not fused that frame for).

A target the backend can never see (the sim backend's vocabulary is closed: the classes a
simulated house can hold; a real model's is open, any word goes) is not scored; the service
says so in its info (``unknown_targets``: per robot the targets and why, ``did you mean
'candle'?``), where the planner reads it to fail the task with that reason instead of waiting
for a map layer that never comes.

A frame no backend can use (wrong size, or a camera frame sent to the sim
backend) is rejected: counted as ``malformed`` on its frame key (as the bus
counts undecodable ones), logged (sampled) and answered with no result.

Replicas: membership is the set of ``ready`` liveliness tokens under this
service's own robot id (a fleet's perception runs under one id, e.g. ``fleet``),
watched through the inbox like messages; this replica declares its own once the
backend is loaded and its inputs are wired, and withdraws it first when it
stops. Each robot it serves by name also sees it among its own services (an
``alive`` token and stats under that robot: ``ovamos status``, the gateway's health).
"""

from __future__ import annotations

import time
from collections import defaultdict
from collections.abc import Callable, Sequence
from typing import Any

from ovamos.services.perception.backend import Job, PerceptionBackend, Seen, load_backend
from ovamos.services.perception.config import PerceptionServiceConfig
from ovamos.services.perception.errors import FrameRejected
from ovamos.services.perception.fleet import FrameSlots, RobotTargets
from ovamos.services.perception.frames import frame_problem
from ovamos.services.perception.replicas import ReplicaSet
from ovamos.shared import keys
from ovamos.shared.bus import BusCore
from ovamos.shared.log import fields, sampled
from ovamos.shared.messages import PerceptionResult, RgbdFrame
from ovamos.shared.service import Service


class PerceptionService(Service):
    name = "perception"
    Config = PerceptionServiceConfig
    config: PerceptionServiceConfig
    #: how often a batch still waiting for frames is checked against ``batch_wait_ms``
    tick_hz = 200.0

    def __init__(self, bus: BusCore, config: PerceptionServiceConfig,
                 backend: PerceptionBackend | None = None) -> None:
        super().__init__(bus, config)
        self.backend = backend or load_backend(config)
        self.replicas = ReplicaSet(bus.instance)
        self.robots = config.robots or [bus.robot_id]
        self.slots = FrameSlots()
        self._targets: defaultdict[str, RobotTargets] = defaultdict(RobotTargets)
        self._processed: defaultdict[str, int] = defaultdict(int)
        self._latest: dict[str, RgbdFrame] = {}  # per robot the newest frame processed: re-scored on new targets
        self._rejected = self._batches = self._rescored = 0
        self._last_seq: int | None = None
        self._last_ms: float | None = None
        self._last_batch = 0
        self._last_rejection = ""
        self._ready: Any = None
        # a closed-vocabulary backend's (the sim's) check of a target list; None: any word goes
        self._vocabulary: Callable[[Sequence[str]], tuple[tuple[str, ...], str]] | None = \
            getattr(self.backend, "unknown_targets", None)
        self._unknown: dict[str, tuple[tuple[str, ...], str]] = {}  # per robot: targets never seen, why

    def start(self) -> None:
        robot = self.bus.robot_id
        targets = self._targets
        self.wire_robots(self.robots, {
            "task_current": lambda r, task: self._retarget(r, targets[r].on_task(task)),
            "task_events": lambda r, event: self._retarget(r, targets[r].on_event(event)),
            "rgbd": self._on_frame}, keep={"rgbd": self.config.queue_frames})
        self.bus.watch_liveliness(keys.ready(robot, self.name), self._on_member)
        for other in self.robots:
            if other not in (robot, keys.ANY):
                self.bus.serve_robot(other)
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

    def _retarget(self, robot: str, gained: bool) -> None:
        """A robot's list gained a target: its latest processed frame is scored again (unless a
        newer frame of it is waiting, which will be scored for the new list anyway)."""
        self._check_vocabulary(robot)
        latest = self._latest.get(robot)
        if gained and latest is not None and robot not in self.slots:
            self._rescored += 1
            self.slots.put(robot, latest, time.monotonic())
            self.tick()

    def _check_vocabulary(self, robot: str) -> None:
        """Note (and say once) which of the robot's targets the backend can never see."""
        if self._vocabulary is None:
            return
        unknown, why = self._vocabulary(self._targets[robot].targets)
        if not unknown:
            self._unknown.pop(robot, None)
        elif self._unknown.get(robot) != (unknown, why):
            self._unknown[robot] = (unknown, why)
            self.log.warning("%s: %s", robot, why)

    def _on_frame(self, robot: str, frame: RgbdFrame) -> None:
        if self.replicas.owns(frame.seq):
            self.slots.put(robot, frame, time.monotonic())
            self.tick()

    def tick(self) -> None:
        """Run a batch when one is due (full, or its oldest frame waited long enough)."""
        while self.slots.due(self.config.batch_size, self.config.batch_wait_ms / 1e3, time.monotonic()):
            self._run(self.slots.take(self.config.batch_size))

    # -- the model -----------------------------------------------------------------------------
    def _run(self, batch: list[tuple[str, RgbdFrame]]) -> None:
        start = time.perf_counter()
        jobs, empty = [], []
        for robot, frame in batch:
            problem = frame_problem(frame, self.config.frames)
            if problem is not None:
                self._reject(robot, frame, problem)
            elif self._targets[robot].targets:
                jobs.append(Job(robot, frame, self._targets[robot].targets))
            else:
                empty.append(Job(robot, frame, ()))
        outcomes = self.backend.process(jobs, self.config.detect) if jobs else []
        for job, outcome in [*zip(jobs, outcomes), *((job, Seen({})) for job in empty)]:
            if isinstance(outcome, FrameRejected):
                self._reject(job.robot_id, job.frame, str(outcome))
                continue
            self.output("perception_result", job.robot_id).put(PerceptionResult.build(
                job.frame.seq, job.frame.stamp, outcome.scores, outcome.detections, job.frame.depth.shape,
                job.frame.odom_session))
            self._processed[job.robot_id] += 1
            self._latest[job.robot_id] = job.frame
            self._last_seq = job.frame.seq
        self._batches += 1
        self._last_batch = len(batch)
        self._last_ms = (time.perf_counter() - start) * 1e3

    def _reject(self, robot: str, frame: RgbdFrame, reason: str) -> None:
        frame_key = keys.rgbd(robot)
        self.bus.counters.bump(frame_key, "malformed")
        self._rejected += 1
        self._last_rejection = reason
        if sampled(self._rejected):
            self.log.warning("rejected frame %d of %s: %s", frame.seq, robot, reason,
                             extra=fields(key=frame_key, count=self._rejected))

    # -- status and shutdown -------------------------------------------------------------------
    def info(self) -> dict[str, Any]:
        members = self.replicas.members()
        return {"backend": self.backend.name, "robots": self.robots,
                "targets": {r: list(t.targets) for r, t in self._targets.items()},
                "unknown_targets": {r: {"targets": list(unknown), "reason": why}
                                    for r, (unknown, why) in self._unknown.items()},
                "replicas": members, "replica_index": members.index(self.bus.instance),
                "processed": sum(self._processed.values()), "processed_by_robot": dict(self._processed),
                "replaced_by_robot": dict(self.slots.replaced), "rescored": self._rescored,
                "batches": self._batches,
                "last_batch": self._last_batch, "rejected": self._rejected,
                "last_rejection": self._last_rejection, "last_seq": self._last_seq,
                "last_ms": None if self._last_ms is None else round(self._last_ms, 1)}

    def stop(self) -> None:
        """Withdraw the ``ready`` token first: the others take over this replica's share at once
        (the loop has ended, so no frame is in progress; the bus closes the rest)."""
        if self._ready is not None:
            token, self._ready = self._ready, None
            token.undeclare()
