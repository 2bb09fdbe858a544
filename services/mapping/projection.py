"""From an RGB-D frame to world points and the floor area the camera saw."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ovamos.shared.messages import RgbdFrame
from ovamos.shared.motion import Pose


@dataclass(frozen=True)
class View:
    """What one frame tells the map: obstacle points, and the seen area as a polygon.

    ``polygon`` starts at the camera and follows, column by column, the
    farthest horizontal distance at which that column saw something.
    """

    obstacles: np.ndarray  # N x 2 world xy of points within the obstacle height band
    camera: tuple[float, float]
    heading: float         # yaw of the optical axis in the world
    hfov: float
    polygon: np.ndarray    # M x 2 world xy

    def moved(self, transform: Pose) -> View:
        """The same view seen from ``transform`` * its pose (a localization's correction)."""
        return View(transform.apply_points(self.obstacles), transform.apply(*self.camera),
                    self.heading + transform.yaw, self.hfov, transform.apply_points(self.polygon))


def planar_pose(frame: RgbdFrame) -> Pose:
    """Where ``frame``'s camera stands on the floor and the heading of its optical axis."""
    pose = frame.pose_matrix
    return Pose(x=float(pose[0, 3]), y=float(pose[1, 3]), yaw=math.atan2(pose[1, 2], pose[0, 2]))


def placed(frame: RgbdFrame, transform: Pose) -> RgbdFrame:
    """``frame`` with its camera pose moved by the planar ``transform`` (map_T_odom, a correction)."""
    if transform.identity:
        return frame
    c, s = math.cos(transform.yaw), math.sin(transform.yaw)
    planar = np.array([[c, -s, 0.0, transform.x], [s, c, 0.0, transform.y], [0.0, 0.0, 1.0, 0.0],
                       [0.0, 0.0, 0.0, 1.0]])
    return frame.model_copy(update={"camera_pose": tuple(float(v) for v in (planar @ frame.pose_matrix).ravel())})


def project(frame: RgbdFrame, stride: int, depth_range: tuple[float, float],
            obstacle_band: tuple[float, float]) -> View:
    k = frame.intrinsics
    depth = frame.depth[::stride, ::stride].astype(np.float32)
    if frame.depth_scale != 1.0:
        depth *= np.float32(frame.depth_scale)
    rows, cols = depth.shape
    u = np.arange(cols, dtype=np.float32) * stride
    v = np.arange(rows, dtype=np.float32) * stride
    valid = (depth >= depth_range[0]) & (depth <= depth_range[1])
    x_cam = ((u - k.cx) / k.fx)[None, :] * depth
    y_cam = ((v - k.cy) / k.fy)[:, None] * depth
    pose = frame.pose_matrix
    r, t = pose[:3, :3].astype(np.float32), pose[:3, 3].astype(np.float32)
    # world = R @ p + t, one coordinate at a time (no N x 3 temporaries)
    wx = r[0, 0] * x_cam + r[0, 1] * y_cam + r[0, 2] * depth + t[0]
    wy = r[1, 0] * x_cam + r[1, 1] * y_cam + r[1, 2] * depth + t[1]
    wz = r[2, 0] * x_cam + r[2, 1] * y_cam + r[2, 2] * depth + t[2]
    band = valid & (wz >= obstacle_band[0]) & (wz <= obstacle_band[1])
    obstacles = np.stack([wx[band], wy[band]], axis=1)

    cam_x, cam_y = float(t[0]), float(t[1])
    forward, right = pose[:3, 2], pose[:3, 0]
    heading = math.atan2(forward[1], forward[0])
    hfov = 2 * math.atan(frame.depth.shape[1] / (2 * k.fx))
    horizontal = np.hypot(wx - cam_x, wy - cam_y)
    reach = np.where(valid, horizontal, 0.0).max(axis=0)  # per column; 0 = saw nothing
    # direction of each column's rays projected on the floor
    dirs = forward[None, :2] + right[None, :2] * ((u - k.cx) / k.fx)[:, None]
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    edge = np.array([cam_x, cam_y]) + dirs * reach[:, None]
    polygon = np.vstack([[cam_x, cam_y], edge])
    return View(obstacles, (cam_x, cam_y), heading, hfov, polygon)
