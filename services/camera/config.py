"""Every setting of the robot's camera service, defined once (unknown keys are errors).

The core (:mod:`ovamos.services.camera.core`) reads :class:`CameraConfig` and nothing
else, so a camera that is mounted, timed or gated differently is a config file,
not a code change. The backends' own settings (device serial, resolution, fps,
recording path) live in their backends' modules (which import no SDK until a
backend starts) and are nested here under the backend's name.
"""

from __future__ import annotations

from typing import Literal

from pydantic import Field, model_validator

from ovamos.services.camera.file import FileConfig
from ovamos.services.camera.oakd import OakdConfig
from ovamos.services.camera.realsense import RealSenseConfig
from ovamos.services.camera.ros2 import Ros2CameraConfig
from ovamos.shared.config import ServiceConfig, StrictModel
from ovamos.shared.sessions import SessionSwitch

__all__ = ["Mount", "ClockConfig", "OdometryConfig", "CameraConfig"]


class Mount(StrictModel):
    """Where the camera sits on the robot: its body frame (REP-103: x forward, y left, z up,
    through the optical centre) in the base frame (the frame odometry poses, on the floor).

    Angles are degrees, applied as yaw about z, then pitch about y, then roll about x
    (R = Rz(yaw) Ry(pitch) Rx(roll), the REP-103 / URDF ``rpy`` convention), so a camera tilted
    down by 10 deg has ``pitch = 10`` (y points left: a positive turn about it lowers the nose).
    Measure x, y, z to the colour lens: depth is aligned to colour, so the colour camera is the
    camera whose pose the frames carry.
    The default is the simulator's camera: level, on the base's axis, 0.88 m up.
    """

    x: float = Field(default=0.0, description="metres forward of the base origin")
    y: float = Field(default=0.0, description="metres left of the base origin")
    z: float = Field(default=0.88, description="metres above the floor (the base frame's z = 0)")
    roll: float = Field(default=0.0, ge=-180, le=180, description="degrees about the camera's x (forward)")
    pitch: float = Field(default=0.0, ge=-90, le=90, description="degrees about y; positive looks down")
    yaw: float = Field(default=0.0, ge=-180, le=180, description="degrees about z; positive looks left")


class ClockConfig(StrictModel):
    """How a frame's device timestamp becomes a time on this host's monotonic clock.

    ``device``: the backend's clock is its own (a RealSense hardware clock, a recording's
    timestamps); its offset to the host is estimated from the frames themselves (see
    :class:`ovamos.services.camera.clock.DeviceClock`). ``host``: the backend already stamps frames on
    this host's monotonic clock (depthai's ``getTimestamp()`` is host-synchronised), used as is.
    """

    source: Literal["device", "host"] = "device"
    window_s: float = Field(
        default=10.0, gt=0,
        description="the offset is the least (receipt - device) time over this many seconds of "
                    "frames: long enough to hold a frame with little delay, short enough that the "
                    "two clocks' drift (~100 ppm: 1 ms in 10 s) stays below a millisecond")
    reset_s: float = Field(
        default=0.5, gt=0,
        description="a frame whose (receipt - device) time differs from the estimate by more than "
                    "this is a clock jump (device re-plugged, recording looped), not a delay")
    reset_confirm: int = Field(
        default=3, ge=1,
        description="consecutive frames that must show a later-looking jump before the estimate "
                    "restarts (one frame stuck in a USB queue is not a reset; a clock that runs "
                    "backwards or ahead restarts it at once)")
    min_latency_s: float = Field(
        default=0.0, ge=0,
        description="the least capture-to-receipt delay, if measured: the estimate treats the "
                    "fastest frame as instantaneous, so every mapped time is late by this much "
                    "unless it is given here")


class OdometryConfig(StrictModel):
    """How frames are matched with the base's odometry (``odom``, ~50 Hz, the robot host's
    wall clock)."""

    window_s: float = Field(
        default=2.0, gt=0,
        description="odometry kept, back from the newest message; a frame captured before the "
                    "oldest kept message is not published (skipped, counted)")
    tolerance_s: float = Field(
        default=0.05, ge=0,
        description="a frame captured after the newest odometry by at most this much is posed by "
                    "extrapolating the newest message's velocities; later ones are skipped")
    max_gap_s: float = Field(
        default=0.25, gt=0,
        description="two odometry messages further apart than this are not interpolated between "
                    "(the driver stalled: where the base went meanwhile is unknown); frames "
                    "captured in such a gap are skipped. Above the driver's period (20 Hz: 50 ms)")
    wait_s: float = Field(
        default=0.1, ge=0,
        description="how long (host time since receipt) a frame newer than the newest odometry "
                    "waits for a message after it before the tolerance decides")
    max_pending: int = Field(default=16, ge=1, description="frames waiting for odometry at most; "
                             "the oldest is skipped when more come")
    session_switch: SessionSwitch = Field(
        default_factory=SessionSwitch, description="when odometry of a new odometry session is "
        "followed (the driver restarted); until then it is dropped and counted as stray")


class CameraConfig(ServiceConfig):
    """The camera service: which backend, where it is mounted, how frames are timed and gated."""

    backend: Literal["realsense", "file", "oakd", "ros2"] = "realsense"
    realsense: RealSenseConfig = Field(default_factory=RealSenseConfig,
                                       description="backend realsense: which camera, size, rate, filters")
    file: FileConfig | None = Field(default=None, description="backend file: the recording to play "
                                                              "(required with backend = 'file')")
    oakd: OakdConfig = Field(default_factory=OakdConfig, description="backend oakd (refused: see oakd.py)")
    ros2: Ros2CameraConfig = Field(default_factory=Ros2CameraConfig,
                                   description="backend ros2: a camera run by ROS 2 (its topics)")
    mount: Mount = Field(default_factory=Mount)
    clock: ClockConfig = Field(default_factory=ClockConfig)
    odometry: OdometryConfig = Field(default_factory=OdometryConfig)
    lock_step: bool = Field(
        default=True,
        description="publish one frame per completed command (the first captured after the base "
                    "reported it, see settle_s); false: every frame, up to max_hz")
    settle_s: float = Field(
        default=0.0, ge=0,
        description="lock-step: a frame counts as after a completion only if captured this long "
                    "after the driver state saying so arrived (a base that rocks when it stops)")
    republish_s: float = Field(default=1.0, gt=0,
                               description="lock-step: re-publish the latest frame (same seq) this "
                                           "often while idle, for subscribers that joined late")
    max_hz: float | None = Field(default=None, gt=0,
                                 description="free-running: at most this many frames a second "
                                             "(by capture time); None = every frame")
    frame_timeout_s: float = Field(default=1.0, gt=0,
                                   description="no frame for this long is a fault")
    depth_zero_fault_s: float = Field(
        default=5.0, ge=0,
        description="depth all zero in every frame for this long is a fault (a depth stream that is off, "
                    "a covered lens); until then such frames are published, since a wall nearer than the "
                    "camera's minimum range shows no depth either; 0: every such frame is a fault")
    state_hz: float = Field(default=2.0, gt=0,
                            description="camera/state rate; a fault change goes out at once")

    @model_validator(mode="after")
    def _file_has_a_path(self) -> CameraConfig:
        if self.backend == "file" and self.file is None:
            raise ValueError("backend 'file' needs [file] path = \"run.db3\" (a RealSense recording)")
        return self
