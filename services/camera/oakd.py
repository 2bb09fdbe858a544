"""The OAK-D backend entry: configured like the others, refused with a clear error.

Not implemented on purpose. Every backend here is tested through its real SDK
without hardware (the RealSense one through pyrealsense2's own software device
and recordings). depthai (3.x) has no such device: its ``StereoDepth`` node, and
the alignment of depth to the RGB camera, run on the camera's vision processor
(RVC2/RVC4), and even its host-fed examples ("stereo depth from host",
``ReplayVideo``) send the frames to a connected device to compute depth. Code for
it could not be run here, so none is shipped: ``backend: oakd`` fails at start
with that reason rather than with an untested pipeline.
"""

from __future__ import annotations

from pydantic import Field

from ovamos.services.camera.capture import CameraError, CapturedFrame
from ovamos.shared.config import StrictModel

__all__ = ["OakdConfig", "OakdBackend", "NOT_IMPLEMENTED"]

NOT_IMPLEMENTED = (
    "the oakd backend is not implemented: depthai has no hardware-free device to test it "
    "against (its StereoDepth and depth-to-RGB alignment run only on an OAK camera's "
    "processor); use backend 'realsense', or 'file' with a RealSense recording")


class OakdConfig(StrictModel):
    """A Luxonis OAK-D (``backend: oakd``): accepted so configs can name it; the backend refuses."""

    device_id: str | None = Field(default=None, description="device id (MxId); None = the first")
    width: int = Field(default=640, gt=0)
    height: int = Field(default=480, gt=0)
    fps: int = Field(default=30, gt=0)


class OakdBackend:
    """Raises :class:`CameraError` (see the module docstring) whenever it is asked for frames."""

    name = "oakd"

    def __init__(self, config: OakdConfig | None = None) -> None:
        self.config = config or OakdConfig()

    def start(self) -> None:
        raise CameraError(NOT_IMPLEMENTED)

    def read(self, timeout_s: float) -> CapturedFrame | None:
        raise CameraError(NOT_IMPLEMENTED)

    def stop(self) -> None:
        """Nothing was started."""
