"""A search task as the planner runs it: queued -> searching -> done | failed | cancelled.

The planner owns one task per robot. Targets may be added or removed while
searching (a user changes their mind); finding the last remaining target ends
the task, and so does running out of steps. The states and the found objects
are the ones the planner reports (:class:`ovamos.shared.messages.TaskStatus`,
:class:`ovamos.shared.messages.FoundObject`): one vocabulary from planner to user.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from ovamos.shared.messages import FoundObject, TaskSpec, TaskStatus


class SearchTaskError(RuntimeError):
    """An operation the task's current status does not allow."""


@dataclass
class SearchTask:
    """The planner's record of one task: its targets, progress, and what was found where."""

    task_id: str
    targets: list[str]
    max_steps: int = 500
    state: TaskStatus = TaskStatus.QUEUED  # not started yet
    steps: int = 0
    distance: float = 0.0
    found: dict[str, FoundObject] = field(default_factory=dict)
    reason: str = ""  # why the task failed
    last_action: int = 0  # the id of the newest command booked as a step (0: none yet)

    def __post_init__(self) -> None:
        if not self.targets or len(set(self.targets)) != len(self.targets):
            raise SearchTaskError("a task needs at least one target and no duplicates")

    @classmethod
    def from_spec(cls, spec: TaskSpec) -> SearchTask:
        """The task a spec names, with the progress its owner recorded (steps, distance, found
        targets, the last command booked): a planner restarted mid-task goes on counting, with
        the step budget left, instead of starting the task again."""
        return cls(spec.task_id, list(spec.targets), max_steps=spec.max_steps, steps=spec.steps,
                   distance=spec.distance_m, last_action=spec.last_action,
                   found={f.label: f for f in spec.found if f.label in spec.targets})

    @property
    def remaining(self) -> list[str]:
        return [t for t in self.targets if t not in self.found]

    def _require(self, *states: TaskStatus) -> None:
        if self.state not in states:
            raise SearchTaskError(f"task {self.task_id} is {self.state.value}; "
                                  f"this needs {' or '.join(s.value for s in states)}")

    def start(self) -> None:
        """Searching, unless the progress it resumes from left nothing to do: every target found,
        or the step budget spent (a planner killed between the last step and its report)."""
        self._require(TaskStatus.QUEUED)
        self.state = TaskStatus.SEARCHING if self.remaining else TaskStatus.DONE
        if self.state is TaskStatus.SEARCHING and self.steps >= self.max_steps:
            self.fail(f"step limit {self.max_steps} reached")

    def record_step(self, distance: float, found: tuple[str, float, float] | None = None) -> None:
        """One executed command (a STOP that declared ``found``, (label, x, y), included);
        the task fails when the step limit is reached with targets left."""
        self._require(TaskStatus.SEARCHING)
        self.steps += 1
        self.distance += distance
        if found is not None:
            self.mark_found(*found)
        if self.state is TaskStatus.SEARCHING and self.steps >= self.max_steps:
            self.fail(f"step limit {self.max_steps} reached")

    def book_unreported(self, last_completed: int, distance: float) -> None:
        """Book as steps the commands after ``last_action`` up to the driver's ``last_completed``:
        those a killed planner sent for this task and completed without reporting them (its
        last event was lost with it); ``distance``: how far the robot got over them together."""
        while self.state is TaskStatus.SEARCHING and self.last_action < last_completed:
            self.record_step(distance)
            self.last_action += 1
            distance = 0.0

    def mark_found(self, label: str, x: float, y: float) -> None:
        self._require(TaskStatus.SEARCHING)
        if label not in self.remaining:
            raise SearchTaskError(f"{label!r} is not a remaining target of task {self.task_id}")
        self.found[label] = FoundObject(label=label, x=x, y=y, step=self.steps)
        if not self.remaining:
            self.state = TaskStatus.DONE

    def fail(self, reason: str) -> None:
        self._require(TaskStatus.SEARCHING)
        self.state = TaskStatus.FAILED
        self.reason = reason

    def explain(self, why: str) -> None:
        """Add why the task failed to its reason (``step limit 500 reached: bed never seen``)."""
        self._require(TaskStatus.FAILED)
        if why:
            self.reason = f"{self.reason}: {why}"

    def add_targets(self, labels: list[str]) -> None:
        self._require(TaskStatus.QUEUED, TaskStatus.SEARCHING)
        self.targets += [t for t in dict.fromkeys(labels) if t not in self.targets]

    def remove_targets(self, labels: list[str]) -> None:
        """Drop targets; removing every remaining one finishes the task (nothing left to find)."""
        self._require(TaskStatus.QUEUED, TaskStatus.SEARCHING)
        keep = [t for t in self.targets if t not in labels or t in self.found]
        if not keep:
            raise SearchTaskError("a task cannot lose all of its targets; cancel it instead")
        self.targets = keep
        if self.state is TaskStatus.SEARCHING and not self.remaining:
            self.state = TaskStatus.DONE

    def cancel(self) -> None:
        self._require(TaskStatus.QUEUED, TaskStatus.SEARCHING)
        self.state = TaskStatus.CANCELLED
