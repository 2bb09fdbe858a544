"""A RealSense device made of software: pyrealsense2's own ``software_device``, fed numpy frames.

The SDK's ``rs.software_device`` is a real device object: its sensors produce real
``rs.frame`` s with stream profiles, intrinsics, extrinsics and depth units, which
the SDK's syncer, ``rs.align``, depth filters and ``rs.recorder`` process exactly
as they process a D4xx's. :class:`SoftwareCamera` builds one shaped like a D4xx
(a depth sensor with z16 and a colour sensor with rgb8) and pushes given frames
through it, so the RealSense backend's real processing path runs in tests and in
the benchmark without a camera.

It is a frame source of :class:`ovamos.services.camera.realsense.RealSenseBackend` (see
:class:`ovamos.services.camera.realsense.FrameSource`): the backend starts its sensors
into an ``rs.syncer`` and reads framesets from there. A pipeline cannot open it:
in pyrealsense2 2.59.1 ``software_device.add_to(context)`` registers the device
in the context only through a weak reference to a device-info object nobody
keeps, so the context never lists it ("No device connected"). The syncer is the
same block the pipeline uses to match depth with colour; everything after it
(filters, align, conversion) is the backend's one code path for every source.

Two SDK facts shape the feeding:

- The syncer pairs frames by timestamp within half a frame interval, using the
  frame rate from the ``ACTUAL_FPS`` metadata when a frame carries it. A software
  sensor otherwise derives that from the host time between pushes, so pushes
  slower than the nominal rate (a test that renders between frames) would stop
  the pairing. Both sensors therefore report the nominal rate, as a D4xx does
  in its metadata, and timestamps default to ``frame_number / fps``.
- The syncer learns of a stream only from its first frame, so the very first
  depth and colour frames come out unpaired (the backend skips incomplete
  framesets, as a pipeline does): the first pair pushed is not delivered.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pyrealsense2 as rs

from ovamos.services.camera.capture import CameraError
from ovamos.shared.messages import Intrinsics

__all__ = ["SoftwareCamera"]

_IDENTITY_ROTATION = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]


def rs_intrinsics(intrinsics: Intrinsics, width: int, height: int) -> rs.intrinsics:
    """Pinhole intrinsics as the SDK's struct (no distortion: the simulator's camera has none)."""
    out = rs.intrinsics()
    out.width, out.height = width, height
    out.fx, out.fy = intrinsics.fx, intrinsics.fy
    out.ppx, out.ppy = intrinsics.cx, intrinsics.cy
    out.model = rs.distortion.none
    out.coeffs = [0.0] * 5
    return out


class SoftwareCamera:
    """An ``rs.software_device`` with a depth (z16) and a colour (rgb8) sensor of one size.

    ``intrinsics`` are the colour camera's; ``depth_intrinsics`` default to the same
    and ``depth_to_color`` (rotation row-major 3x3, translation in metres) to the
    identity: a simulated RGB-D camera has one optical centre, so the SDK's
    alignment must then leave depth where it is. ``depth_scale`` is the depth
    sensor's ``depth_units`` option, the value the backend reads as a D4xx's.
    """

    def __init__(self, width: int, height: int, intrinsics: Intrinsics, *,
                 depth_intrinsics: Intrinsics | None = None,
                 depth_to_color: tuple[list[float], list[float]] | None = None,
                 depth_scale: float = 0.001, fps: int = 30,
                 serial: str = "SOFTWARE-0001", queue_size: int = 8) -> None:
        if width <= 0 or height <= 0 or fps <= 0:
            raise ValueError(f"bad stream shape {width}x{height} @ {fps} fps")
        self.width, self.height, self.fps = width, height, fps
        self.depth_scale, self.serial = depth_scale, serial
        self._queue_size = queue_size
        self.device = rs.software_device()
        self.device.register_info(rs.camera_info.name, "OVAMOS software RGB-D camera")
        self.device.register_info(rs.camera_info.serial_number, serial)
        self.depth_sensor = self.device.add_sensor("Stereo Module")
        self.color_sensor = self.device.add_sensor("RGB Camera")
        self.depth_sensor.add_read_only_option(rs.option.depth_units, depth_scale)
        self.depth_profile = self._add_stream(self.depth_sensor, rs.stream.depth, rs.format.z16, 2,
                                              depth_intrinsics or intrinsics, uid=1)
        self.color_profile = self._add_stream(self.color_sensor, rs.stream.color, rs.format.rgb8, 3,
                                              intrinsics, uid=2)
        extrinsics = rs.extrinsics()
        rotation, translation = depth_to_color or (_IDENTITY_ROTATION, [0.0, 0.0, 0.0])
        extrinsics.rotation, extrinsics.translation = list(rotation), list(translation)
        self.depth_profile.register_extrinsics_to(self.color_profile, extrinsics)
        for sensor in (self.depth_sensor, self.color_sensor):
            # See the module docstring: the syncer's pairing uses this rate.
            sensor.set_metadata(rs.frame_metadata_value.actual_fps, fps * 1000)
        self._syncer: rs.syncer | None = None
        self._recorder: rs.recorder | None = None
        self._next_frame = 0
        self._streaming = False

    def _add_stream(self, sensor: rs.software_sensor, stream: rs.stream, fmt: rs.format, bpp: int,
                    intrinsics: Intrinsics, uid: int) -> rs.video_stream_profile:
        vs = rs.video_stream()
        vs.type, vs.index, vs.uid = stream, 0, uid
        vs.width, vs.height, vs.fps, vs.bpp, vs.fmt = self.width, self.height, self.fps, bpp, fmt
        vs.intrinsics = rs_intrinsics(intrinsics, self.width, self.height)
        return sensor.add_video_stream(vs).as_video_stream_profile()

    # -- FrameSource (what RealSenseBackend reads) -------------------------------------------

    def describe(self) -> str:
        return f"software device {self.serial}"

    def open(self) -> float:
        """Start both sensors into a fresh syncer; return the depth sensor's depth scale.

        Called again after :meth:`close`, it starts streaming anew (recovery paths)."""
        self.close()
        self._syncer = rs.syncer(self._queue_size)
        self.depth_sensor.open(self.depth_profile)
        self.color_sensor.open(self.color_profile)
        self.depth_sensor.start(self._syncer)
        self.color_sensor.start(self._syncer)
        self._streaming = True
        return float(self.device.first_depth_sensor().get_depth_scale())

    def wait(self, timeout_ms: int) -> rs.composite_frame | None:
        """The next frameset from the syncer, or None when none came within ``timeout_ms``."""
        if self._syncer is None:
            raise CameraError(f"{self.describe()} is not streaming")
        ok, frames = self._syncer.try_wait_for_frames(max(0, int(timeout_ms)))
        return frames if ok else None

    def check(self) -> None:
        """A software device cannot be unplugged: a silence is only a silence."""

    def close(self) -> None:
        """Stop and close both sensors (idempotent)."""
        if not self._streaming:
            return
        self._streaming = False
        for sensor in (self.depth_sensor, self.color_sensor):
            try:
                sensor.stop()
            finally:
                sensor.close()
        self._syncer = None

    # -- feeding --------------------------------------------------------------------------

    def push(self, rgb: np.ndarray, depth: np.ndarray, *, timestamp_ms: float | None = None,
             frame_number: int | None = None) -> int:
        """Deliver one colour + depth pair captured together; return its frame number.

        ``rgb`` is HxWx3 uint8, ``depth`` HxW uint16 in units of ``depth_scale``.
        The timestamp (device clock, milliseconds, hardware-clock domain) defaults to
        ``frame_number * 1000 / fps``: a device running exactly at its nominal rate.
        Frames pushed while the sensors are not streaming are dropped by the SDK,
        as a stopped camera's would be.
        """
        if rgb.shape != (self.height, self.width, 3) or rgb.dtype != np.uint8:
            raise ValueError(f"rgb must be {self.height}x{self.width}x3 uint8, "
                             f"got {rgb.shape} {rgb.dtype}")
        if depth.shape != (self.height, self.width) or depth.dtype != np.uint16:
            raise ValueError(f"depth must be {self.height}x{self.width} uint16, "
                             f"got {depth.shape} {depth.dtype}")
        number = self._next_frame if frame_number is None else frame_number
        self._next_frame = number + 1
        stamp = number * 1000.0 / self.fps if timestamp_ms is None else timestamp_ms
        self._send(self.depth_sensor, self.depth_profile, depth, 2, stamp, number)
        self._send(self.color_sensor, self.color_profile, rgb, 3, stamp, number)
        return number

    def _send(self, sensor: rs.software_sensor, profile: rs.video_stream_profile,
              pixels: np.ndarray, bpp: int, stamp: float, number: int) -> None:
        # A fresh frame struct per call: its pixels setter copies the array into a buffer the SDK
        # frees when the frame is released, and setting pixels twice on one struct would free
        # that buffer a second time.
        frame: Any = rs.software_video_frame()
        frame.pixels = np.ascontiguousarray(pixels)
        frame.stride, frame.bpp = self.width * bpp, bpp
        frame.timestamp, frame.domain = stamp, rs.timestamp_domain.hardware_clock
        frame.frame_number, frame.profile = number, profile
        if profile.stream_type() == rs.stream.depth:
            frame.depth_units = self.depth_scale
        sensor.on_video_frame(frame)

    # -- recording -------------------------------------------------------------------------

    def start_recording(self, path: str | Path) -> None:
        """Record everything the sensors deliver from now on to ``path`` with ``rs.recorder``.

        Call it before :meth:`open` (the recorder hooks the sensors as they start). The
        SDK writes ROS2 rosbag (``.db3``) files and refuses any other name; the file is
        complete after :meth:`stop_recording`.
        """
        if self._streaming:
            raise CameraError("start_recording() must come before the sensors start streaming")
        if Path(path).suffix != ".db3":
            raise CameraError(f"rs.recorder writes .db3 (rosbag2) files only, not {path}")
        try:
            self._recorder = rs.recorder(str(path), self.device)
        except RuntimeError as exc:
            raise CameraError(f"cannot record to {path}: {exc}") from None

    def stop_recording(self) -> None:
        """Stop streaming and close the recording (the SDK writes it out when the recorder goes)."""
        self.close()
        if self._recorder is not None:
            self._recorder.pause()
            self._recorder = None
