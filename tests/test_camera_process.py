"""`ovamos run camera` over real Zenoh: a RealSense recording (made here with the SDK's recorder
from the software device) played by the `file` backend, posed from odometry on the bus, and the end
of the recording reported on camera/state; at ``rate = "max"`` every frame of it reaches
sensors/rgbd, in order."""

from __future__ import annotations

import threading
import time
import uuid
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("pyrealsense2")

from ovamos.services.camera.config import CameraConfig, OdometryConfig
from ovamos.services.camera.file import FileConfig
from ovamos.services.camera.realsense import RealSenseBackend, RealSenseConfig
from ovamos.services.camera.service import CameraService
from ovamos.services.camera.software_device import SoftwareCamera
from ovamos.shared import keys
from ovamos.shared.bus import Bus
from ovamos.shared.bus.status import live_services
from ovamos.shared.bus.zconfig import build_config
from ovamos.shared.camera import camera_pose
from ovamos.shared.messages import CameraState, Odometry, RgbdFrame, ServiceStats
from ovamos.world.render import SceneRenderer
from tests.polling import wait_for
from tests.service_helpers import Running
from tests.sim_scenes import two_rooms

W, H, FPS, FRAMES = 160, 120, 30, 12
MAX_FRAMES = 60  # enough that a capture queue which drops while the service is busy loses some
POSE = (1.5, 2.0, -0.4)


