"""Checks a frame must pass before any model sees it.

A decodable :class:`~ovamos.shared.messages.RgbdFrame` already has a uint8 H x W x 3
image and a depth image of the same size (the bus drops, and counts, any
other); :func:`frame_problem` adds what the models need on top: a usable size.
"""

from __future__ import annotations

from ovamos.services.perception.config import FrameLimits
from ovamos.shared.messages import RgbdFrame


def frame_problem(frame: RgbdFrame, limits: FrameLimits) -> str | None:
    """Why ``frame`` cannot be processed, or None when it can."""
    height, width = frame.depth.shape
    if limits.size is not None and (width, height) != limits.size:
        return f"frame is {width}x{height}, the camera is configured for {limits.size[0]}x{limits.size[1]}"
    if min(width, height) < limits.min_side or max(width, height) > limits.max_side:
        return (f"frame is {width}x{height}, sides must be within "
                f"{limits.min_side}..{limits.max_side} pixels")
    return None
