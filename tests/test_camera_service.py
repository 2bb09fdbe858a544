"""The camera service's adapter on the fake bus, with the real RealSense backend on the SDK's own
software device: posed frames out, lock-step after each completed command, and a camera that stops
delivering is a fault within 1.5 s that clears when frames return, without a restart."""

from __future__ import annotations

import math
import threading
import time

import numpy as np
import pytest

pytest.importorskip("pyrealsense2")

from ovamos.services.camera.config import CameraConfig
from ovamos.services.camera.realsense import RealSenseBackend, RealSenseConfig
from ovamos.services.camera.service import CameraService
from ovamos.services.camera.software_device import SoftwareCamera
from ovamos.shared import keys
from ovamos.shared.camera import camera_pose
from ovamos.shared.fake_bus import FakeNetwork
from ovamos.shared.messages import CameraState, DriverMode, DriverState, Odometry, RgbdFrame
from ovamos.world.render import SceneRenderer
from tests.sim_scenes import two_rooms

pytestmark = pytest.mark.serial  # real-time devices, rates or deadlines: run alone, after the parallel tests (make test-all)

ROBOT, W, H, FPS = "r1", 160, 120, 30
POSE = (1.5, 2.0, 0.3)  # the robot stands still here


class Rig:
    """The camera service on a fake bus, a software camera fed at FPS, odometry at 50 Hz."""

    def __init__(self, config: CameraConfig) -> None:
        with SceneRenderer(two_rooms(), W, H) as renderer:
            frame = renderer.render(*POSE)
        self.rgb, self.depth = frame.rgb.copy(), np.round(frame.depth / 0.001).astype(np.uint16)
        self.camera = SoftwareCamera(W, H, frame.intrinsics, fps=FPS)
        backend = RealSenseBackend(RealSenseConfig(width=W, height=H, fps=FPS, warmup_frames=0),
                                   source=self.camera)
        self.net = FakeNetwork()
        self.service = CameraService(self.net.bus(ROBOT, "camera"), config, backend=backend)
        tester = self.net.bus(ROBOT, "tester")
        self.frames: list[RgbdFrame] = []
        self.states: list[tuple[float, CameraState]] = []
        tester.subscribe(keys.rgbd(ROBOT), RgbdFrame, self.frames.append)
        tester.subscribe(keys.camera_state(ROBOT), CameraState,
                         lambda s: self.states.append((time.monotonic(), s)))
        self.odom = tester.publisher(keys.odom(ROBOT), Odometry)
        self.driver = tester.publisher(keys.driver_state(ROBOT), DriverState)
        self.feeding = threading.Event()
        self._done = threading.Event()
        self._odom_seq = 0
        self._feeder = threading.Thread(target=self._feed, daemon=True)

    def _feed(self) -> None:
        n = 0
        while not self._done.is_set():
            if self.feeding.is_set():
                self.camera.push(self.rgb, self.depth, frame_number=n)
                n += 1
            time.sleep(1.0 / FPS)

    def __enter__(self) -> Rig:
        self.service.start()
        self._feeder.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._done.set()
        self._feeder.join(5)
        self.service.stop()
        self.camera.close()

    def run(self, seconds: float) -> None:
        """The service's loop by hand: odometry at 50 Hz, events pumped, ticks."""
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            self._odom_seq += 1
            self.odom.put(Odometry(seq=self._odom_seq, stamp=time.time(), x=POSE[0], y=POSE[1], yaw=POSE[2]))
            self.net.pump()
            self.service.tick()
            self.net.pump()
            time.sleep(0.02)


def test_frames_are_posed_from_odometry_and_gated_by_completed_commands() -> None:
    with Rig(CameraConfig(lock_step=True)) as rig:
        rig.feeding.set()
        rig.run(1.0)
        assert rig.frames, "the start-up frame"
        first = rig.frames[0]
        assert first.after_action == 0 and first.depth.dtype == np.uint16
        assert first.depth_scale == pytest.approx(0.001)  # the SDK keeps it as a float32
        np.testing.assert_allclose(first.pose_matrix, np.asarray(camera_pose(*POSE)).reshape(4, 4),
                                   atol=1e-6)  # odometry x the default mount = the simulator's camera
        assert len({f.seq for f in rig.frames}) == 1  # lock-step: nothing new without a completion
        rig.driver.put(DriverState(stamp=time.time(), mode=DriverMode.READY, last_completed=1))
        rig.run(0.5)
        after = [f for f in rig.frames if f.after_action == 1]
        assert after and len({f.seq for f in after}) == 1 and after[0].seq == first.seq + 1


def test_a_camera_that_stops_is_a_fault_within_1_5_s_and_recovers_without_a_restart() -> None:
    with Rig(CameraConfig(lock_step=False)) as rig:
        rig.feeding.set()
        rig.run(1.0)
        assert rig.frames and all(not s.fault for _, s in rig.states)
        rig.feeding.clear()
        stopped = time.monotonic()
        rig.run(2.0)
        faults = [(t, s) for t, s in rig.states if s.fault]
        assert faults, "no fault reported"
        assert faults[0][0] - stopped <= 1.5 and "no camera frames" in faults[0][1].fault
        assert "no camera frames" in rig.service.info()["fault"]  # in `ovamos status` too
        count = len(rig.frames)
        rig.feeding.set()
        rig.run(1.0)
        assert len(rig.frames) > count and not rig.states[-1][1].fault  # back, same process
        assert rig.service.restarts == 0  # a silence is not an error: nothing was restarted
        assert math.isfinite(rig.frames[-1].stamp)
