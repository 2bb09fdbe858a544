"""A ROS 2 RGB-D camera as a backend: colour, depth aligned to colour, and the colour camera's info.

For a camera already run by ROS 2: the ``realsense2_camera`` driver (launched with
``align_depth.enable:=true``, so that ``aligned_depth_to_color`` exists) or a TurtleBot 4's OAK-D.
Colour (``rgb8`` or ``bgr8``) and depth (``16UC1`` millimetres or ``32FC1`` metres) are paired by
header stamp within ``pair_tolerance_s``; the colour camera's ``CameraInfo`` gives the
intrinsics. The colour stamp is the capture time on the device's clock (the camera core maps it
to this host's, as for a RealSense).

Subscriptions are best effort (``qos_profile_sensor_data``), which matches reliable and
best-effort publishers alike; rclpy's callbacks only keep the newest few messages under a lock.
What cannot make a frame is a :class:`~ovamos.services.camera.capture.CameraError` with the reason (an
encoding this cannot read, sizes that differ, no camera info for ``info_timeout_s`` while images
come); a colour image no depth image pairs with is dropped and counted (``unpaired``). A simulated
robot's camera also has an instance-id image (``instance_ids``), paired as depth is.
"""

from __future__ import annotations

import functools
import threading
import time
from collections import Counter, deque
from typing import Any

import numpy as np
from pydantic import Field

from ovamos.services.camera.capture import CameraError, CapturedFrame
from ovamos.shared.config import StrictModel
from ovamos.shared.messages import Intrinsics
from ovamos.shared.ros2 import NETWORK_FIELD, Network, Ros2Unavailable, node, stamp_s

__all__ = ["Ros2CameraConfig", "Ros2Backend"]

KEEP = 8  # newest messages kept per topic while waiting for their pair
DEPTH_SCALE = 0.001  # metres per unit of the depth handed on (millimetres, as a D4xx's)


class Ros2CameraConfig(StrictModel):
    """Which ROS 2 topics carry the camera (defaults: ``realsense2_camera`` with aligned depth)."""

    color: str = Field(default="/camera/camera/color/image_raw", description="sensor_msgs/Image, rgb8 or bgr8")
    depth: str = Field(default="/camera/camera/aligned_depth_to_color/image_raw",
                       description="sensor_msgs/Image aligned to colour, 16UC1 (mm) or 32FC1 (m)")
    info: str = Field(default="/camera/camera/color/camera_info", description="the colour camera's CameraInfo")
    instance_ids: str | None = Field(
        default=None, description="a simulated robot's instance-id image (32SC1, stamped as the colour), "
        "for the simulated perception backend (ovamos demo --base ros2); a real camera has none")
    pair_tolerance_s: float = Field(default=0.01, ge=0, description="colour and depth stamps this close pair")
    info_timeout_s: float = Field(default=2.0, gt=0, description="images with no CameraInfo for this long: a fault")
    network: Network = NETWORK_FIELD


def _pixels(msg: Any, dtype: np.dtype, channels: int, topic: str) -> np.ndarray:
    """The image's pixels as an H x W (x channels) array of its own (rows may be padded)."""
    if msg.is_bigendian:
        raise CameraError(f"{topic}: big-endian images are not read")
    per_row = msg.width * channels * dtype.itemsize
    if msg.step < per_row or len(msg.data) < msg.step * msg.height:
        raise CameraError(f"{topic}: {len(msg.data)} bytes do not hold {msg.height} rows of step {msg.step} "
                          f"for {msg.width} px of {msg.encoding}")
    rows = np.frombuffer(bytes(msg.data), np.uint8, msg.step * msg.height).reshape(msg.height, msg.step)
    image = rows[:, :per_row].copy().view(dtype)
    return image.reshape(msg.height, msg.width, channels) if channels > 1 else image


