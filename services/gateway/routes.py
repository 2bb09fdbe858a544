"""The ``/v1`` HTTP endpoints.

Handlers that query Zenoh (through the callables the adapter put in :class:`Gateway`) or
SQLite are plain ``def``: FastAPI runs them on worker threads, so a slow query never blocks
the event loop; the one ``async``
handler (the event stream) reads through ``asyncio.to_thread``. Reads go
straight to the store (they never wait for a commit); submit and cancel are
run by the TaskManager's owner thread while the worker thread waits (503 when
it cannot take them in time, with nothing changed)."""

from __future__ import annotations

import asyncio
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Annotated

from fastapi import APIRouter, Depends, HTTPException, Query, Request, Response, status
from fastapi.responses import StreamingResponse

from ovamos.services.gateway.config import GatewayConfig
from ovamos.services.gateway.maps import NoMap, map_png
from ovamos.services.gateway.models import (
    Health,
    Pose,
    Problem,
    RobotHealth,
    ServiceEntry,
    TaskAccepted,
    TaskList,
    TaskRequest,
    TaskView,
    check_against_config,
    task_view,
)
from ovamos.services.gateway.robots import RobotMonitor
from ovamos.services.gateway.sse import TaskWatchers, task_stream
from ovamos.services.gateway.store import TaskRecord, TaskStore
from ovamos.services.gateway.tasks import GatewayBusy, TaskConflict, TaskManager
from ovamos.shared.messages import MapSnapshot, TaskStatus
from ovamos.shared.motion import Pose as MotionPose


@dataclass
class Gateway:
    """What the handlers need, created in the app's lifespan.

    ``fetch_map(robot_id)``: the robot's current map from its mapping service, NoMap when none
    answers; ``alive()``: the service instances alive on each robot. Both ask Zenoh and block
    (worker threads only)."""

    config: GatewayConfig
    store: TaskStore
    manager: TaskManager
    watchers: TaskWatchers
    monitor: RobotMonitor
    fetch_map: Callable[[str], MapSnapshot]
    alive: Callable[[], Mapping[str, list[ServiceEntry]]]

    def view(self, record: TaskRecord) -> TaskView:
        return task_view(record, self.store.queue_position(record))

    def find(self, task_id: str) -> TaskRecord:
        record = self.store.get(task_id)
        if record is None:
            raise HTTPException(status.HTTP_404_NOT_FOUND, f"no task {task_id!r}")
        return record


def _gateway(request: Request) -> Gateway:
    return request.app.state.gateway


GW = Annotated[Gateway, Depends(_gateway)]
ODOM_SESSION_HEADER = "X-Ovamos-Odom-Session"
"""The map.png answer's header naming the odometry session the map belongs to."""
router = APIRouter(prefix="/v1", responses={401: {"model": Problem}})


def _busy(exc: GatewayBusy) -> HTTPException:
    return HTTPException(status.HTTP_503_SERVICE_UNAVAILABLE, str(exc))


@router.post("/tasks", status_code=status.HTTP_202_ACCEPTED, response_model=TaskAccepted,
             responses={422: {"model": Problem}, 503: {"model": Problem}})
def submit_task(body: TaskRequest, response: Response, gw: GW) -> TaskAccepted:
    """Queue a search. It starts at once when the robot is idle, else after the tasks before it."""
    robot_id, max_steps = check_against_config(body, gw.config)
    try:
        record = gw.manager.submit(robot_id, body.targets, max_steps)
    except GatewayBusy as exc:
        raise _busy(exc) from None
    location = f"/v1/tasks/{record.id}"
    response.headers["Location"] = location
    return TaskAccepted(id=record.id, status=record.status, robot_id=robot_id, location=location,
                        queue_position=gw.store.queue_position(record))


@router.get("/tasks", response_model=TaskList, responses={422: {"model": Problem}})
def list_tasks(gw: GW, robot_id: str | None = None, status: TaskStatus | None = None,
               limit: Annotated[int, Query(ge=1, le=1000)] = 100) -> TaskList:
    """Tasks, newest first."""
    return TaskList(tasks=[gw.view(r) for r in gw.store.list(robot_id, status, limit)])


