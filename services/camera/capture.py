"""What a camera backend hands the camera core: one captured, aligned RGB-D frame.

A backend (RealSense, OAK-D, a recording) knows its SDK and nothing else: it
delivers colour and depth aligned to the colour camera, the colour camera's
intrinsics, the depth unit, and when the frame was captured on the device's
clock. Everything about the robot (where the camera is mounted, where the base
was at the capture time, lock-step, faults) is the core's
(:mod:`ovamos.services.camera.core`), so every backend gets it the same way.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

from ovamos.shared.messages import Intrinsics

__all__ = ["CameraError", "CapturedFrame", "CameraBackend"]


class CameraError(RuntimeError):
    """The camera cannot deliver (not found, unplugged, stream stopped, bad recording)."""


@dataclass(frozen=True)
class CapturedFrame:
    """One RGB-D frame, depth aligned to colour (same size, same pixel grid)."""

    rgb: np.ndarray          # H x W x 3 uint8, RGB order
    depth: np.ndarray        # H x W uint16, units of depth_scale metres, 0 = no reading
    depth_scale: float       # metres per depth unit (0.001 for a D4xx at its default)
    intrinsics: Intrinsics   # of the colour camera, in pixels
    device_time_s: float     # capture time on the device's clock (seconds; any epoch)
    host_time_s: float       # time.monotonic() on this host when the frame was received
    #: which simulated object each pixel shows (H x W int32, -1 none): only a simulated robot's
    #: camera has it, for the simulated perception backend (``ovamos demo --base ros2``)
    instance_ids: np.ndarray | None = None


class CameraBackend(Protocol):
    """A source of :class:`CapturedFrame` s. ``read`` returns None when no frame came within
    ``timeout_s`` and raises :class:`CameraError` when the device is gone; ``start`` may be
    called again after a failure (recovery without restarting the process).

    Optional attributes the service reads when present: ``lossless`` (true: every frame matters
    and the source waits for its reader, as a recording played at ``rate = "max"``; the service
    then waits for room instead of keeping only the newest captures) and ``ended`` (true: the
    source is over, as a recording played to its end; not restarted)."""

    name: str

    def start(self) -> None: ...

    def read(self, timeout_s: float) -> CapturedFrame | None: ...

    def stop(self) -> None: ...
