"""How the driver reaches a TurtleBot 3's OpenCR board (the ``[driver.opencr]`` section) and which model it drives."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from ovamos.services.base_driver.opencr import table as T
from ovamos.shared.config import StrictModel

__all__ = ["OpenCRConfig"]


class OpenCRConfig(StrictModel):
    """How to reach the OpenCR and which TurtleBot 3 it drives."""

    port: str = Field(default="/dev/ttyACM0", description="serial port (a udev symlink is best)")
    baudrate: int = Field(default=T.BAUDRATE, gt=0, description="the firmware's is 1000000")
    device_id: int = Field(default=T.DEVICE_ID, ge=0, le=252)
    model: Literal["burger", "waffle"] = "burger"
    poll_period_s: float = Field(default=0.02, gt=0, le=0.2,
                                 description="feedback() reads the board at most this often")
    heartbeat_period_s: float = Field(default=0.1, gt=0, lt=T.HEARTBEAT_TIMEOUT_S,
                                      description="below the firmware's 500 ms timeout")
    bumpers: bool = Field(default=False, description="optional touch sensors on bumper_1/2 (front/back)")
    open_attempts: int = Field(default=3, ge=1, description="pings before giving up (noise, a booting board)")
    write_attempts: int = Field(
        default=3, ge=1,
        description="tries of a write the board does not acknowledge in time before it is a fault: "
                    "writes are idempotent (a velocity, a heartbeat, torque), and one late answer "
                    "(a busy host, a USB hiccup) should not stop the robot")
