"""The camera model every producer and consumer of frames agrees on.

Pinhole with square pixels; the robot's camera is level, ``CAMERA_HEIGHT_M``
above the floor, looking along the robot's heading (the paper's setup).
Camera frame: optical (x right, y down, z forward); world: REP-103.
"""

from __future__ import annotations

import math

import numpy as np

from ovamos.shared.messages import Intrinsics

CAMERA_HEIGHT_M = 0.88
HFOV_DEG = 79.0
DEPTH_RANGE_M = (0.5, 5.0)
# Optical axes expressed in REP-103 body axes (x forward, y left, z up).
OPTICAL_TO_BODY = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def pinhole(width: int, height: int, hfov_deg: float = HFOV_DEG) -> Intrinsics:
    """Square-pixel intrinsics for a camera with the given horizontal field of view."""
    f = (width / 2) / math.tan(math.radians(hfov_deg) / 2)
    return Intrinsics(fx=f, fy=f, cx=(width - 1) / 2, cy=(height - 1) / 2)


def camera_pose(x: float, y: float, yaw: float, height: float = CAMERA_HEIGHT_M) -> tuple[float, ...]:
    """world_T_camera (row-major 4x4) for a level camera at (x, y, height) looking along ``yaw``."""
    c, s = math.cos(yaw), math.sin(yaw)
    pose = np.eye(4)
    pose[:3, :3] = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ OPTICAL_TO_BODY
    pose[:3, 3] = (x, y, height)
    return tuple(float(v) for v in pose.ravel())
