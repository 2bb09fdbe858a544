"""`ovamos run camera` over real Zenoh: a RealSense recording (made here with the SDK's recorder
from the software device) played by the `file` backend, posed from odometry on the bus, and the end
of the recording reported on camera/state."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("pyrealsense2")

from services.camera.config import CameraConfig  # noqa: E402
from services.camera.file import FileConfig  # noqa: E402
from services.camera.realsense import RealSenseBackend, RealSenseConfig  # noqa: E402
from services.camera.service import CameraService  # noqa: E402
from services.camera.software_device import SoftwareCamera  # noqa: E402
from services.sim.render import SceneRenderer  # noqa: E402
from shared import keys  # noqa: E402
from shared.bus import Bus  # noqa: E402
from shared.camera import camera_pose  # noqa: E402
from shared.messages import CameraState, Odometry, RgbdFrame  # noqa: E402
from shared.zconfig import build_config  # noqa: E402
from tests.polling import wait_for  # noqa: E402
from tests.service_helpers import ROBOT, Running  # noqa: E402
from tests.sim_scenes import two_rooms  # noqa: E402

W, H, FPS, FRAMES = 160, 120, 30, 12
POSE = (1.5, 2.0, -0.4)


def _record(path: Path) -> None:
    with SceneRenderer(two_rooms(), W, H) as renderer:
        frame = renderer.render(*POSE)
    rgb, depth = frame.rgb.copy(), np.round(frame.depth / 0.001).astype(np.uint16)
    camera = SoftwareCamera(W, H, frame.intrinsics, fps=FPS)
    camera.start_recording(path)
    backend = RealSenseBackend(RealSenseConfig(width=W, height=H, fps=FPS, warmup_frames=0), source=camera)
    backend.start()
    try:
        for n in range(FRAMES):
            camera.push(rgb, depth, frame_number=n)
            backend.read(1.0)
            time.sleep(1.0 / FPS)
    finally:
        backend.stop()
        camera.stop_recording()
        camera.close()


def test_a_recording_is_played_posed_and_its_end_reported(inproc_router: str, tmp_path: Path) -> None:
    path = tmp_path / "run.db3"
    _record(path)
    frames: list[RgbdFrame] = []
    states: list[CameraState] = []
    stop = threading.Event()
    with Bus.open(build_config(connect=[inproc_router]), ROBOT, "test-robot") as bus:
        bus.subscribe(keys.rgbd(ROBOT), RgbdFrame, frames.append)
        bus.subscribe(keys.camera_state(ROBOT), CameraState, states.append)
        odom = bus.publisher(keys.odom(ROBOT), Odometry)

        def base() -> None:  # the base driver's odometry, 50 Hz, standing still
            seq = 0
            while not stop.is_set():
                seq += 1
                odom.put(Odometry(seq=seq, stamp=time.time(), x=POSE[0], y=POSE[1], yaw=POSE[2]))
                stop.wait(0.02)

        threading.Thread(target=base, daemon=True).start()
        time.sleep(0.3)  # odometry before the first frame
        config = CameraConfig(backend="file", file=FileConfig(path=path, rate="realtime"), lock_step=False)
        running = Running(CameraService, inproc_router, config)
        try:
            wait_for(lambda: any("end of recording" in s.fault for s in states), 30,
                     "the end of the recording on camera/state")
        finally:
            running.close()
            stop.set()
    assert len({f.seq for f in frames}) >= FRAMES - 4  # real-time playback may lose its first ones
    expected = np.asarray(camera_pose(*POSE)).reshape(4, 4)
    for frame in frames:
        np.testing.assert_allclose(frame.pose_matrix, expected, atol=1e-6)
        assert frame.depth.dtype == np.uint16 and frame.rgb.shape == (H, W, 3)
