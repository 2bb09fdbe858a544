"""The simulated robot's settings: the scene, how its base moves, and when it renders a frame.

It stands in for the base driver, so it publishes odometry and driver state at the rates a
driver does (:class:`~ovamos.services.base_driver.config.PublishingConfig`).
"""

from __future__ import annotations

from pathlib import Path

from pydantic import Field, model_validator

from ovamos.services.base_driver.config import DriverConfig, PublishingConfig
from ovamos.services.base_driver.odrive.config import SimAxisConfig
from ovamos.services.sim.robot import MotionConfig
from ovamos.services.sim.wheels import Motion
from ovamos.shared.motion import Pose

__all__ = ["SimServiceConfig"]


class SimServiceConfig(PublishingConfig):
    scene_file: Path | None = Field(default=None, description="else the episode's scene")
    episode_seed: int = 0
    episode_index: int = Field(default=0, ge=0)
    start: Pose | None = Field(default=None, description="required with scene_file; else the episode's")
    motion: Motion = "kinematic"
    robot: MotionConfig = Field(default_factory=MotionConfig, description="primitive sizes, wheel geometry")
    driver: DriverConfig = Field(default_factory=DriverConfig,
                                 description="odrive mode; geometry and primitive sizes come from robot")
    odrive: SimAxisConfig = Field(default_factory=SimAxisConfig)
    lock_step: bool = True
    frame_hz: float = Field(default=2.0, gt=0, description="free-running frame rate")
    republish_s: float = Field(default=1.0, gt=0, description="lock-step: re-publish the latest frame")
    width: int = Field(default=640, ge=16)
    height: int = Field(default=480, ge=16)

    @model_validator(mode="after")
    def _start_with_scene(self) -> SimServiceConfig:
        if self.scene_file is not None and self.start is None:
            raise ValueError("a scene_file needs a start pose (start = {x = ..., y = ..., yaw = ...})")
        return self
