"""Every setting of the base driver (unknown keys are errors, as for every service).

:class:`BaseDriverServiceConfig` is the service's: how often its outputs go out
(:class:`PublishingConfig`, which the simulated robot shares), the driver, and the simulated ODrives
of a dry run. :class:`DriverConfig` holds the controller's settings (geometry, limits, timing,
primitives: whatever the base) and names the hardware interface (``hardware``); each base's own
section (``odrive``, ``kobuki``, ``opencr``, ``ros2``) is defined in its subpackage's ``config.py``.
Defaults are a TurtleBot3 Waffle-like base: 0.26 m/s and 1.82 rad/s top speeds, the wheel geometry
and primitive sizes of :mod:`ovamos.shared.robot`.
"""

from __future__ import annotations

import math
from typing import Literal

from pydantic import Field, model_validator

from ovamos.services.base_driver.kobuki.config import KobukiConfig
from ovamos.services.base_driver.kobuki.protocol import WHEEL_RADIUS_M as KOBUKI_WHEEL_RADIUS_M
from ovamos.services.base_driver.odrive.config import ODriveConfig, SimAxisConfig
from ovamos.services.base_driver.opencr.config import OpenCRConfig
from ovamos.services.base_driver.opencr.table import MODELS as TB3_MODELS
from ovamos.services.base_driver.ros2.config import Ros2BaseConfig
from ovamos.shared.config import ServiceConfig, StrictModel
from ovamos.shared.motion import Pose
from ovamos.shared.robot import PRIMITIVES, ROBOT, Primitives


class FollowConfig(StrictModel):
    """How a path command is followed (:mod:`ovamos.services.base_driver.follower`): a regulated
    pure pursuit on odometry, within the driver's speed and acceleration limits."""

    lookahead_m: float = Field(default=0.3, gt=0, description="the point steered toward, this far along the path")
    goal_tolerance_m: float = Field(default=0.05, gt=0, description="the path is done this close to its last point")
    rotate_in_place_rad: float = Field(
        default=0.8, gt=0, le=math.pi,
        description="a heading error to the lookahead point above this turns the base in place first")
    min_radius_m: float = Field(default=0.5, gt=0, description="tighter curves than this are driven slower, "
                                                                 "in proportion (regulated pure pursuit)")
    min_speed_m_s: float = Field(default=0.05, gt=0, description="the slowest a curve or the goal's approach drives")
    corner_rad: float = Field(default=0.6, gt=0, le=math.pi,
                              description="a waypoint where the path turns by more than this is a corner: driven "
                                          "to, slowing, and turned at, not cut")
    corner_pass_m: float = Field(default=0.1, gt=0, description="a corner is gone round once the robot is this close")
    back_off_m: float = Field(default=0.1, gt=0, description="with back_off_on_bump, a path stopped by a collision "
                                                             "report drives back this far before it completes blocked")
    slow_clearance_m: float = Field(
        default=0.2, ge=0,
        description="a gap narrower than this between the footprint (footprint_m) and the nearest obstacle the "
                    "path command names drives proportionally slower (regulated pure pursuit's proximity "
                    "rule), down to near_obstacle_m_s; 0: never")
    near_obstacle_m_s: float = Field(
        default=0.12, gt=0,
        description="the slowest the proximity rule drives: planned paths keep only the navigator's radius "
                    "(below the footprint) from mapped obstacles, and scaled to zero the robot crept along "
                    "every piece of furniture (Nav2's regulated pure pursuit floors it likewise)")
    footprint_m: float = Field(default=ROBOT.radius_m, gt=0, description="the robot's radius, for the gap to an obstacle")