def _record(path: Path, frames: int = FRAMES, period_s: float = 1.0 / FPS) -> None:
    """Record ``frames`` views of the house from POSE, frame n marked with n in its first pixel
    (see :func:`_mark`), pushed ``period_s`` apart (the host times real-time playback replays)."""
    with SceneRenderer(two_rooms(), W, H) as renderer:
        frame = renderer.render(*POSE)
    rgb, depth = frame.rgb.copy(), np.round(frame.depth / 0.001).astype(np.uint16)
    camera = SoftwareCamera(W, H, frame.intrinsics, fps=FPS)
    camera.start_recording(path)
    backend = RealSenseBackend(RealSenseConfig(width=W, height=H, fps=FPS, warmup_frames=0), source=camera)
    backend.start()
    try:
        for n in range(frames):
            marked = rgb.copy()
            marked[0, 0] = (n % 256, n // 256, 0)
            camera.push(marked, depth, frame_number=n)
            backend.read(1.0)
            if period_s:
                time.sleep(period_s)
    finally:
        backend.stop()
        camera.stop_recording()
        camera.close()


def _mark(frame: RgbdFrame) -> int:
    """Which recorded frame this is (colour reaches sensors/rgbd unchanged: aligning depth to
    colour leaves colour alone)."""
    return int(frame.rgb[0, 0, 0]) + 256 * int(frame.rgb[0, 0, 1])


@pytest.fixture(scope="module")
def max_recording(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("rec") / "run.db3"
    _record(path, MAX_FRAMES, period_s=0.0)  # paced by each read; max playback ignores host times
    return path


@pytest.fixture
def robot() -> str:
    """A robot id of this test's own: a camera service another test left running (connected to a
    router that a later test's router took the port of) answers for its robot id, not for this."""
    return f"cam-{uuid.uuid4().hex[:8]}"


def _readers() -> set[threading.Thread]:
    """The camera reader threads alive in this process (another test's may still be ending)."""
    return {t for t in threading.enumerate() if t.name == "camera-reader"}


def _camera_stats(bus: Bus, robot: str) -> ServiceStats | None:
    """What the camera service answers on its stats key, or None while it is not up yet."""
    found = [s.stats for s in live_services(bus.session, robot) if s.service == "camera" and s.stats]
    return found[0] if found else None


def _max_config(path: Path) -> CameraConfig:
    # A frame captured just before an odometry message arrives waits for it (the default 0.1 s
    # would skip it on a loaded machine).
    return CameraConfig(backend="file", file=FileConfig(path=path, rate="max"), lock_step=False,
                        odometry=OdometryConfig(wait_s=5.0))


class _Robot:
    """The test's end of the bus: the base driver's odometry at 50 Hz (standing still at POSE)
    and what the camera publishes. Subscribers are callbacks appending to lists (through the
    bus's inbox, which keeps every ordinary event), so the test side loses no frame."""

    def __init__(self, bus: Bus, robot: str) -> None:
        self.frames: list[RgbdFrame] = []
        self.states: list[CameraState] = []
        bus.subscribe(keys.rgbd(robot), RgbdFrame, self.frames.append)
        bus.subscribe(keys.camera_state(robot), CameraState, self.states.append)
        self._odom = bus.publisher(keys.odom(robot), Odometry)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._base, daemon=True)
        self.sent = 0  # odometry messages put so far

    def _base(self) -> None:
        while not self._stop.is_set():
            self.sent = seq = self.sent + 1
            self._odom.put(Odometry(seq=seq, stamp=time.time(), x=POSE[0], y=POSE[1], yaw=POSE[2]))
            self._stop.wait(0.02)

    def __enter__(self) -> _Robot:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(5)

    def ended(self) -> bool:
        return any("end of recording" in s.fault for s in self.states)


def test_a_recording_is_played_posed_and_its_end_reported(inproc_router: str, robot: str, tmp_path: Path) -> None:
    path = tmp_path / "run.db3"
    _record(path)
    with Bus.open(build_config(connect=[inproc_router]), robot, "test-robot") as bus, _Robot(bus, robot) as base:
        wait_for(lambda: base.sent >= 5, 10, "odometry streaming before the camera starts")
        config = CameraConfig(backend="file", file=FileConfig(path=path, rate="realtime"), lock_step=False)
        running = Running(CameraService, inproc_router, config, robot)
        try:
            wait_for(base.ended, 30, "the end of the recording on camera/state")
        finally:
            running.close()
    frames = base.frames
    assert len({f.seq for f in frames}) >= FRAMES - 4  # real-time playback may lose its first ones
    expected = np.asarray(camera_pose(*POSE)).reshape(4, 4)
    for frame in frames:
        np.testing.assert_allclose(frame.pose_matrix, expected, atol=1e-6)
        assert frame.depth.dtype == np.uint16 and frame.rgb.shape == (H, W, 3)


def test_max_rate_playback_delivers_every_frame_in_order(inproc_router: str, robot: str,
                                                      max_recording: Path) -> None:
    """``rate = "max"`` promises every frame: the reader waits for the service (and for room among
    the frames the core holds for odometry) instead of dropping the oldest capture."""
    with Bus.open(build_config(connect=[inproc_router]), robot, "test-robot") as bus, _Robot(bus, robot) as base:
        running = Running(CameraService, inproc_router, _max_config(max_recording), robot)
        try:
            wait_for(base.ended, 30, "the end of the recording on camera/state")

            def settled() -> ServiceStats | None:  # nothing left in the core, all it published here
                stats = _camera_stats(bus, robot)
                info = stats.info if stats is not None else {}
                done = info.get("pending") == 0 and info.get("published") == len(base.frames)
                return stats if done else None
            stats = wait_for(settled, 30, "the camera's published frames to arrive")
        finally:
            running.close()
    marks = [_mark(f) for f in base.frames]
    capture = stats.counters.get("camera/capture")
    assert marks == list(range(MAX_FRAMES)), (
        f"{len(marks)} of {MAX_FRAMES} frames; missing {sorted(set(range(MAX_FRAMES)) - set(marks))}; "
        f"capture dropped {capture.dropped if capture else 0}; received {stats.info['received']}, "
        f"skipped {stats.info['skipped']}, rejected {stats.info['rejected']}")
    assert [f.seq for f in base.frames] == list(range(MAX_FRAMES))
    expected = np.asarray(camera_pose(*POSE)).reshape(4, 4)
    for frame in base.frames:
        np.testing.assert_allclose(frame.pose_matrix, expected, atol=1e-6)


def test_a_max_playback_waits_for_odometry_before_it_reads(inproc_router: str, robot: str,
                                                          max_recording: Path) -> None:
    """No odometry yet: the reader reads nothing (a frame captured before the first odometry
    could only be skipped), and stopping the service then ends it at once."""
    before = _readers()
    with Bus.open(build_config(connect=[inproc_router]), robot, "test-robot") as bus:
        running = Running(CameraService, inproc_router, _max_config(max_recording), robot)
        try:
            stats = wait_for(lambda: _camera_stats(bus, robot), 30, "the camera's stats")
            assert stats.info["paced_posing"] is False and stats.info["received"] == 0
        finally:
            running.close()  # asserts the service's thread ended
    # the reader saw the stop (one still waiting would outlive the service's 5 s join, a daemon)
    assert not _readers() - before


def test_a_max_playback_waiting_for_the_service_stops_cleanly(inproc_router: str, robot: str,
                                                              max_recording: Path) -> None:
    """Odometry that stops after one message: the core holds its odometry.max_pending frames
    waiting for newer odometry, the reader waits for room, and stopping the service then ends it
    at once."""
    before = _readers()
    config = _max_config(max_recording)
    with Bus.open(build_config(connect=[inproc_router]), robot, "test-robot") as bus:
        odom = bus.publisher(keys.odom(robot), Odometry)
        running = Running(CameraService, inproc_router, config, robot)
        try:
            one = Odometry(seq=1, stamp=time.time(), x=POSE[0], y=POSE[1], yaw=POSE[2])

            def heard() -> bool:  # one message, sent until the camera has it (repeats are dropped)
                stats = _camera_stats(bus, robot)
                if stats is None or not stats.info.get("paced_posing"):
                    odom.put(one)
                    return False
                return True
            wait_for(heard, 30, "the camera to hear odometry")
            wait_for(lambda: (stats := _camera_stats(bus, robot)) is not None
                     and stats.info.get("paced_in_flight") == config.odometry.max_pending,
                     30, "the reader waiting for room")
        finally:
            running.close()  # asserts the service's thread ended
    # the reader saw the stop, not odometry.wait_s freeing room (it would outlive the service's 5 s join)
    assert not _readers() - before
