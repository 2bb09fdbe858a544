"""One perception service for several robots: each robot's targets, and fair batches of frames.

Plain state, no Zenoh: the core (:mod:`.core`) feeds it on the service's one thread.

Fairness: each robot has one slot holding its newest frame not yet taken (a
newer frame replaces it, counted per robot), and batches are filled round robin:
the robots served by the last batch go to the back of the line. A robot that
streams at 30 Hz therefore only ever replaces its own frame and cannot push a
5 Hz robot's frame out: every robot with a frame waiting is in one of the next
``ceil(robots / batch_size)`` batches.
"""

from __future__ import annotations

from collections import Counter

from ovamos.shared.messages import RgbdFrame, TaskEvent, TaskSpec


class RobotTargets:
    """One robot's targets: its task's, less those its planner reported found."""

    def __init__(self) -> None:
        self._task_id: str | None = None
        self._spec: tuple[str, ...] = ()
        self._found: frozenset[str] = frozenset()
        self.targets: tuple[str, ...] = ()

    def on_task(self, task: TaskSpec) -> bool:
        """A task (or its cancellation: no targets any more); whether the list gained a target."""
        if task.task_id != self._task_id:
            self._task_id, self._found = task.task_id, frozenset()
        self._spec = () if task.cancelled else task.targets
        return self._retarget()

    def on_event(self, event: TaskEvent) -> bool:
        """A found target is not looked for any more (its map layer goes with it)."""
        if event.task_id != self._task_id:
            return False
        self._found = frozenset(f.label for f in event.found)
        return self._retarget()

    def _retarget(self) -> bool:
        before, self.targets = self.targets, tuple(t for t in self._spec if t not in self._found)
        return bool(set(self.targets) - set(before))


class FrameSlots:
    """Per robot the newest frame not yet taken, with when it arrived; round-robin batches."""

    def __init__(self) -> None:
        self._slots: dict[str, tuple[RgbdFrame, float]] = {}
        self._line: list[str] = []  # every robot seen, the next to be served first
        #: frames replaced in their slot by a newer one before a batch took them, per robot
        self.replaced: Counter[str] = Counter()

    def put(self, robot: str, frame: RgbdFrame, now: float) -> None:
        """``frame`` waits in ``robot``'s slot (replacing an older one, counted); ``now`` in seconds."""
        if robot not in self._line:
            self._line.append(robot)
        if robot in self._slots:
            self.replaced[robot] += 1
            now = self._slots[robot][1]  # the slot has been waiting since its first frame
        self._slots[robot] = (frame, now)

    def __len__(self) -> int:
        return len(self._slots)

    def __contains__(self, robot: str) -> bool:
        """Whether ``robot`` has a frame waiting."""
        return robot in self._slots

    def due(self, batch_size: int, wait_s: float, now: float) -> bool:
        """A batch should run now: ``batch_size`` frames wait, or one has waited ``wait_s``."""
        if not self._slots:
            return False
        return len(self._slots) >= batch_size or now - min(t for _, t in self._slots.values()) >= wait_s

    def take(self, batch_size: int) -> list[tuple[str, RgbdFrame]]:
        """Up to ``batch_size`` waiting frames, one per robot, first those at the front of the line;
        the robots served go to the back of it."""
        served = [r for r in self._line if r in self._slots][:batch_size]
        self._line = [r for r in self._line if r not in served] + served
        return [(r, self._slots.pop(r)[0]) for r in served]