class DriverConfig(StrictModel):
    hardware: Literal["odrive_can", "kobuki", "opencr", "ros2"] = Field(
        default="odrive_can", description="the base's hardware interface: odrive_can (a custom CAN base), "
                                          "kobuki (TurtleBot 2), opencr (TurtleBot 3), ros2 (a base run by "
                                          "ROS 2: cmd_vel out, its odometry in)")
    odrive: ODriveConfig = Field(default_factory=ODriveConfig)
    kobuki: KobukiConfig = Field(default_factory=KobukiConfig)
    opencr: OpenCRConfig = Field(default_factory=OpenCRConfig)
    ros2: Ros2BaseConfig = Field(default_factory=Ros2BaseConfig)
    # geometry
    wheel_radius_m: float = Field(default=ROBOT.wheel_radius_m, gt=0)
    track_width_m: float = Field(default=ROBOT.track_width_m, gt=0)
    initial_pose: Pose = Field(default_factory=lambda: Pose(x=0.0, y=0.0, yaw=0.0),
                               description="odometry starts here (the simulator: the start pose)")
    # limits
    max_linear_m_s: float = Field(default=0.26, gt=0)
    max_angular_rad_s: float = Field(default=1.82, gt=0)
    max_linear_accel_m_s2: float = Field(default=1.0, gt=0)
    max_angular_accel_rad_s2: float = Field(default=4.0, gt=0)
    # timing
    control_hz: float = Field(default=50.0, gt=0, le=500, description="velocity setpoint rate")
    feedback_timeout_s: float = Field(default=0.3, gt=0,
                                      description="older feedback (ODrive: heartbeat, encoder) = fault")
    deadman_s: float = Field(default=0.5, gt=0, description="no command for this long: ramp to zero")
    command_timeout_s: float | None = Field(
        default=None, gt=0, description="a primitive whose command stops being re-sent (the planner's "
                                        "keep-alive, every resend_s) for this long is aborted and the "
                                        "wheels ramp to zero: a lost link stops the robot mid-primitive; "
                                        "None = a primitive runs to its goal")
    enable_timeout_s: float = Field(default=2.0, gt=0,
                                    description="after open(), healthy feedback must come within this")
    recover_every_s: float = Field(default=1.0, gt=0, description="retry after a fault this often")
    auto_recover: bool = Field(default=True, description="re-open once a fault's cause is gone")
    # primitives (ovamos.shared.robot's sizes; advertised in driver/state) and their closed loop
    forward_m: float = Field(default=PRIMITIVES.forward_m, gt=0)
    turn_deg: float = Field(default=PRIMITIVES.turn_deg, gt=0, le=180)
    linear_tolerance_m: float = Field(default=0.002, gt=0)
    angular_tolerance_rad: float = Field(default=0.003, gt=0)
    approach_gain: float = Field(default=4.0, gt=0, description="1/s; speed = gain * remaining near the goal")
    creep_m_s: float = Field(default=0.01, gt=0, description="slowest approach speed")
    creep_rad_s: float = Field(default=0.05, gt=0)
    heading_gain: float = Field(default=2.0, ge=0, description="1/s; holds the heading on a forward move")
    settle_rev_s: float = Field(default=0.01, gt=0, description="wheels slower than this are at rest")
    primitive_timeout_s: float = Field(default=10.0, gt=0, description="abort a primitive after this")
    follow: FollowConfig = Field(default_factory=FollowConfig, description="path commands")
    back_off_on_bump: bool = Field(
        default=True,
        description="a MOVE_FORWARD stopped by a collision report (BaseController.bump: the "
                    "simulator's contact check) drives straight back to where it started (a path: "
                    "follow.back_off_m) before it completes as blocked: the planner treats a blocked step as not made, and "
                    "a robot left touching the obstacle cannot plan its way out")
    stall_s: float | None = Field(
        default=1.0, gt=0,
        description="a move driven at 0.05 m/s or more for this long whose odometry advanced less than "
                    "a quarter of the way commanded is stopped as a bump (a base with no bumper, e.g. a "
                    "TurtleBot 3, pushing against a wall: its wheels stall); None: off")

    def fixed_wheels(self) -> tuple[float, float, str] | None:
        """(wheel radius, track width, what) of a base whose wheels its hardware fixes (a Kobuki, a
        TurtleBot 3 model), None for one whose config sets them (ODrive)."""
        if self.hardware == "kobuki":
            return KOBUKI_WHEEL_RADIUS_M, self.kobuki.wheel_base_m, "a Kobuki"
        if self.hardware == "opencr":
            model = TB3_MODELS[self.opencr.model]
            return model.wheel_radius_m, model.track_m, f"a TurtleBot 3 {model.name}"
        return None

    @model_validator(mode="after")
    def _geometry_fits_the_hardware(self) -> DriverConfig:
        """Odometry computed with other wheels than the hardware's would be wrong by the ratio, so
        a config that disagrees with :meth:`fixed_wheels` is refused."""
        fixed = self.fixed_wheels()
        if fixed is None:
            return self
        radius, track, what = fixed
        if not (math.isclose(self.wheel_radius_m, radius) and math.isclose(self.track_width_m, track)):
            raise ValueError(f"{what} has {radius} m wheels {track} m apart: set wheel_radius_m = {radius} "
                             f"and track_width_m = {track} under [driver] (got {self.wheel_radius_m}, "
                             f"{self.track_width_m})")
        return self

    @property
    def primitives(self) -> Primitives:
        """The primitive sizes this driver executes (what it advertises)."""
        return Primitives(forward_m=self.forward_m, turn_deg=self.turn_deg)

    @property
    def max_wheel_rev_s(self) -> float:
        """The fastest a wheel may turn: the top linear speed (rev/s)."""
        return self.max_linear_m_s / (2 * math.pi * self.wheel_radius_m)


class PublishingConfig(ServiceConfig):
    """How often the driver's outputs go out (shared by the real and the simulated base)."""

    odom_hz: float = Field(default=20.0, gt=0)
    state_hz: float = Field(default=5.0, gt=0, description="also published on every change")
    tick_hz: float = Field(default=50.0, gt=0, description="how often changes are looked for")


class BaseDriverServiceConfig(PublishingConfig):
    driver: DriverConfig = Field(default_factory=DriverConfig)
    simulated_axes: bool = Field(default=False, description="simulated ODrives on the virtual bus")
    sim_axes: SimAxisConfig = Field(default_factory=SimAxisConfig)

    @model_validator(mode="after")
    def _virtual_for_sim(self) -> BaseDriverServiceConfig:
        if self.simulated_axes and (self.driver.hardware != "odrive_can"
                                    or self.driver.odrive.can.interface != "virtual"):
            raise ValueError("simulated_axes needs driver.hardware = 'odrive_can' and "
                             "driver.odrive.can.interface = 'virtual'")
        return self
