"""The services' dataflow, declared once: what each service takes in and puts out.

This table is the architecture in data (like a dora dataflow or ``ros2 node
info``): services wire themselves from it (:meth:`ovamos.shared.service.Service.wire`),
so a key a service uses but does not declare cannot exist, and ``ovamos graph``
prints it. Keys are named by their builder in :mod:`ovamos.shared.keys`; every key is
under ``ovamos/<robot_id>/``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from ovamos.shared import keys
from ovamos.shared.messages import (
    CameraState,
    DecisionTrace,
    DriverState,
    EStop,
    MapSnapshot,
    Odometry,
    PerceptionResult,
    PlanCommand,
    RgbdFrame,
    TaskEvent,
    TaskSpec,
    UnknownTargets,
)

__all__ = ["Port", "Node", "TOPOLOGY", "graph"]


@dataclass(frozen=True)
class Port:
    """One key a service uses, with its message type.

    ``keep``: for inputs, 0 = every message, in order; n > 0 = only the newest n are
    kept while the service is busy (frames, maps, odometry: a slow consumer drops
    stale samples, counted, instead of queueing them without bound).
    """

    name: str
    message: type | None  # None: raw payloads of any type (monitoring)
    keep: int = 0

    def key(self, robot_id: str) -> str:
        return getattr(keys, self.name)(robot_id)

    def describe(self) -> dict[str, Any]:
        out: dict[str, Any] = {"key": self.key("{robot_id}"),
                               "message": None if self.message is None else self.message.__name__}
        if self.keep:
            out["keep_latest"] = self.keep
        return out


@dataclass(frozen=True)
class Node:
    """A service: its adapter (``module:Class``, what ``ovamos run`` starts, imported only then) and its
    ports: subscriptions, publications, queryables it answers, keys it queries."""

    adapter: str
    inputs: tuple[Port, ...] = ()
    outputs: tuple[Port, ...] = ()
    answers: tuple[Port, ...] = ()
    queries: tuple[Port, ...] = ()

    def port(self, kind: str, name: str) -> Port:
        for port in getattr(self, kind):
            if port.name == name:
                return port
        raise KeyError(f"no {kind[:-1]} {name!r} declared")


_DRIVER_IN = (Port("plan_command", PlanCommand), Port("estop", EStop), Port("estop_clear", EStop))
_DRIVER_OUT = (Port("odom", Odometry), Port("driver_state", DriverState))
_AT = "ovamos.services."

TOPOLOGY: dict[str, Node] = {
    "sim": Node(_AT + "sim.service:SimRobotService",
                inputs=_DRIVER_IN, outputs=(*_DRIVER_OUT, Port("rgbd", RgbdFrame))),
    "base_driver": Node(_AT + "base_driver.service:BaseDriverService", inputs=_DRIVER_IN, outputs=_DRIVER_OUT),
    "camera": Node(_AT + "camera.service:CameraService",
                   inputs=(Port("odom", Odometry), Port("driver_state", DriverState)),
                   outputs=(Port("rgbd", RgbdFrame), Port("camera_state", CameraState))),
    "perception": Node(_AT + "perception.service:PerceptionService",
                       inputs=(Port("task_current", TaskSpec), Port("task_events", TaskEvent),
                               Port("rgbd", RgbdFrame, keep=1)),
                       outputs=(Port("perception_result", PerceptionResult),
                                Port("unknown_targets", UnknownTargets))),
    "mapping": Node(_AT + "mapping.service:MappingService",
                    inputs=(Port("rgbd", RgbdFrame, keep=1), Port("perception_result", PerceptionResult),
                            Port("odom", Odometry, keep=1)),
                    outputs=(Port("map_snapshot", MapSnapshot),),
                    answers=(Port("map_snapshot", MapSnapshot),)),
    "planner": Node(_AT + "planner.service:PlannerService",
                    inputs=(Port("task_current", TaskSpec), Port("driver_state", DriverState),
                            Port("camera_state", CameraState), Port("unknown_targets", UnknownTargets),
                            Port("odom", Odometry, keep=1), Port("map_snapshot", MapSnapshot, keep=1)),
                    outputs=(Port("plan_command", PlanCommand), Port("task_events", TaskEvent),
                             Port("plan_trace", DecisionTrace)),
                    queries=(Port("map_snapshot", MapSnapshot),)),
    "gateway": Node(_AT + "gateway.service:GatewayService",
                    inputs=(Port("task_events", TaskEvent), Port("driver_state", DriverState),
                            Port("odom", Odometry, keep=1), Port("plan_trace", DecisionTrace, keep=1)),
                    outputs=(Port("task_current", TaskSpec), Port("estop", EStop), Port("estop_clear", EStop)),
                    queries=(Port("map_snapshot", MapSnapshot),)),
    "rosview": Node(_AT + "rosview.service:RosViewService",
                    inputs=(Port("map_snapshot", MapSnapshot, keep=1), Port("odom", Odometry, keep=1),
                            Port("plan_trace", DecisionTrace), Port("task_events", TaskEvent))),
    "testpattern": Node(_AT + "diag.service:TestPatternService", outputs=(Port("rgbd", RgbdFrame),)),
    "monitor": Node(_AT + "diag.service:MonitorService", inputs=(Port("robot_all", None),)),
}

DRIVERS = tuple(name for name, node in TOPOLOGY.items() if any(p.name == "driver_state" for p in node.outputs))
"""The services that drive a robot: their liveliness says whether it is reachable, and live."""


def graph() -> dict[str, Any]:
    """The table as plain data: ``{"services": {name: {"inputs": [...], "outputs": [...], ...}}}``."""
    services: dict[str, Any] = {}
    for name, node in TOPOLOGY.items():
        entry: dict[str, Any] = {"inputs": [p.describe() for p in node.inputs],
                                 "outputs": [p.describe() for p in node.outputs]}
        if node.answers:
            entry["answers"] = [p.describe() for p in node.answers]
        if node.queries:
            entry["queries"] = [p.describe() for p in node.queries]
        services[name] = entry
    return {"services": services}
