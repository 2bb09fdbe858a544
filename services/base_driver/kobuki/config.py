"""How the driver reaches a Kobuki (the ``[driver.kobuki]`` section): its port and the wheel figures."""

from __future__ import annotations

from pydantic import Field

from ovamos.services.base_driver.kobuki.protocol import BAUDRATE, TICK_TO_RAD, WHEEL_BASE_M
from ovamos.shared.config import StrictModel

__all__ = ["KobukiConfig"]


class KobukiConfig(StrictModel):
    """How to reach a Kobuki. The wheel figures are the Kobuki's published ones (see the protocol module)."""

    port: str = Field(default="/dev/kobuki",
                      description="serial device: /dev/kobuki with kobuki_ftdi's udev rule, else /dev/ttyUSB0")
    baudrate: int = Field(default=BAUDRATE, gt=0, description="the Kobuki speaks 115200 8N1")
    read_timeout_s: float = Field(default=0.05, gt=0, description="reader thread's poll; bounds close()")
    write_timeout_s: float = Field(default=0.1, gt=0, description="a command that cannot leave in this is an error")
    first_feedback_timeout_s: float = Field(
        default=1.0, gt=0, description="open() fails unless Basic Sensor Data arrives within this (50 Hz normally)")
    wheel_base_m: float = Field(default=WHEEL_BASE_M, gt=0, description="for (v, w) -> speed / radius")
    tick_to_rad: float = Field(default=TICK_TO_RAD, gt=0, description="encoder tick -> wheel angle")
