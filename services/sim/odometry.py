"""How a simulated base's true motion departs from what its wheels report.

A real differential-drive base integrates its encoders with the nominal wheel radius and track
width, so its odometry drifts: systematically (one wheel a fraction of a percent larger than the
other, the track width off by a percent or two: UMBmark's E_d and E_b) and at random (slip, which
grows with the distance each wheel travels, Chong and Kleeman's variance k * |d| per wheel), and
most at a bump, where the robot is knocked round while the encoders see nothing. The simulator
keeps the encoders' story (what the driver, or the kinematic base, reports) and moves the true
robot by the perturbed one; the presets' numbers and their sources are in docs/method.md
(#odometry-as-a-real-base-reports-it).

A :class:`WheelSlip` is one robot: its systematic errors are drawn once from the preset's
magnitudes with a random sign each, its slip from the same seeded generator, so a seed gives
the same drift.
"""

from __future__ import annotations

import math
from typing import Literal, get_args

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

__all__ = ["OdometryErrors", "OdometryPreset", "ODOMETRY_PRESETS", "ODOMETRY_PRESET_NAMES", "WheelSlip",
           "odometry_errors"]

OdometryPreset = Literal["ideal", "realistic", "hard"]
ODOMETRY_PRESET_NAMES: tuple[str, ...] = get_args(OdometryPreset)


class OdometryErrors(BaseModel):
    """The size of each error source; the sign of each systematic one is drawn per robot."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    wheel_scale: float = Field(default=0.0, ge=0, lt=0.5, description="both wheels' radius off by this "
                               "fraction (a worn or under-inflated tyre): a distance error")
    wheel_ratio: float = Field(default=0.0, ge=0, lt=0.5, description="|E_d - 1|: the right wheel's radius "
                               "this fraction off the left's, a curve on a straight run")
    track_scale: float = Field(default=0.0, ge=0, lt=0.5, description="|E_b - 1|: the effective track width "
                               "off by this fraction, a heading error on every turn")
    slip_m: float = Field(default=0.0, ge=0, description="k of each wheel's random slip, variance k * |travel| "
                          "(metres): sqrt(k * 1 m) is the standard deviation over a metre")
    bump_deg: float = Field(default=0.0, ge=0, description="standard deviation of the turn a bump knocks the "
                            "robot through, unseen by the encoders")
    bump_m: float = Field(default=0.0, ge=0, description="standard deviation of the shift a bump gives it")

    @property
    def ideal(self) -> bool:
        return not any(self.model_dump().values())


ODOMETRY_PRESETS: dict[str, OdometryErrors] = {
    "ideal": OdometryErrors(),
    "realistic": OdometryErrors(wheel_scale=0.005, wheel_ratio=0.003, track_scale=0.015, slip_m=1e-5,
                                bump_deg=1.0, bump_m=0.005),
    "hard": OdometryErrors(wheel_scale=0.02, wheel_ratio=0.01, track_scale=0.04, slip_m=1e-4,
                           bump_deg=4.0, bump_m=0.02),
}
"""``ideal``: the true motion is what the wheels report (every result before odometry errors);
``realistic``: a TurtleBot on a hard floor, uncalibrated; ``hard``: a worn one on carpet."""


def odometry_errors(value: str | OdometryErrors | dict[str, float]) -> OdometryErrors:
    """A preset by name, or the errors given (a config file's table)."""
    if isinstance(value, str):
        if value not in ODOMETRY_PRESETS:
            raise ValueError(f"unknown odometry preset {value!r} (known: {', '.join(ODOMETRY_PRESET_NAMES)})")
        return ODOMETRY_PRESETS[value]
    return OdometryErrors.model_validate(value)


class WheelSlip:
    """One robot's odometry errors: true wheel travel and track from the nominal ones."""

    def __init__(self, errors: OdometryErrors, seed: int) -> None:
        self.errors = errors
        self._rng = np.random.default_rng(seed)
        signs = self._rng.choice((-1.0, 1.0), size=3)
        scale = 1.0 + signs[0] * errors.wheel_scale
        half_ratio = signs[1] * errors.wheel_ratio / 2
        self.left_scale = scale * (1.0 - half_ratio)
        self.right_scale = scale * (1.0 + half_ratio)
        self.track_scale = 1.0 + signs[2] * errors.track_scale

    @classmethod
    def of(cls, errors: OdometryErrors, seed: int) -> WheelSlip | None:
        """The robot's errors, or None for ``ideal`` ones (its wheels report the truth)."""
        return None if errors.ideal else cls(errors, seed)

    def wheels(self, left_m: float, right_m: float) -> tuple[float, float]:
        """How far each wheel truly carried the robot when its encoder says ``left_m`` / ``right_m``."""
        k = self.errors.slip_m
        noise = self._rng.normal(0.0, 1.0, 2) * np.sqrt(k * np.abs((left_m, right_m))) if k else (0.0, 0.0)
        return left_m * self.left_scale + float(noise[0]), right_m * self.right_scale + float(noise[1])

    def track(self, track_m: float) -> float:
        return track_m * self.track_scale

    def bump(self) -> tuple[float, float, float]:
        """A bump's knock in the robot's frame: (forward m, left m, turn rad)."""
        e = self.errors
        dx, dy, turn = self._rng.normal(0.0, 1.0, 3)
        return float(dx * e.bump_m), float(dy * e.bump_m), float(turn * math.radians(e.bump_deg))

