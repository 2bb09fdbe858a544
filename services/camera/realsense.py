"""The RealSense backend: frames from pyrealsense2, depth aligned to colour, as CapturedFrames.

One processing path serves every source of RealSense framesets, so what the tests
and the benchmark exercise (a :class:`~ovamos.services.camera.software_device.SoftwareCamera`,
a recording) is the code a robot runs on a D4xx:

    frameset -> depth filters (optional, off by default) -> rs.align(colour)
             -> colour HxWx3 uint8 + depth HxW uint16 (copied, never converted to float)
             -> colour intrinsics, the depth sensor's depth scale, the colour frame's
                device timestamp (ms -> s), the host's monotonic receipt time.

Sources (:class:`FrameSource`): :class:`DeviceSource` (a camera through
``rs.pipeline`` + ``rs.config``, by serial number), the file backend's
:class:`ovamos.services.camera.file.FileSource` (a recording), and the software device.
A source only starts, waits for the next frameset, says whether a silence means
the device is gone, and stops.

pyrealsense2 is imported when a backend starts, not with this module: the configs
here are read by ``ovamos`` and the camera core on machines without the SDK, and
a missing SDK (or its libusb) is then the backend's CameraError, a fault the
service reports, rather than an ImportError.
"""

from __future__ import annotations

import time
from types import ModuleType
from typing import TYPE_CHECKING, Protocol

import numpy as np
from pydantic import Field

from ovamos.services.camera.capture import CameraError, CapturedFrame
from ovamos.shared.config import StrictModel
from ovamos.shared.messages import Intrinsics

if TYPE_CHECKING:
    import pyrealsense2 as rs

__all__ = ["DepthFilters", "RealSenseConfig", "FrameSource", "DeviceSource", "RealSenseBackend",
           "connected_serials", "sdk"]


def sdk() -> ModuleType:
    """pyrealsense2, or a CameraError that says how to install it."""
    try:
        import pyrealsense2
    except ImportError as exc:
        raise CameraError(f"pyrealsense2 is not usable ({exc}): install it with "
                          "pip install 'ovamos[camera]' (make does), and Debian's libusb-1.0-0"
                          ) from None
    return pyrealsense2


class DepthFilters(StrictModel):
    """The SDK's host-side depth post-processing, applied before alignment (all off by default:
    they smooth and fill depth, which a map may or may not want; each costs CPU per frame)."""

    spatial: bool = Field(default=False, description="edge-preserving spatial smoothing")
    temporal: bool = Field(default=False, description="smoothing over the last frames (keeps "
                                                       "state: a moving camera smears)")
    hole_filling: bool = Field(default=False, description="fill missing depth from neighbours")


class RealSenseConfig(DepthFilters):
    """A RealSense D4xx camera (``backend: realsense``)."""

    serial: str | None = Field(default=None, description="serial number; None = the first "
                                                         "device found")
    width: int = Field(default=640, gt=0, description="colour and depth width, pixels")
    height: int = Field(default=480, gt=0, description="colour and depth height, pixels")
    fps: int = Field(default=30, gt=0, description="frames per second of both streams")
    warmup_frames: int = Field(default=15, ge=0, description="frames dropped after each start "
                                                             "while auto-exposure settles")


class FrameSource(Protocol):
    """Where framesets come from (a device, a recording, a software device)."""

    def describe(self) -> str:
        """For error messages: which device or file this is."""
        ...

    def open(self) -> float:
        """Start streaming; return the depth scale (metres per depth unit). Raises CameraError."""
        ...

    def wait(self, timeout_ms: int) -> rs.composite_frame | None:
        """The next frameset, or None when none came within ``timeout_ms``."""
        ...

    def check(self) -> None:
        """After a silence: raise CameraError if the source is gone (unplugged, recording over)."""
        ...

    def close(self) -> None:
        """Stop streaming (idempotent)."""
        ...


def connected_serials(ctx: rs.context) -> list[str]:
    """Serial numbers of the RealSense devices this host sees now."""
    rs = sdk()
    return [dev.get_info(rs.camera_info.serial_number) for dev in ctx.query_devices()]


def _runtime_reason(exc: BaseException) -> str:
    return str(exc).strip() or type(exc).__name__


