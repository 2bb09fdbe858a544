"""Every setting of the planner service (unknown keys are errors, as for every service).

:class:`PlannerServiceConfig` is the service's: its polling and request timings, over the
executive's (:class:`ovamos.services.planner.executive.ExecutiveConfig`: the lock-step protocol,
and under ``agent`` the search itself, its policy included).
"""

from __future__ import annotations

from pydantic import Field

from ovamos.services.planner.executive import ExecutiveConfig
from ovamos.shared.config import ServiceConfig


class PlannerServiceConfig(ServiceConfig, ExecutiveConfig):
    tick_hz: float = Field(default=20.0, gt=0, description="how often the protocol is polled")
    query_timeout_s: float = Field(default=0.5, gt=0, description="wait this long for a map on request")
    off_grace_s: float = Field(
        default=0.5, gt=0, description="after a driver's token goes, wait this long for its word that it "
                                       "shut down before saying the robot is unreachable")
