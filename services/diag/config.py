"""The settings of the diag services: the test pattern's frame stream and the monitor's window."""

from __future__ import annotations

from pydantic import Field

from ovamos.shared.config import ServiceConfig

__all__ = ["TestPatternConfig", "MonitorConfig"]


class TestPatternConfig(ServiceConfig):
    rate_hz: float = Field(default=10.0, gt=0, le=200)
    width: int = Field(default=640, ge=8, le=4096)
    height: int = Field(default=480, ge=8, le=4096)
    seed: int = 0


class MonitorConfig(ServiceConfig):
    window_s: float = Field(default=5.0, gt=0)
    report_s: float = Field(default=5.0, gt=0, description="seconds between log lines")
