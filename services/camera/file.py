"""The file backend: a RealSense recording played back as if it were the camera.

A recorded run can be searched again: the recording is opened with
``rs.config.enable_device_from_file`` and goes through ``rs.pipeline`` and then
the RealSense backend's own filters, alignment and conversion, with the
intrinsics and depth units stored in the file. pyrealsense2 2.59 records rosbag2
``.db3`` files (``rs.recorder`` refuses other names); its playback still opens an
older ROS1 ``.bag`` with its ROS1 reader (a malformed one fails there with "Error
reading version line"), but no real ``.bag`` was at hand to test that path.

``rate``: ``realtime`` plays at the pace the frames were recorded at (the host
times in the file): like the camera, it drops frames a slow consumer misses, and
the SDK's real-time playback loses its first frame or two in about one start out
of ten. ``max`` turns real time off (``playback.set_real_time(False)``), so the
playback waits for each frame to be consumed: every frame, as fast as the core
takes them (what a replayed search wants). The backend then says it is
``lossless``, and the camera service's reader waits for the service instead of
dropping captures while it is busy (:mod:`ovamos.services.camera.service`).

pyrealsense2 is imported when the backend starts (see :mod:`ovamos.services.camera.realsense`).

The end of the recording is not a silence: ``read`` raises :class:`RecordingEnded`
(a :class:`~ovamos.services.camera.capture.CameraError`, message ``"end of recording:
<path>"``) and :attr:`FileBackend.ended` turns true. ``start()`` plays it again
from the beginning.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import TYPE_CHECKING, Literal

from pydantic import Field

from ovamos.services.camera.capture import CameraError
from ovamos.services.camera.realsense import DepthFilters, RealSenseBackend, sdk

if TYPE_CHECKING:
    import pyrealsense2 as rs

__all__ = ["FileConfig", "FileSource", "FileBackend", "RecordingEnded", "RECORDING_SUFFIXES"]

RECORDING_SUFFIXES = (".db3", ".bag")
_POLL_MS = 50  # how often a wait looks whether the playback has stopped


class RecordingEnded(CameraError):
    """The recording has no more frames (not a fault of the camera: the run is over)."""


class FileConfig(DepthFilters):
    """A RealSense recording (``backend: file``)."""

    path: Path = Field(description="a .db3 (rosbag2) or .bag (ROS1) RealSense recording")
    rate: Literal["realtime", "max"] = Field(
        default="realtime",
        description="realtime: at the recorded rate; max: every frame, as fast as consumed")


class FileSource:
    """A recording through ``rs.pipeline`` (see the module docstring)."""

    def __init__(self, config: FileConfig) -> None:
        self._config = config
        self._pipeline: rs.pipeline | None = None
        self._playback: rs.playback | None = None
        self.ended = False

    def describe(self) -> str:
        return f"recording {self._config.path}"

    def open(self) -> float:
        self.close()
        self.ended = False
        path = self._config.path
        if not path.is_file():
            raise CameraError(f"recording not found: {path}")
        if path.suffix not in RECORDING_SUFFIXES:
            raise CameraError(f"{path} is not a RealSense recording (expected "
                              f"{' or '.join(RECORDING_SUFFIXES)})")
        rs = sdk()
        config = rs.config()
        pipeline = rs.pipeline()
        try:
            config.enable_device_from_file(str(path), repeat_playback=False)
            config.enable_stream(rs.stream.color)
            config.enable_stream(rs.stream.depth)
            # Real time is set before start, so no frame plays at the wrong rate (set after
            # start, the first frames of a "max" playback race ahead and are lost).
            playback = config.resolve(rs.pipeline_wrapper(pipeline)).get_device().as_playback()
            playback.set_real_time(self._config.rate == "realtime")
            # The pipeline starts the playback's sensors one after the other, and a frame read
            # before its stream's sensor has started is lost (seen for frame 0 on a loaded
            # machine): the playback waits, paused, until every stream is started.
            playback.pause()
            profile = pipeline.start(config)
            playback.resume()
        except RuntimeError as exc:
            raise CameraError(f"cannot read recording {path} (it needs a colour and a depth "
                              f"stream): {str(exc).strip()}") from None
        self._pipeline = pipeline
        device = profile.get_device()
        self._playback = device.as_playback()
        return float(device.first_depth_sensor().get_depth_scale())

    def wait(self, timeout_ms: int) -> rs.composite_frame | None:
        if self._pipeline is None or self._playback is None:
            raise CameraError(f"{self.describe()} is not playing")
        deadline = time.monotonic() + timeout_ms / 1000
        while True:
            remaining = int((deadline - time.monotonic()) * 1000)
            ok, frames = self._pipeline.try_wait_for_frames(max(0, min(_POLL_MS, remaining)))
            if ok:
                return frames
            if self._playback.current_status() == sdk().playback_status.stopped:
                ok, frames = self._pipeline.try_wait_for_frames(0)  # a last one queued meanwhile
                if ok:
                    return frames
                self.ended = True
                raise RecordingEnded(f"end of recording: {self._config.path}")
            if remaining <= 0:
                return None

    def check(self) -> None:
        if self.ended:
            raise RecordingEnded(f"end of recording: {self._config.path}")

    def close(self) -> None:
        pipeline, self._pipeline, self._playback = self._pipeline, None, None
        if pipeline is not None:
            try:
                pipeline.stop()
            except RuntimeError:
                pass  # the playback already stopped it


class FileBackend(RealSenseBackend):
    """Plays a RealSense recording through the RealSense backend's processing path."""

    name = "file"

    def __init__(self, config: FileConfig) -> None:
        self.file_source = FileSource(config)
        super().__init__(config, source=self.file_source)
        # every frame, at the consumer's pace: the service waits instead of dropping
        self.lossless = config.rate == "max"

    @property
    def ended(self) -> bool:
        """True once the recording has played to its end (until the next start())."""
        return self.file_source.ended
