"""Which ROS 2 topics drive a base run by ROS 2 (the ``[driver.ros2]`` section)."""

from __future__ import annotations

from pydantic import Field, field_validator

from ovamos.shared.config import StrictModel
from ovamos.shared.ros2 import NETWORK_FIELD, Network

__all__ = ["Ros2BaseConfig"]


class Ros2BaseConfig(StrictModel):
    """Which ROS 2 topics drive the base and report its odometry."""

    namespace: str = Field(default="", description="the robot's ROS namespace, e.g. '/robot1' ('' for none)")
    cmd_vel: str = Field(default="cmd_vel", description="velocity command topic (relative to namespace)")
    odom: str = Field(default="odom", description="nav_msgs/Odometry topic (relative to namespace)")
    stamped: bool = Field(default=True, description="TwistStamped (TurtleBot 3 on Jazzy, nav2) or, false, "
                                                     "Twist (the Create 3 / TurtleBot 4)")
    frame_id: str = Field(default="base_link", description="header.frame_id of a TwistStamped")
    estop: str | None = Field(default="estop", description="std_msgs/Bool topic whose true engages the "
                              "e-stop (relative to namespace); none: no ROS e-stop")
    bump: str | None = Field(default=None, description="std_msgs/Bool topic whose true says the base ran "
                             "into something (a bridge of a Create 3's hazard_detection; the simulated "
                             "robot's contact): the move ends blocked, as on a bumper; none: no such input")
    localization: str | None = Field(default=None, description="geometry_msgs/PoseWithCovarianceStamped topic of "
                                     "the robot's own localization in its map (AMCL: 'amcl_pose', slam_toolbox: "
                                     "'pose'; relative to namespace): passed on with the odometry, so a map whose "
                                     "[localization] source is 'base' follows it; none: not read")
    localization_max_std_m: float = Field(default=0.25, gt=0, description="a localized pose whose position "
                                          "is less certain than this (standard deviation) is not passed on")
    localization_max_std_deg: float = Field(default=10.0, gt=0, description="the same for its heading")
    network: Network = NETWORK_FIELD

    @field_validator("namespace")
    @classmethod
    def _namespace(cls, value: str) -> str:
        if value and (not value.startswith("/") or value.endswith("/") or " " in value):
            raise ValueError(f"namespace {value!r}: write '/name' (or '' for none)")
        return value

    def topic(self, name: str) -> str:
        """``name`` under the namespace."""
        return name if name.startswith("/") else f"{self.namespace}/{name}" if self.namespace else name
