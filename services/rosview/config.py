"""The rosview service's settings: where on the ROS graph the search is shown, and how often."""

from __future__ import annotations

from pydantic import Field

from ovamos.shared.config import ServiceConfig
from ovamos.shared.ros2 import NETWORK_FIELD, Network
from ovamos.shared.sessions import SessionSwitch

__all__ = ["RosViewConfig"]


class RosViewConfig(ServiceConfig):
    prefix: str = Field(default="/ovamos", description="topic prefix ('/robot1/ovamos' for a fleet robot)")
    frame_id: str = Field(default="odom", description="the frame everything is in (our odometry's)")
    publish_hz: float = Field(default=2.0, gt=0, description="how often what changed is published")
    path_step_m: float = Field(default=0.05, gt=0, description="a path pose every this far")
    path_poses: int = Field(default=5000, ge=2, description="the path keeps this many poses at most")
    network: Network = NETWORK_FIELD
    session_switch: SessionSwitch = Field(
        default_factory=SessionSwitch, description="when odometry of a new odometry session is followed (the "
        "driver restarted): others are counted, never drawn")