class DeviceSource:
    """A camera on this host, through ``rs.pipeline`` with rgb8 colour and z16 depth."""

    def __init__(self, config: RealSenseConfig) -> None:
        self._config = config
        self._ctx: rs.context | None = None
        self._pipeline: rs.pipeline | None = None
        self._serial: str | None = config.serial

    def describe(self) -> str:
        return f"RealSense {self._serial}" if self._serial else "RealSense (first device)"

    def open(self) -> float:
        self.close()
        rs, c = sdk(), self._config
        if self._ctx is None:
            self._ctx = rs.context()
        serials = connected_serials(self._ctx)
        if not serials:
            wanted = f" (wanted serial {c.serial!r})" if c.serial is not None else ""
            raise CameraError(f"no RealSense device connected{wanted}: is it plugged in, on a "
                              "USB 3 port, and readable (udev rules installed)?")
        if c.serial is not None and c.serial not in serials:
            raise CameraError(f"no RealSense device with serial {c.serial!r}; connected: "
                              f"{', '.join(serials)}")
        self._serial = c.serial or serials[0]
        config = rs.config()
        config.enable_device(self._serial)
        config.enable_stream(rs.stream.color, c.width, c.height, rs.format.rgb8, c.fps)
        config.enable_stream(rs.stream.depth, c.width, c.height, rs.format.z16, c.fps)
        pipeline = rs.pipeline(self._ctx)
        try:
            profile = pipeline.start(config)
        except RuntimeError as exc:
            raise CameraError(f"cannot start {self.describe()} at {c.width}x{c.height} @ {c.fps} "
                              f"fps: {_runtime_reason(exc)}") from None
        self._pipeline = pipeline
        return float(profile.get_device().first_depth_sensor().get_depth_scale())

    def wait(self, timeout_ms: int) -> rs.composite_frame | None:
        if self._pipeline is None:
            raise CameraError(f"{self.describe()} is not streaming")
        try:
            ok, frames = self._pipeline.try_wait_for_frames(max(0, int(timeout_ms)))
        except RuntimeError as exc:
            raise CameraError(f"{self.describe()} failed: {_runtime_reason(exc)}") from None
        return frames if ok else None

    def check(self) -> None:
        if self._ctx is None or self._serial not in connected_serials(self._ctx):
            raise CameraError(f"{self.describe()} is gone (unplugged?)")

    def close(self) -> None:
        pipeline, self._pipeline = self._pipeline, None
        if pipeline is not None:
            try:
                pipeline.stop()
            except RuntimeError:
                pass  # already stopped by the SDK (device lost): nothing left to release


def _rgb(frame: rs.video_frame) -> np.ndarray:
    """The colour frame as an HxWx3 RGB uint8 copy (recordings may hold BGR or 4-channel)."""
    rs = sdk()
    fmt = frame.profile.format()
    data = np.asanyarray(frame.get_data())
    if fmt == rs.format.rgb8:
        return data.copy()
    if fmt == rs.format.bgr8:
        return np.ascontiguousarray(data[..., ::-1])
    if fmt == rs.format.rgba8:
        return np.ascontiguousarray(data[..., :3])
    if fmt == rs.format.bgra8:
        return np.ascontiguousarray(data[..., 2::-1])
    raise CameraError(f"colour format {fmt} is not supported (rgb8, bgr8, rgba8, bgra8 are)")


