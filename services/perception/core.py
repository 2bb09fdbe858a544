"""The perception service's core: frames in, one result per frame (same seq) out, for one robot or a fleet.

No Zenoh and no bus here: the service adapter (:mod:`ovamos.services.perception.service`) feeds
the core from its one thread, with the time each message arrived, and publishes on each
robot's key what :meth:`PerceptionCore.poll` returns, so the batching and targeting rules below
are tested message by message.

Frames: each frame is checked for ownership (:mod:`.replicas`); an owned one goes
to its robot's slot (:class:`~.fleet.FrameSlots`), and a batch of up to
``batch_size`` frames, one per robot, round robin, runs once it is full or its
oldest frame has waited ``batch_wait_ms`` (the default, 1 and 0 ms, runs each
frame at once, as a single-robot service should). Each frame of the batch gets
exactly one ``perception/result`` with its seq on its robot's key.

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
simulated house can hold; a real model's is open, any word goes) is not scored; the core
says so (:meth:`PerceptionCore.unknown_targets`, which the adapter sends the planner with each
task it is true of, and the info: per robot the targets and why, ``did you mean 'candle'?``): the
planner fails the task with that reason instead of waiting for a map layer that never comes.

A frame no backend can use (wrong size, or a camera frame sent to the sim
backend) is rejected: handed to the ``rejected`` callable (the adapter counts it
as ``malformed`` on its frame key, as the bus counts undecodable ones), logged
(sampled) and answered with no result.

``now`` arguments are ``time.monotonic()`` seconds (how long a batch has waited).
"""

from __future__ import annotations

import logging
import time
from collections import defaultdict
from collections.abc import Callable, Sequence
from typing import Any

from ovamos.services.perception.backend import Job, PerceptionBackend, Seen
from ovamos.services.perception.config import PerceptionServiceConfig
from ovamos.services.perception.errors import FrameRejected
from ovamos.services.perception.fleet import FrameSlots, RobotTargets
from ovamos.services.perception.frames import frame_problem
from ovamos.services.perception.replicas import ReplicaSet
from ovamos.shared import keys
from ovamos.shared.log import fields, sampled
from ovamos.shared.messages import PerceptionResult, RgbdFrame, TaskEvent, TaskSpec, UnknownTargets

__all__ = ["PerceptionCore"]


