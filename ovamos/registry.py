"""Which services ``ovamos run`` can start, imported lazily.

Lazy imports keep a robot that only runs the base driver free of the heavy
dependencies (torch, MuJoCo) of the services it does not run.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # importing ovamos.shared.service loads Zenoh; profiles only need the names
    from ovamos.shared.service import Service

SERVICES: dict[str, str] = {
    "testpattern": "ovamos.services.diag.service:TestPatternService",
    "monitor": "ovamos.services.diag.service:MonitorService",
    "mapping": "ovamos.services.mapping.service:MappingService",
    "planner": "ovamos.services.planner.service:PlannerService",
    "gateway": "ovamos.services.gateway.service:GatewayService",
    "perception": "ovamos.services.perception.service:PerceptionService",
    "sim": "ovamos.services.sim.service:SimRobotService",
    "base_driver": "ovamos.services.base_driver.service:BaseDriverService",
    "camera": "ovamos.services.camera.service:CameraService",
    "rosview": "ovamos.services.rosview.service:RosViewService",
}


class UnknownServiceError(LookupError):
    """A service name ``ovamos run`` cannot start."""


def service_class(name: str) -> type[Service]:
    if name not in SERVICES:
        raise UnknownServiceError(f"unknown service {name!r}; available: {', '.join(SERVICES)}")
    module, _, attr = SERVICES[name].partition(":")
    return getattr(importlib.import_module(module), attr)