class Ros2Backend:
    """The :class:`~ovamos.services.camera.capture.CameraBackend` of a ROS 2 camera (module docstring)."""

    name = "ros2"

    def __init__(self, config: Ros2CameraConfig) -> None:
        self.config = config
        self._ready = threading.Condition()
        self._color: deque[tuple[Any, float]] = deque(maxlen=KEEP)  # (message, receipt monotonic)
        # the images aligned to colour, by what they hold: depth, and a simulated camera's ids
        self._aligned: dict[str, deque[Any]] = {
            kind: deque(maxlen=KEEP) for kind in ("depth", "instance_ids") if getattr(config, kind)}
        self._info: Any = None
        self._subs: list[Any] = []
        self._images_since: float | None = None  # when images came with no info yet
        self.counters: Counter[str] = Counter()

    def start(self) -> None:
        self.stop()
        try:
            ros = node(self.config.network)
        except Ros2Unavailable as exc:
            raise CameraError(str(exc)) from None
        from rclpy.qos import qos_profile_sensor_data
        from sensor_msgs.msg import CameraInfo, Image

        cfg = self.config
        self._subs = [ros.create_subscription(Image, cfg.color, self._on_color, qos_profile_sensor_data),
                      ros.create_subscription(CameraInfo, cfg.info, self._on_info, qos_profile_sensor_data)]
        self._subs += [ros.create_subscription(Image, getattr(cfg, kind), functools.partial(self._on_aligned, queue),
                                               qos_profile_sensor_data) for kind, queue in self._aligned.items()]

    def _on_color(self, msg: Any) -> None:
        with self._ready:
            self._color.append((msg, time.monotonic()))
            self._ready.notify_all()

    def _on_aligned(self, queue: deque[Any], msg: Any) -> None:
        with self._ready:
            queue.append(msg)
            self._ready.notify_all()

    def _on_info(self, msg: Any) -> None:
        with self._ready:
            self._info = msg

    def read(self, timeout_s: float) -> CapturedFrame | None:
        deadline = time.monotonic() + timeout_s
        with self._ready:
            while True:
                pair = self._take_pair()
                if pair is not None:
                    break
                left = deadline - time.monotonic()
                if left <= 0:
                    return None
                self._ready.wait(left)
            info = self._info
        if info is None:
            since = self._images_since = self._images_since or time.monotonic()
            if time.monotonic() - since > self.config.info_timeout_s:
                raise CameraError(f"no sensor_msgs/CameraInfo on {self.config.info} for "
                                  f"{self.config.info_timeout_s:.1f} s while images come")
            self.counters["waiting_for_info"] += 1
            return None
        self._images_since = None
        return self._frame(*pair, info)

    def _take_pair(self) -> tuple[Any, float, dict[str, Any]] | None:
        """The newest colour image every aligned image pairs with (older colour images are
        dropped, those that cannot be paired any more counted); under the lock."""
        tolerance = self.config.pair_tolerance_s
        while self._color:
            color, received = self._color[-1]
            t = stamp_s(color)
            nearest = {kind: min(queue, key=lambda m: abs(stamp_s(m) - t), default=None)
                       for kind, queue in self._aligned.items()}
            missing = [kind for kind, m in nearest.items() if m is None or abs(stamp_s(m) - t) > tolerance]
            if not missing:
                self.counters["unpaired"] += len(self._color) - 1
                self._color.clear()
                return color, received, nearest
            if any(not self._aligned[kind] or max(stamp_s(m) for m in self._aligned[kind]) <= t + tolerance
                   for kind in missing):
                return None  # its pair may still come
            self._color.pop()
            self.counters["unpaired"] += 1
        return None

    def _frame(self, color: Any, received: float, aligned: dict[str, Any], info: Any) -> CapturedFrame:
        cfg, depth = self.config, aligned["depth"]
        if color.encoding == "rgb8":
            rgb = _pixels(color, np.dtype(np.uint8), 3, cfg.color)
        elif color.encoding == "bgr8":
            rgb = np.ascontiguousarray(_pixels(color, np.dtype(np.uint8), 3, cfg.color)[:, :, ::-1])
        else:
            raise CameraError(f"{cfg.color}: colour encoding {color.encoding!r} is not read (rgb8 or bgr8)")
        if depth.encoding == "16UC1":
            mm = _pixels(depth, np.dtype("<u2"), 1, cfg.depth)
        elif depth.encoding == "32FC1":
            metres = _pixels(depth, np.dtype("<f4"), 1, cfg.depth)
            metres = np.where(np.isfinite(metres) & (metres > 0), metres, 0.0)  # no reading: 0
            mm = np.clip(np.rint(metres / DEPTH_SCALE), 0, np.iinfo(np.uint16).max).astype(np.uint16)
        else:
            raise CameraError(f"{cfg.depth}: depth encoding {depth.encoding!r} is not read (16UC1 or 32FC1)")
        if mm.shape != rgb.shape[:2] or (info.height, info.width) != rgb.shape[:2]:
            raise CameraError(f"sizes differ: colour {color.width}x{color.height}, depth {depth.width}x"
                              f"{depth.height}, camera info {info.width}x{info.height} (is the depth "
                              "aligned to colour? realsense2_camera: align_depth.enable:=true)")
        k = info.k
        if min(k[0], k[4]) <= 0:
            raise CameraError(f"{cfg.info}: the camera info has no focal length (K = {list(k)}): is the "
                              "camera calibrated, and is this the colour camera's info?")
        return CapturedFrame(rgb=rgb, depth=np.ascontiguousarray(mm), depth_scale=DEPTH_SCALE,
                             intrinsics=Intrinsics(fx=float(k[0]), fy=float(k[4]), cx=float(k[2]), cy=float(k[5])),
                             device_time_s=stamp_s(color), host_time_s=received,
                             instance_ids=self._instance_ids(aligned.get("instance_ids"), rgb.shape[:2]))

    def _instance_ids(self, msg: Any, shape: tuple[int, ...]) -> np.ndarray | None:
        if msg is None:
            return None
        topic = self.config.instance_ids
        if msg.encoding != "32SC1":
            raise CameraError(f"{topic}: instance-id encoding {msg.encoding!r} is not read (32SC1)")
        ids = _pixels(msg, np.dtype("<i4"), 1, str(topic))
        if ids.shape != shape:
            raise CameraError(f"sizes differ: colour {shape[1]}x{shape[0]}, instance ids {msg.width}x{msg.height}")
        return ids

    def stop(self) -> None:
        if self._subs:
            ros = node(self.config.network)
            for sub in self._subs:
                ros.destroy_subscription(sub)
        self._subs = []
        with self._ready:
            self._color.clear()
            for queue in self._aligned.values():
                queue.clear()
            self._info = None
