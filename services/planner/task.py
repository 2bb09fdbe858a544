"""A search task's life: idle -> searching -> done | failed (step limit) | cancelled.

The planner owns one task per robot. Targets may be added or removed while
searching (a user changes their mind); finding the last remaining target ends
the task, and so does running out of steps.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import Enum


class TaskState(str, Enum):
    IDLE = "idle"
    SEARCHING = "searching"
    DONE = "done"
    FAILED = "failed"
    CANCELLED = "cancelled"


FINAL = (TaskState.DONE, TaskState.FAILED, TaskState.CANCELLED)


class TaskError(RuntimeError):
    """An operation the task's current state does not allow."""


@dataclass(frozen=True)
class Found:
    label: str
    x: float
    y: float
    step: int


@dataclass
class Task:
    task_id: str
    targets: list[str]
    max_steps: int = 500
    state: TaskState = TaskState.IDLE
    steps: int = 0
    distance: float = 0.0
    found: dict[str, Found] = field(default_factory=dict)
    reason: str = ""  # why the task failed

    def __post_init__(self) -> None:
        if not self.targets or len(set(self.targets)) != len(self.targets):
            raise TaskError("a task needs at least one target and no duplicates")

    @property
    def remaining(self) -> list[str]:
        return [t for t in self.targets if t not in self.found]

    def _require(self, *states: TaskState) -> None:
        if self.state not in states:
            raise TaskError(f"task {self.task_id} is {self.state.value}; "
                            f"this needs {' or '.join(s.value for s in states)}")

    def start(self) -> None:
        self._require(TaskState.IDLE)
        self.state = TaskState.SEARCHING

    def record_step(self, distance: float, found: Found | None = None) -> None:
        """One executed command (a STOP that declared ``found`` included); the task fails
        when the step limit is reached with targets left."""
        self._require(TaskState.SEARCHING)
        self.steps += 1
        self.distance += distance
        if found is not None:
            self.mark_found(found.label, found.x, found.y)
        if self.state is TaskState.SEARCHING and self.steps >= self.max_steps:
            self.fail(f"step limit {self.max_steps} reached")

    def mark_found(self, label: str, x: float, y: float) -> None:
        self._require(TaskState.SEARCHING)
        if label not in self.remaining:
            raise TaskError(f"{label!r} is not a remaining target of task {self.task_id}")
        self.found[label] = Found(label, x, y, self.steps)
        if not self.remaining:
            self.state = TaskState.DONE

    def fail(self, reason: str) -> None:
        self._require(TaskState.SEARCHING)
        self.state = TaskState.FAILED
        self.reason = reason

    def add_targets(self, labels: list[str]) -> None:
        self._require(TaskState.IDLE, TaskState.SEARCHING)
        self.targets += [t for t in dict.fromkeys(labels) if t not in self.targets]

    def remove_targets(self, labels: list[str]) -> None:
        """Drop targets; removing every remaining one finishes the task (nothing left to find)."""
        self._require(TaskState.IDLE, TaskState.SEARCHING)
        keep = [t for t in self.targets if t not in labels or t in self.found]
        if not keep:
            raise TaskError("a task cannot lose all of its targets; cancel it instead")
        self.targets = keep
        if self.state is TaskState.SEARCHING and not self.remaining:
            self.state = TaskState.DONE

    def cancel(self) -> None:
        self._require(TaskState.IDLE, TaskState.SEARCHING)
        self.state = TaskState.CANCELLED
