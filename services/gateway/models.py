"""What the HTTP API accepts and returns.

Validation lives in these models so that every malformed request fails the
same way (422 with a message naming the field) before any handler runs.
Checks that depend on the configuration (known robot ids, the step limit)
are done by :func:`check_against_config`, which raises the same kind of error.
"""

from __future__ import annotations

from datetime import UTC, datetime

from fastapi.exceptions import RequestValidationError
from pydantic import BaseModel, ConfigDict, Field, field_validator

from services.gateway.config import MAX_STEPS_LIMIT, GatewayConfig
from services.gateway.store import TaskRecord
from shared.messages import FINAL, FoundObject, TaskStatus

MAX_TARGETS = 16
MAX_TARGET_CHARS = 64


class TaskRequest(BaseModel):
    """``POST /v1/tasks``: what to search for, on which robot."""

    model_config = ConfigDict(extra="forbid", strict=True, json_schema_extra={
        "examples": [{"targets": ["chair", "fridge"], "robot_id": "sim", "max_steps": 500}]})
    targets: list[str] = Field(description=f"1-{MAX_TARGETS} object names, each 1-{MAX_TARGET_CHARS} "
                                           "printable characters, no duplicates (case-insensitive)")
    robot_id: str | None = Field(default=None, description="default: the first configured robot")
    max_steps: int | None = Field(default=None, ge=1, le=MAX_STEPS_LIMIT,
                                  description="decision steps before the task fails")

    @field_validator("targets")
    @classmethod
    def _targets(cls, targets: list[str]) -> list[str]:
        if not 1 <= len(targets) <= MAX_TARGETS:
            raise ValueError(f"must hold 1 to {MAX_TARGETS} names, got {len(targets)}")
        cleaned: list[str] = []
        seen: dict[str, str] = {}
        for i, raw in enumerate(targets):
            name = raw.strip()
            if not 1 <= len(name) <= MAX_TARGET_CHARS:
                raise ValueError(f"target {i} must be 1 to {MAX_TARGET_CHARS} characters after "
                                 f"trimming, got {len(name)}")
            if not name.isprintable():
                raise ValueError(f"target {i} ({name!r}) contains non-printable characters")
            folded = name.casefold()
            if folded in seen:
                raise ValueError(f"target {i} ({name!r}) duplicates {seen[folded]!r} "
                                 "(names are compared ignoring case)")
            seen[folded] = name
            cleaned.append(name)
        return cleaned


def check_against_config(request: TaskRequest, config: GatewayConfig) -> tuple[str, int]:
    """The request's robot id and step limit with defaults applied; 422 when out of bounds."""
    robot = request.robot_id if request.robot_id is not None else config.robots[0]
    if robot not in config.robots:
        raise _body_error("robot_id", f"unknown robot {robot!r}; known: {', '.join(config.robots)}",
                          robot)
    steps = request.max_steps if request.max_steps is not None else config.default_max_steps
    if steps > config.max_steps_limit:
        raise _body_error("max_steps", f"must be at most {config.max_steps_limit}", steps)
    return robot, steps


def _body_error(field: str, message: str, value: object) -> RequestValidationError:
    return RequestValidationError([{"type": "value_error", "loc": ("body", field), "msg": message,
                                    "input": value}])


class Position(BaseModel):
    x: float
    y: float


class TaskView(BaseModel):
    """A task as the API shows it (``GET /v1/tasks/{id}``, the event stream)."""

    id: str
    robot_id: str
    status: TaskStatus
    targets: list[str]
    remaining: list[str] = Field(description="targets not found yet")
    found: list[FoundObject] = Field(description="found objects with their world position (m)")
    max_steps: int
    steps: int
    distance_m: float
    message: str = Field(description="the planner's last word (why a task failed, ...)")
    position: Position | None = Field(description="the robot's last reported position")
    queue_position: int | None = Field(description="1 = next to start; null unless queued")
    created_at: datetime
    started_at: datetime | None
    updated_at: datetime
    finished_at: datetime | None

    @property
    def final(self) -> bool:
        return self.status in FINAL


class TaskAccepted(BaseModel):
    """``202`` answer of ``POST /v1/tasks``."""

    id: str
    status: TaskStatus
    robot_id: str
    location: str = Field(description="where to GET the task")
    queue_position: int | None


class TaskList(BaseModel):
    tasks: list[TaskView]


class ServiceEntry(BaseModel):
    service: str
    instance: str
    pid: int | None


class RobotHealth(BaseModel):
    services: list[ServiceEntry] = Field(description="instances holding a Zenoh liveliness token")
    active_task: str | None
    queued: int


class Health(BaseModel):
    status: str = "ok"
    robots: dict[str, RobotHealth]
    counters: dict[str, int] = Field(description="task events applied / ignored, and why")


class Problem(BaseModel):
    """Every error answer: one sentence for people, the field-level details for programs."""

    detail: str
    errors: list[dict[str, str]] = []


def timestamp(seconds: float | None) -> datetime | None:
    return None if seconds is None else datetime.fromtimestamp(seconds, UTC)


def task_view(record: TaskRecord, queue_position: int | None) -> TaskView:
    """The API's picture of a stored task."""
    position = record.position
    return TaskView(
        id=record.id, robot_id=record.robot_id, status=record.status, targets=record.targets,
        remaining=[t for t in record.targets if t not in {f.label for f in record.found}],
        found=record.found, max_steps=record.max_steps, steps=record.steps,
        distance_m=record.distance_m, message=record.message,
        position=None if position is None else Position(x=position[0], y=position[1]),
        queue_position=queue_position, created_at=timestamp(record.created),
        started_at=timestamp(record.started), updated_at=timestamp(record.updated),
        finished_at=timestamp(record.finished))