@router.get("/tasks/{task_id}", response_model=TaskView, responses={404: {"model": Problem}})
def get_task(task_id: str, gw: GW) -> TaskView:
    """State, targets, found objects with positions, steps, distance, timestamps."""
    return gw.view(gw.find(task_id))


@router.delete("/tasks/{task_id}", response_model=TaskView,
               responses={404: {"model": Problem}, 409: {"model": Problem}, 503: {"model": Problem}})
def cancel_task(task_id: str, gw: GW) -> TaskView:
    """Cancel a queued or running task (the planner is told with a cancelled TaskSpec)."""
    try:
        record = gw.manager.cancel(task_id)
    except TaskConflict as exc:
        raise HTTPException(status.HTTP_409_CONFLICT, str(exc)) from None
    except GatewayBusy as exc:
        raise _busy(exc) from None
    if record is None:
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"no task {task_id!r}")
    return gw.view(record)


@router.get("/tasks/{task_id}/events", responses={404: {"model": Problem}, 200: {
    "content": {"text/event-stream": {}},
    "description": "`event: task` with the task's JSON at once, then on every change; "
                   "ends after the final state"}})
async def task_events(task_id: str, gw: GW) -> StreamingResponse:
    """Server-Sent Events of one task's progress."""
    await asyncio.to_thread(gw.find, task_id)

    def current() -> TaskView | None:
        record = gw.store.get(task_id)
        return None if record is None else gw.view(record)

    stream = task_stream(gw.watchers, task_id, current, gw.config.sse_heartbeat_s)
    return StreamingResponse(stream, media_type="text/event-stream",
                             headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"})


@router.get("/health", response_model=Health)
def health(gw: GW) -> Health:
    """Services alive per robot (Zenoh liveliness), each robot's queue, event counters."""
    alive = gw.alive()
    robots = {}
    for robot in gw.config.robots:
        active = gw.store.active(robot)
        robots[robot] = RobotHealth(services=alive.get(robot, []),
                                    active_task=active.id if active else None,
                                    queued=gw.store.count(robot, TaskStatus.QUEUED))
    return Health(robots=robots, counters=gw.manager.counters())


def robot_pose(gw: Gateway, robot_id: str, snapshot: MapSnapshot | None = None) -> Pose | None:
    """The robot's pose from its latest odometry (None before any); placed in ``snapshot``'s map
    (localization's ``map_T_odom``) when given and of the same odometry session."""
    odom = gw.monitor.odometry(robot_id)
    if odom is None:
        return None
    o = odom.message
    at = MotionPose(x=o.x, y=o.y, yaw=o.yaw)
    if snapshot is not None and snapshot.odom_session == o.odom_session:
        at = snapshot.to_map(at)
    return Pose(x=at.x, y=at.y, yaw=at.yaw)


@router.get("/robots/{robot_id}/map.png", response_class=Response, responses={
    200: {"content": {"image/png": {}}, "description": "the map, with the latest task's path; the "
          "odometry session it belongs to in the X-Ovamos-Odom-Session header"},
    404: {"model": Problem}, 422: {"model": Problem}, 503: {"model": Problem}})
def robot_map(robot_id: str, gw: GW, layer: str | None = None) -> Response:
    """The robot's current map from its mapping service (503 while none answers)."""
    if robot_id not in gw.config.robots:
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"unknown robot {robot_id!r}")
    try:
        snapshot = gw.fetch_map(robot_id)
    except NoMap as exc:
        raise HTTPException(status.HTTP_503_SERVICE_UNAVAILABLE, str(exc)) from None
    latest = gw.store.list(robot_id, limit=1)
    task = latest[0] if latest else None
    try:
        png = map_png(snapshot, layer=layer, task=task, robot=robot_pose(gw, robot_id, snapshot),
                      goal=gw.manager.goal(robot_id, task.id) if task is not None
                      and task.status is TaskStatus.SEARCHING else None)
    except ValueError as exc:
        raise HTTPException(422, str(exc)) from None
    return Response(png, media_type="image/png", headers={"Cache-Control": "no-store",
                                                          ODOM_SESSION_HEADER: snapshot.odom_session})
