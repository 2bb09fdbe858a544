"""The ODrive base's settings: the CAN bus and the two axes (the ``[driver.odrive]`` section), and the
simulated ODrives' own configuration.

``CanConfig`` is python-can's standard bus configuration, passed to ``can.Bus(**bus_kwargs())``
unchanged, so a real robot uses e.g. ``interface = "socketcan", channel = "can0", bitrate = 250000``.
"""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

from ovamos.shared.config import StrictModel

__all__ = ["CanConfig", "AxisConfig", "ODriveConfig", "SimAxisConfig"]


class CanConfig(StrictModel):
    """python-can bus settings (``can.Bus(interface=..., channel=..., bitrate=...)``)."""

    interface: str = Field(default="virtual", description="socketcan, pcan, slcan, virtual, ...")
    channel: str = Field(default="ovamos-base", description="can0 for socketcan")
    bitrate: int | None = Field(default=None, gt=0, description="e.g. 250000; None = the interface's")

    def bus_kwargs(self) -> dict[str, Any]:
        kwargs: dict[str, Any] = {"interface": self.interface, "channel": self.channel}
        if self.bitrate is not None:
            kwargs["bitrate"] = self.bitrate
        return kwargs


class AxisConfig(StrictModel):
    """One wheel's ODrive axis. ``direction`` -1 for a motor mounted mirrored."""

    node_id: int = Field(ge=0, le=63)
    direction: Literal[1, -1] = 1


class ODriveConfig(StrictModel):
    """The ``odrive_can`` hardware: two ODrive axes over CANSimple."""

    can: CanConfig = Field(default_factory=CanConfig)
    left: AxisConfig = Field(default_factory=lambda: AxisConfig(node_id=0))
    right: AxisConfig = Field(default_factory=lambda: AxisConfig(node_id=1))
    current_limit_a: float = Field(default=10.0, gt=0, description="sent with Set_Limits")

    @model_validator(mode="after")
    def _distinct_nodes(self) -> ODriveConfig:
        if self.left.node_id == self.right.node_id:
            raise ValueError("left and right axes need different node ids")
        return self


class SimAxisConfig(BaseModel):
    """What the simulated ODrives are configured with (on hardware: the ODrive's own config)."""

    model_config = ConfigDict(extra="forbid")
    vel_ramp_rate_rev_s2: float = Field(default=20.0, gt=0, description="VEL_RAMP input mode")
    idle_decel_rev_s2: float = Field(default=20.0, gt=0, description="a disarmed wheel coasts to rest")
    watchdog_timeout_s: float = Field(default=0.3, ge=0, description="0 disables the watchdog")
    heartbeat_period_s: float = Field(default=0.1, gt=0)
    encoder_period_s: float = Field(default=0.01, gt=0)
    vel_limit_rev_s: float = Field(default=2.0, gt=0, description="until Set_Limits changes it")
