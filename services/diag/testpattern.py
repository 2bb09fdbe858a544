"""A synthetic RGB-D camera: a known, seeded frame stream for checking a deployment.

Like a video test card, it lets a user see that frames reach every consumer
intact and on time before a real camera or the simulator is attached. The
camera turns in place at the paper's camera height, so downstream code gets
plausible poses as well as pixels.
"""

from __future__ import annotations

import math

import numpy as np

from shared.messages import Intrinsics, RgbdFrame

CAMERA_HEIGHT_M = 0.88
HFOV_DEG = 79.0
DEPTH_RANGE_M = (0.5, 5.0)
TURN_PER_FRAME_RAD = math.radians(5.0)
# Optical frame (x right, y down, z forward) expressed in REP-103 axes (x fwd, y left, z up).
_OPTICAL_TO_BODY = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
_BARS = np.array([[255, 255, 255], [255, 255, 0], [0, 255, 255], [0, 255, 0],
                  [255, 0, 255], [255, 0, 0], [0, 0, 255], [0, 0, 0]], dtype=np.uint8)


def pinhole(width: int, height: int, hfov_deg: float = HFOV_DEG) -> Intrinsics:
    """Square-pixel intrinsics for a camera with the given horizontal field of view."""
    f = (width / 2) / math.tan(math.radians(hfov_deg) / 2)
    return Intrinsics(fx=f, fy=f, cx=(width - 1) / 2, cy=(height - 1) / 2)


def camera_pose(yaw: float, height: float = CAMERA_HEIGHT_M) -> tuple[float, ...]:
    """world_T_camera for a level camera at ``height`` looking along ``yaw``."""
    c, s = math.cos(yaw), math.sin(yaw)
    pose = np.eye(4)
    pose[:3, :3] = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ _OPTICAL_TO_BODY
    pose[2, 3] = height
    return tuple(float(x) for x in pose.ravel())


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
                     camera_pose=camera_pose(seq * TURN_PER_FRAME_RAD), **arrays)
