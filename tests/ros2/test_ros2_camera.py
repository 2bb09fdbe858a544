"""The ros2 camera backend against a mock ROS 2 camera (bench/ros2_peers/fake_camera.py, real rclpy in
its own process): frames with the camera info's intrinsics and depth in millimetres from 16UC1
and 32FC1, colour from rgb8 and bgr8, reliable and best-effort publishers; each fault a clear
CameraError (or, unpaired stamps, counted)."""

from __future__ import annotations

import time
from collections.abc import Iterator

import numpy as np
import pytest

from ovamos.bench.ros2_peers.nodes import MockNode
from ovamos.services.camera.capture import CameraError, CapturedFrame
from ovamos.services.camera.ros2 import Ros2Backend, Ros2CameraConfig


def read_frame(backend: Ros2Backend, timeout_s: float = 20.0) -> CapturedFrame:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        frame = backend.read(0.5)
        if frame is not None:
            return frame
    raise AssertionError(f"no frame in {timeout_s} s: {dict(backend.counters)}")


IDS = "/camera/camera/instance_ids"  # where fake_camera.py puts them


def camera(*args: str, **config: float | str) -> Iterator[Ros2Backend]:
    node = MockNode("fake_camera.py", *args)
    backend = Ros2Backend(Ros2CameraConfig(**config))
    backend.start()
    try:
        yield backend
    finally:
        backend.stop()
        node.close()


@pytest.mark.parametrize("args", [(), ("--depth-encoding", "32FC1", "--color-encoding", "bgr8"), ("--best-effort",)],
                         ids=["16UC1-rgb8-reliable", "32FC1-bgr8", "best-effort"])
def test_frames_carry_the_infos_intrinsics_and_depth_in_millimetres(args: tuple[str, ...]) -> None:
    for backend in camera(*args):
        frame = read_frame(backend)
        assert frame.rgb.shape == (48, 64, 3) and frame.rgb.dtype == np.uint8
        assert frame.rgb[5, 9].tolist() == [9, 5, 7]  # red: column, green: row, in RGB order
        assert frame.depth.shape == (48, 64) and frame.depth.dtype == np.uint16 and frame.depth_scale == 0.001
        assert frame.depth[20, 30] == 1234 and frame.depth[:4, :4].max() == 0
        if "32FC1" in args:
            assert frame.depth[:4, 4:8].max() == 0  # NaN: no reading
        k = frame.intrinsics
        assert (k.fx, k.fy, k.cx, k.cy) == (50.0, 52.0, 31.5, 23.5)
        assert abs(frame.device_time_s - time.time()) < 60 and frame.host_time_s <= time.monotonic()


@pytest.mark.parametrize("args,config,message", [
    (("--color-encoding", "mono8"), {}, "colour encoding 'mono8' is not read"),
    (("--depth-width", "32"), {}, "sizes differ: colour 64x48, depth 32x48"),
    (("--no-info",), {"info_timeout_s": 0.5}, "no sensor_msgs/CameraInfo on /camera/camera/color/camera_info"),
    (("--ids-encoding", "16UC1"), {"instance_ids": IDS}, "instance-id encoding '16UC1' is not read"),
    (("--ids-encoding", "32SC1", "--ids-width", "32"), {"instance_ids": IDS},
     "sizes differ: colour 64x48, instance ids 32x48"),
], ids=["wrong-encoding", "mismatched-sizes", "no-camera-info", "ids-encoding", "ids-size"])
def test_each_fault_is_a_camera_error_with_the_reason(args: tuple[str, ...], config: dict, message: str) -> None:
    for backend in camera(*args, **config):
        deadline = time.monotonic() + 20
        with pytest.raises(CameraError, match=message):
            while time.monotonic() < deadline:
                backend.read(0.5)


def test_a_simulated_cameras_instance_ids_come_with_its_frame_and_only_when_asked_for() -> None:
    for backend in camera("--ids-encoding", "32SC1", instance_ids=IDS):
        frame = read_frame(backend)
        assert frame.instance_ids is not None and frame.instance_ids.dtype.kind == "i"
        assert frame.instance_ids.shape == (48, 64) and frame.instance_ids[7].tolist() == list(range(64))
    for backend in camera("--ids-encoding", "32SC1"):
        assert read_frame(backend).instance_ids is None


def test_unpaired_stamps_give_no_frame_and_are_counted() -> None:
    for backend in camera("--depth-offset-s", "0.03"):  # a depth 30 ms after its colour: never within 10 ms
        deadline = time.monotonic() + 20
        while backend.counters["unpaired"] < 5 and time.monotonic() < deadline:
            assert backend.read(0.5) is None
        assert backend.counters["unpaired"] >= 5


def test_through_the_camera_service_frames_reach_sensors_rgbd_posed_from_odometry() -> None:
    """The camera service with this backend, on the fake bus (an in-process stand-in for Zenoh):
    the mock camera's frames come out on ``sensors/rgbd`` with its intrinsics and depths, posed
    from odometry (a robot standing at POSE) with the default mount."""
    from ovamos.services.camera.config import CameraConfig
    from ovamos.services.camera.service import CameraService
    from ovamos.shared import keys
    from ovamos.shared.camera import camera_pose
    from ovamos.shared.fake_bus import FakeNetwork
    from ovamos.shared.messages import Odometry, RgbdFrame

    pose = (1.5, 2.0, 0.3)
    node = MockNode("fake_camera.py")
    net = FakeNetwork()
    service = CameraService(net.bus("r1", "camera"), CameraConfig(backend="ros2", lock_step=False))
    tester = net.bus("r1", "tester")
    frames: list[RgbdFrame] = []
    tester.subscribe(keys.rgbd("r1"), RgbdFrame, frames.append)
    odom = tester.publisher(keys.odom("r1"), Odometry)
    service.start()
    try:
        deadline, seq = time.monotonic() + 30, 0
        while len(frames) < 3 and time.monotonic() < deadline:  # the service's loop by hand, 50 Hz odometry
            seq += 1
            odom.put(Odometry(seq=seq, stamp=time.time(), x=pose[0], y=pose[1], yaw=pose[2]))
            net.pump()
            service.tick()
            net.pump()
            time.sleep(0.02)
    finally:
        service.stop()
        node.close()
    assert len(frames) >= 3, service.info()
    frame = frames[-1]
    assert (frame.intrinsics.fx, frame.intrinsics.cy) == (50.0, 23.5)
    assert frame.depth[20, 30] * frame.depth_scale == pytest.approx(1.234)
    np.testing.assert_allclose(frame.pose_matrix, np.asarray(camera_pose(*pose)).reshape(4, 4), atol=1e-6)