class RealSenseBackend:
    """A :class:`~ovamos.services.camera.capture.CameraBackend` over RealSense framesets.

    Without ``source`` it opens the camera the config names; with one (a
    :class:`~ovamos.services.camera.software_device.SoftwareCamera`, a recording) it reads
    that instead, through the same filters, alignment and conversion.
    """

    name = "realsense"

    def __init__(self, config: DepthFilters | None = None, *,
                 source: FrameSource | None = None) -> None:
        # Any source's config carries the depth filters; only a camera's has warm-up frames.
        self.config = config if config is not None else RealSenseConfig()
        if source is None:
            if not isinstance(self.config, RealSenseConfig):
                raise TypeError("a RealSense camera needs a RealSenseConfig")
            source = DeviceSource(self.config)
        self.source: FrameSource = source
        self._align: rs.align | None = None
        self._filters: list[rs.filter] = []
        self._depth_scale = 0.0
        self._to_skip = 0
        self._started = False
        self._intrinsics: tuple[int, Intrinsics] | None = None
        self.skipped_incomplete = 0  # framesets without both depth and colour (syncer start-up)
        self.skipped_unpaired = 0  # framesets whose depth and colour are from different moments
        self.skipped_repeated = 0  # framesets whose colour frame was already delivered
        self._last: tuple[int, float] | None = None  # colour (number, timestamp) delivered last
        self.timing_ms = {"wait": 0.0, "align": 0.0}  # of the last frame read

    def _make_filters(self) -> list[rs.filter]:
        # The SDK's recommended order; spatial and temporal work best on disparity, as there.
        rs, c, out = sdk(), self.config, []
        if c.spatial or c.temporal:
            out.append(rs.disparity_transform(True))
            if c.spatial:
                out.append(rs.spatial_filter())
            if c.temporal:
                out.append(rs.temporal_filter())
            out.append(rs.disparity_transform(False))
        if c.hole_filling:
            out.append(rs.hole_filling_filter())
        return out

    def start(self) -> None:
        """Open the source (again, after a failure or a stop). Raises CameraError."""
        self.stop()
        rs = sdk()
        self._align = rs.align(rs.stream.color)
        self._depth_scale = self.source.open()
        if not self._depth_scale > 0:
            self.source.close()
            raise CameraError(f"{self.source.describe()} reports depth scale {self._depth_scale}")
        self._filters = self._make_filters()  # fresh: the temporal filter's history is per stream
        self._to_skip = self.config.warmup_frames if isinstance(self.config, RealSenseConfig) else 0
        self._intrinsics = None
        self._last = None
        self._started = True

    def read(self, timeout_s: float) -> CapturedFrame | None:
        """The next aligned frame, or None when none came within ``timeout_s``.

        Raises CameraError when the source is gone (device unplugged, end of recording).
        """
        if not self._started:
            raise CameraError(f"{self.name}: read() before start()")
        deadline = time.monotonic() + timeout_s
        while True:
            t0 = time.perf_counter()
            frames = self.source.wait(int(max(0.0, deadline - time.monotonic()) * 1000))
            if frames is None:
                self.source.check()
                return None
            received = time.monotonic()
            t1 = time.perf_counter()
            depth, color = frames.get_depth_frame(), frames.get_color_frame()
            if not depth or not color:
                self.skipped_incomplete += 1
            elif not self._paired(depth, color):
                self.skipped_unpaired += 1
            elif (color.get_frame_number(), color.get_timestamp()) == self._last:
                self.skipped_repeated += 1  # re-sent by a pipeline when only one side is new
            elif self._to_skip > 0:
                self._to_skip -= 1
                self._last = (color.get_frame_number(), color.get_timestamp())
            else:
                break
            if time.monotonic() >= deadline:
                return None
        self._last = (color.get_frame_number(), color.get_timestamp())
        frame = self._convert(frames, received)
        self.timing_ms = {"wait": (t1 - t0) * 1e3, "align": (time.perf_counter() - t1) * 1e3}
        return frame

    @staticmethod
    def _paired(depth: rs.frame, color: rs.frame) -> bool:
        """Whether depth and colour were captured together: the SDK syncer's own test, timestamps
        less than half a frame apart. A pipeline that could not pair them (frames dropped under
        load, a recording played in a burst) fills a frameset with the last frame of the other
        stream, and depth from another moment must not be posed with this colour."""
        fps = color.profile.fps() or depth.profile.fps()
        return fps <= 0 or abs(depth.get_timestamp() - color.get_timestamp()) < 500.0 / fps

    def _convert(self, frames: rs.composite_frame, received: float) -> CapturedFrame:
        assert self._align is not None  # set by start()
        for block in self._filters:
            frames = block.process(frames).as_frameset()
        aligned = self._align.process(frames)
        color, depth = aligned.get_color_frame(), aligned.get_depth_frame()
        if not color or not depth:
            raise CameraError(f"{self.source.describe()}: alignment lost a stream")
        return CapturedFrame(
            rgb=_rgb(color),
            depth=np.asanyarray(depth.get_data()).copy(),
            depth_scale=self._depth_scale,
            intrinsics=self._color_intrinsics(color),
            device_time_s=color.get_timestamp() / 1000.0,
            host_time_s=received,
        )

    def _color_intrinsics(self, color: rs.video_frame) -> Intrinsics:
        profile = color.profile.as_video_stream_profile()
        uid = profile.unique_id()
        if self._intrinsics is None or self._intrinsics[0] != uid:
            i = profile.get_intrinsics()
            # Frames carry pinhole intrinsics: the distortion model and coefficients are not
            # passed on (a D4xx's colour stream reports zero or small ones).
            self._intrinsics = (uid, Intrinsics(fx=i.fx, fy=i.fy, cx=i.ppx, cy=i.ppy))
        return self._intrinsics[1]

    @property
    def depth_scale(self) -> float:
        """Metres per depth unit, from the depth sensor (0 before start)."""
        return self._depth_scale

    def stop(self) -> None:
        """Stop streaming (idempotent); start() may follow."""
        self._started = False
        self.source.close()
