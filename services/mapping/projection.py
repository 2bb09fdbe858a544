"""From an RGB-D frame to world points and the floor area the camera saw."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from shared.messages import RgbdFrame


@dataclass(frozen=True)
class View:
    """What one frame tells the map: 3-D points, and the seen area as a polygon.

    ``polygon`` starts at the camera and follows, column by column, the
    farthest horizontal distance at which that column saw something.
    """

    points: np.ndarray   # N x 3 world points with a valid depth
    camera: tuple[float, float]
    heading: float       # yaw of the optical axis in the world
    hfov: float
    polygon: np.ndarray  # M x 2 world xy


def project(frame: RgbdFrame, stride: int, depth_min: float, depth_max: float) -> View:
    k = frame.intrinsics
    depth = frame.depth[::stride, ::stride].astype(np.float32)
    if frame.depth_scale != 1.0:
        depth *= np.float32(frame.depth_scale)
    rows, cols = depth.shape
    u = np.arange(cols, dtype=np.float32) * stride
    v = np.arange(rows, dtype=np.float32) * stride
    valid = (depth >= depth_min) & (depth <= depth_max)
    x_cam = (u[None, :] - k.cx) / k.fx * depth
    y_cam = (v[:, None] - k.cy) / k.fy * depth
    pose = frame.pose_matrix
    r, t = pose[:3, :3].astype(np.float32), pose[:3, 3].astype(np.float32)
    world = (np.stack([x_cam, y_cam, depth], -1) @ r.T) + t  # rows x cols x 3
    cam_x, cam_y = float(t[0]), float(t[1])
    forward, right = pose[:3, 2], pose[:3, 0]
    heading = math.atan2(forward[1], forward[0])
    hfov = 2 * math.atan(frame.depth.shape[1] / (2 * k.fx))

    horizontal = np.hypot(world[..., 0] - cam_x, world[..., 1] - cam_y)
    reach = np.where(valid, horizontal, 0.0).max(axis=0)  # per column; 0 = saw nothing
    # direction of each column's rays projected on the floor
    dirs = forward[None, :2] + right[None, :2] * ((u - k.cx) / k.fx)[:, None]
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    edge = np.array([cam_x, cam_y]) + dirs * reach[:, None]
    polygon = np.vstack([[cam_x, cam_y], edge])
    return View(world[valid], (cam_x, cam_y), heading, hfov, polygon)
