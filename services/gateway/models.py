"""What the HTTP API accepts and returns.

Validation lives in these models so that every malformed request fails the
same way (422 with a message naming the field) before any handler runs.
Checks that depend on the configuration (known robot ids, the step limit)
are done by :func:`check_against_config`, which raises the same kind of error.
"""

from __future__ import annotations

from datetime import UTC, datetime
from typing import Literal

from fastapi.exceptions import RequestValidationError
from pydantic import BaseModel, ConfigDict, Field, field_validator

from ovamos.services.gateway.config import MAX_STEPS_LIMIT, GatewayConfig
from ovamos.services.gateway.store import TaskRecord
from ovamos.shared.messages import (
    FINAL,
    MAX_TARGETS,
    DriverState,
    FoundObject,
    Goal,
    ObjectInstance,
    TargetMiss,
    TaskStatus,
)

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
    misses: list[TargetMiss] = Field(
        default_factory=list, description="once failed: each target not found and the stage its "
                                          "search reached (never detected, never confirmed, not reached)")
    position: Position | None = Field(description="the robot's last reported position")
    odom_session: str | None = Field(
        default=None, description="the odometry session of the planner's latest report: its "
                                  "position and goal, and the map it searches on, are in that "
                                  "session's frame (null: no report yet)")
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


class Pose(BaseModel):
    """The robot's pose from its odometry (metres, radians; yaw 0 = world +x, counter-clockwise)."""

    x: float
    y: float
    yaw: float


class RobotState(BaseModel):
    """``GET /v1/robots/{id}``: what the robot's driver reports now, whether or not a task runs."""

    robot_id: str
    driver: DriverState | None = Field(description="the driver's latest state; null until one came")
    driver_age_s: float | None = Field(description="how long ago that state came")
    pose: Pose | None = Field(description="the latest odometry pose; null until one came")
    active_task: str | None


class EStopRequest(BaseModel):
    """``POST /v1/robots/{id}/estop`` (the body is optional)."""

    model_config = ConfigDict(extra="forbid", strict=True)
    reason: str = Field(default="", max_length=256, description="shown in the driver's state and log")


class EStopClear(BaseModel):
    """``POST /v1/robots/{id}/estop/clear``: the robot may move again once cleared, so the request
    must say so explicitly."""

    model_config = ConfigDict(extra="forbid", strict=True)
    confirm: Literal[True] = Field(description="must be true: the robot may move again")


class Candidate(BaseModel):
    """A place the target may be, as the planner weighed it at its latest decision (its
    ``plan_trace``): the best cell of a cluster of its decision value map."""

    x: float
    y: float
    value: float


class MapView(BaseModel):
    """``GET /v1/robots/{id}/map``: the robot's map for the operator's page.

    ``image`` is the raster (unexplored, free, value heat, obstacles) of the window that holds
    everything worth showing, one pixel per cell, world +y up; its bottom-left corner is at
    (``x0``, ``y0``) and it is ``width`` x ``height`` cells of ``resolution`` metres. Everything
    else is in world metres, for the page to draw over it.
    """

    seq: int = Field(description="the newest frame the map fused")
    odom_session: str = Field(description="the odometry session the map belongs to (its frames' "
                                          "odometry frame; a driver restart starts a new map)")
    map_T_odom: Pose = Field(default_factory=lambda: Pose(x=0.0, y=0.0, yaw=0.0), description="where that odometry frame lies in the map: "
                             "localization's correction of odometry's drift (identity without it)")
    stamp: float
    resolution: float
    x0: float
    y0: float
    width: int
    height: int
    image: str = Field(description="a data: URL of the raster (PNG)")
    layers: list[str] = Field(description="the value layers the map holds (one per target)")
    layer: str | None = Field(description="the layer shown; null = the aggregate of all")
    frontiers: list[tuple[float, float]]
    candidates: list[Candidate]
    objects: list[ObjectInstance] = Field(description="objects the map believes exist")
    task_id: str | None = Field(description="the robot's latest task (its path and found objects)")
    path: list[tuple[float, float]]
    found: list[FoundObject]
    robot: Pose | None
    robot_radius_m: float = Field(description="the robot's footprint, to draw it to scale")
    goal: Goal | None = Field(description="where the planner takes the robot (searching only)")


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
        distance_m=record.distance_m, message=record.message, misses=record.misses,
        position=None if position is None else Position(x=position[0], y=position[1]),
        odom_session=record.odom_session, queue_position=queue_position, created_at=timestamp(record.created),
        started_at=timestamp(record.started), updated_at=timestamp(record.updated),
        finished_at=timestamp(record.finished))
