"""A synthetic RGB-D camera: a known, seeded frame stream for checking a deployment.

Like a video test card, it lets a user see that frames reach every consumer
intact and on time before a real camera or the simulator is attached. The
camera turns in place at the paper's camera height, so downstream code gets
plausible poses as well as pixels.
"""

from __future__ import annotations

import math

import numpy as np

from ovamos.shared.camera import DEPTH_RANGE_M, camera_pose, pinhole
from ovamos.shared.messages import RgbdFrame

TURN_PER_FRAME_RAD = math.radians(5.0)
_BARS = np.array([[255, 255, 255], [255, 255, 0], [0, 255, 255], [0, 255, 0],
                  [255, 0, 255], [255, 0, 0], [0, 0, 255], [0, 0, 0]], dtype=np.uint8)


def pattern_frame(seq: int, stamp: float, *, width: int = 640, height: int = 480, seed: int = 0
               ) -> RgbdFrame:
    """Frame ``seq`` of the stream: colour bars with a square that moves with ``seq``;
    depth is a ramp over the depth range with seeded noise. Same (seed, seq) => same frame."""
    rng = np.random.default_rng([seed, seq])
    arrays = RgbdFrame.loan(height, width)
    rgb, depth = arrays["rgb"], arrays["depth"]
    rgb[:] = _BARS[np.arange(width) * len(_BARS) // width]
    side = max(2, height // 8)
    x0 = (seq * 7) % max(1, width - side)
    rgb[height // 2 - side // 2:height // 2 + side // 2, x0:x0 + side] = 128
    near, far = DEPTH_RANGE_M
    depth[:] = np.linspace(far, near, height, dtype=np.float32)[:, None]
    depth += rng.normal(0.0, 0.01, (height, width)).astype(np.float32)
    return RgbdFrame(seq=seq, stamp=stamp, intrinsics=pinhole(width, height),
                     camera_pose=camera_pose(0.0, 0.0, seq * TURN_PER_FRAME_RAD), **arrays)