class PerceptionCore:
    """One replica's share of the robots' frames, scored for each robot's targets; see the module."""

    def __init__(self, config: PerceptionServiceConfig, backend: PerceptionBackend, robots: Sequence[str],
                 instance: str, log: logging.Logger, rejected: Callable[[str], None]) -> None:
        """``robots``: those served (``["*"]``: every robot); ``instance``: this replica's name;
        ``rejected(robot)`` is called for each frame of ``robot`` no backend can use."""
        self.config, self.backend, self.log = config, backend, log
        self.robots = list(robots)
        self.replicas = ReplicaSet(instance)
        self.slots = FrameSlots()
        self._on_rejected = rejected
        self._targets: defaultdict[str, RobotTargets] = defaultdict(RobotTargets)
        self._processed: defaultdict[str, int] = defaultdict(int)
        self._latest: dict[str, RgbdFrame] = {}  # per robot the newest frame processed: re-scored on new targets
        self._rejected = self._batches = self._rescored = 0
        self._last_seq: int | None = None
        self._last_ms: float | None = None
        self._last_batch = 0
        self._last_rejection = ""
        self._unknown: dict[str, tuple[tuple[str, ...], str]] = {}  # per robot: targets never seen, why

    # -- inputs --------------------------------------------------------------------------------
    def on_task(self, robot: str, task: TaskSpec, now: float) -> None:
        """``robot``'s current task (or its cancellation)."""
        self._retarget(robot, self._targets[robot].on_task(task), now)

    def on_event(self, robot: str, event: TaskEvent, now: float) -> None:
        """``robot``'s task progress: the targets it found are not looked for any more."""
        self._retarget(robot, self._targets[robot].on_event(event), now)

    def on_frame(self, robot: str, frame: RgbdFrame, now: float) -> None:
        """A frame of ``robot``: it waits in the robot's slot when this replica owns it."""
        if self.replicas.owns(frame.seq):
            self.slots.put(robot, frame, now)

    def on_replica(self, instance: str, alive: bool) -> None:
        """A replica (this one's own name included) became ready, or went away."""
        if alive:
            self.replicas.join(instance)
        else:
            self.replicas.leave(instance)
        self.log.info("perception replicas now %s", self.replicas.members())

    def _retarget(self, robot: str, gained: bool, now: float) -> None:
        """A robot's list gained a target: its latest processed frame is scored again (unless a
        newer frame of it is waiting, which will be scored for the new list anyway)."""
        self._check_vocabulary(robot)
        latest = self._latest.get(robot)
        if gained and latest is not None and robot not in self.slots:
            self._rescored += 1
            self.slots.put(robot, latest, now)

    def unknown_targets(self, robot: str) -> UnknownTargets | None:
        """The robot's targets the backend can never see, and why (None: it may see them all)."""
        entry = self._unknown.get(robot)
        return None if entry is None else UnknownTargets(targets=entry[0], reason=entry[1])

    def _check_vocabulary(self, robot: str) -> None:
        """Note (and say once) which of the robot's targets the backend can never see."""
        unknown, why = self.backend.unknown_targets(self._targets[robot].targets)
        if not unknown:
            self._unknown.pop(robot, None)
        elif self._unknown.get(robot) != (unknown, why):
            self._unknown[robot] = (unknown, why)
            self.log.warning("%s: %s", robot, why)

    # -- the model -----------------------------------------------------------------------------
    def poll(self, now: float) -> list[tuple[str, PerceptionResult]]:
        """Run every batch that is due (full, or its oldest frame waited ``batch_wait_ms``);
        each result with the robot whose key it goes on."""
        results: list[tuple[str, PerceptionResult]] = []
        while self.slots.due(self.config.batch_size, self.config.batch_wait_ms / 1e3, now):
            results += self._run(self.slots.take(self.config.batch_size))
        return results

    def _run(self, batch: list[tuple[str, RgbdFrame]]) -> list[tuple[str, PerceptionResult]]:
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
        results: list[tuple[str, PerceptionResult]] = []
        for job, outcome in [*zip(jobs, outcomes), *((job, Seen({})) for job in empty)]:
            if isinstance(outcome, FrameRejected):
                self._reject(job.robot_id, job.frame, str(outcome))
                continue
            results.append((job.robot_id, PerceptionResult.build(
                job.frame.seq, job.frame.stamp, outcome.scores, outcome.detections, job.frame.depth.shape,
                job.frame.odom_session)))
            self._processed[job.robot_id] += 1
            self._latest[job.robot_id] = job.frame
            self._last_seq = job.frame.seq
        self._batches += 1
        self._last_batch = len(batch)
        self._last_ms = (time.perf_counter() - start) * 1e3
        return results

    def _reject(self, robot: str, frame: RgbdFrame, reason: str) -> None:
        self._on_rejected(robot)
        self._rejected += 1
        self._last_rejection = reason
        if sampled(self._rejected):
            self.log.warning("rejected frame %d of %s: %s", frame.seq, robot, reason,
                             extra=fields(key=keys.rgbd(robot), count=self._rejected))

    # -- status --------------------------------------------------------------------------------
    def info(self) -> dict[str, Any]:
        members = self.replicas.members()
        return {"backend": self.backend.name, "robots": self.robots,
                "targets": {r: list(t.targets) for r, t in self._targets.items()},
                "unknown_targets": {r: {"targets": list(unknown), "reason": why}
                                    for r, (unknown, why) in self._unknown.items()},
                "replicas": members, "replica_index": members.index(self.replicas.me),
                "processed": sum(self._processed.values()), "processed_by_robot": dict(self._processed),
                "replaced_by_robot": dict(self.slots.replaced), "rescored": self._rescored,
                "batches": self._batches,
                "last_batch": self._last_batch, "rejected": self._rejected,
                "last_rejection": self._last_rejection, "last_seq": self._last_seq,
                "last_ms": None if self._last_ms is None else round(self._last_ms, 1)}
