"""The ``/v1/robots/{id}`` endpoints of the operator's page: the robot's state, its e-stop and
its map as data.

All plain ``def`` (FastAPI runs them on worker threads): the e-stop waits for the driver's
confirmation and the map for the mapping service, never on the event loop. The e-stop
endpoints need no task: they talk to the driver, whatever the planner does.
"""

from __future__ import annotations

from fastapi import APIRouter, HTTPException, status

from ovamos.services.gateway.maps import NoMap, map_view
from ovamos.services.gateway.models import EStopClear, EStopRequest, MapView, Problem, RobotState
from ovamos.services.gateway.robots import EStopUnconfirmed
from ovamos.services.gateway.routes import GW, Gateway, robot_pose
from ovamos.shared.messages import TaskStatus

router = APIRouter(prefix="/v1/robots", responses={401: {"model": Problem}, 404: {"model": Problem}})


def _known(gw: Gateway, robot_id: str) -> None:
    if robot_id not in gw.config.robots:
        raise HTTPException(status.HTTP_404_NOT_FOUND,
                            f"unknown robot {robot_id!r}; known: {', '.join(gw.config.robots)}")




def _state(gw: Gateway, robot_id: str) -> RobotState:
    driver, active = gw.monitor.driver(robot_id), gw.store.active(robot_id)
    return RobotState(robot_id=robot_id, driver=None if driver is None else driver.message,
                      driver_age_s=None if driver is None else round(driver.age_s(), 3),
                      pose=robot_pose(gw, robot_id), active_task=None if active is None else active.id)


@router.get("/{robot_id}", response_model=RobotState)
def robot_state(robot_id: str, gw: GW) -> RobotState:
    """The driver's latest state (mode, e-stop latch, faults) and the robot's pose."""
    _known(gw, robot_id)
    return _state(gw, robot_id)


@router.post("/{robot_id}/estop", response_model=RobotState,
             responses={422: {"model": Problem}, 504: {"model": Problem}})
def engage_estop(robot_id: str, gw: GW, body: EStopRequest | None = None) -> RobotState:
    """Latch the driver's emergency stop (running or not, with or without a task); answered once
    the driver reports it latched, 504 when it does not within ``estop_confirm_s``. The task,
    if any, waits (its planner sends nothing while the e-stop is latched)."""
    _known(gw, robot_id)
    try:
        gw.monitor.engage_estop(robot_id, (body or EStopRequest()).reason or "operator's E-STOP")
    except EStopUnconfirmed as exc:
        raise HTTPException(status.HTTP_504_GATEWAY_TIMEOUT, str(exc)) from None
    return _state(gw, robot_id)


@router.post("/{robot_id}/estop/clear", response_model=RobotState,
             responses={422: {"model": Problem}, 504: {"model": Problem}})
def clear_estop(robot_id: str, body: EStopClear, gw: GW) -> RobotState:
    """Release the e-stop latch (``{"confirm": true}`` required: the robot may move again, and a
    running task resumes); answered once the driver reports it released."""
    _known(gw, robot_id)
    try:
        gw.monitor.clear_estop(robot_id)
    except EStopUnconfirmed as exc:
        raise HTTPException(status.HTTP_504_GATEWAY_TIMEOUT, str(exc)) from None
    return _state(gw, robot_id)


@router.get("/{robot_id}/map", response_model=MapView,
            responses={422: {"model": Problem}, 503: {"model": Problem}})
def robot_map_view(robot_id: str, gw: GW, layer: str | None = None) -> MapView:
    """The map as a raster and vector layers (frontiers, candidates, objects, the latest task's
    path and found objects, the robot's pose, the planner's goal), for the operator's page."""
    _known(gw, robot_id)
    try:
        snapshot = gw.fetch_map(robot_id)
    except NoMap as exc:
        raise HTTPException(status.HTTP_503_SERVICE_UNAVAILABLE, str(exc)) from None
    latest = gw.store.list(robot_id, limit=1)
    task = latest[0] if latest else None
    searching = task is not None and task.status is TaskStatus.SEARCHING
    try:
        return map_view(snapshot, task, layer=layer, robot=robot_pose(gw, robot_id, snapshot),
                        goal=gw.manager.goal(robot_id, task.id) if searching else None,
                        decision=gw.monitor.decision(robot_id, task.id) if searching else None)
    except ValueError as exc:
        raise HTTPException(422, str(exc)) from None
