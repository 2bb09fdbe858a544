"""Camera geometry: the mount's conventions, and frames posed by the core map the true house.

End to end without hardware: the simulator renders a known house (tests/sim_scenes.py
``two_rooms``) at the true poses along a path; the frames go to the camera core as a
camera would deliver them (uint16 millimetre depth, a device clock with its own epoch
and drift, 30 ms late with jitter), odometry along the same path at 50 Hz (jittered,
late too); the core times and poses them, the mapping core fuses them, and the map's
obstacles are compared with the simulator's true occupancy over the area the camera saw.
A mount 10 deg off in yaw must visibly break that agreement: the check can fail.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
import pytest

from ovamos.services.camera.capture import CapturedFrame
from ovamos.services.camera.config import CameraConfig, ClockConfig, Mount
from ovamos.services.camera.core import CameraCore
from ovamos.services.camera.pose import BasePose, base_T_optical, camera_pose
from ovamos.services.mapping.config import MappingConfig
from ovamos.services.mapping.state import MapState
from ovamos.shared.camera import CAMERA_HEIGHT_M, OPTICAL_TO_BODY
from ovamos.shared.camera import camera_pose as sim_camera_pose
from ovamos.shared.messages import Intrinsics, Odometry
from ovamos.world.occupancy import rasterize
from tests.sim_scenes import two_rooms

# -- the mount's conventions ---------------------------------------------------------------------


@pytest.mark.parametrize("x, y, yaw", [(0.0, 0.0, 0.0), (1.5, -2.0, 0.7), (-3.2, 4.1, -2.9),
                                       (0.3, 0.2, math.pi), (2.0, 1.0, -math.pi / 2)])
def test_level_mount_gives_the_simulators_camera_pose(x: float, y: float, yaw: float) -> None:
    """A level camera 0.88 m up on the base's axis is the simulator's camera: the robot's frames
    and the simulated ones are posed the same way (one convention, shared/camera.py)."""
    mount = base_T_optical(Mount(x=0, y=0, z=CAMERA_HEIGHT_M, roll=0, pitch=0, yaw=0))
    np.testing.assert_allclose(camera_pose(BasePose(x, y, yaw), mount), sim_camera_pose(x, y, yaw),
                               atol=1e-12)


def optical_axes(mount: Mount, base: BasePose = BasePose(0.0, 0.0, 0.0)) -> np.ndarray:
    """world_T_camera of a mount on a base, as a 4x4."""
    return np.asarray(camera_pose(base, base_T_optical(mount))).reshape(4, 4)


def test_mount_angles_follow_rep103() -> None:
    """pitch > 0 looks down, yaw > 0 looks left, roll > 0 turns the image's right side down;
    the translation is in the base frame, so it turns with the base."""
    forward = optical_axes(Mount(pitch=20))[:3, 2]   # optical z = viewing direction
    np.testing.assert_allclose(forward, [math.cos(math.radians(20)), 0, -math.sin(math.radians(20))],
                               atol=1e-12)
    forward = optical_axes(Mount(yaw=90))[:3, 2]
    np.testing.assert_allclose(forward, [0, 1, 0], atol=1e-12)
    right = optical_axes(Mount(roll=30))[:3, 0]      # optical x = image right
    np.testing.assert_allclose(right, [0, -math.cos(math.radians(30)), -math.sin(math.radians(30))],
                               atol=1e-12)
    pose = optical_axes(Mount(x=0.2, y=0.1, z=0.5), BasePose(1.0, 2.0, math.pi / 2))
    np.testing.assert_allclose(pose[:3, 3], [1.0 - 0.1, 2.0 + 0.2, 0.5], atol=1e-12)
    np.testing.assert_allclose(pose[:3, :3], sim_camera_pose_rotation(math.pi / 2), atol=1e-12)


def sim_camera_pose_rotation(yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ OPTICAL_TO_BODY


# -- end to end: a simulated house mapped through the core ---------------------------------------

SCENE = two_rooms()           # 6 x 4 m, two rooms joined by a door at x = 3, y in [1.5, 2.5]
WIDTH, HEIGHT = 320, 240
FRAME_HZ, ODOM_HZ = 10.0, 50.0
LATENCY_S = 0.030             # capture -> receipt, plus up to 4 ms of jitter
T0 = 100.0                    # host monotonic time at the start of the path
WALL_OFFSET = 1.7e9           # host wall = host monotonic + this
DEVICE_OFFSET, DRIFT = -37.0, 5e-5  # device clock = (host + DEVICE_OFFSET) * (1 + DRIFT)
TURN_RATE, SPEED = 0.8, 0.4   # rad/s, m/s
MAPPING = MappingConfig(grid_cells=240, center=(3.0, 2.0))
IOU_MIN = 0.9

_TURN = 2 * math.pi / TURN_RATE
_DRIVE = 3.0 / SPEED
DURATION = 2 * _TURN + _DRIVE


def true_pose(t: float) -> tuple[float, float, float, float, float]:
    """(x, y, yaw, forward speed, yaw rate) at path time ``t``: a full turn in the kitchen at
    (1.5, 2), through the door to (4.5, 2), a full turn in the office."""
    if t < _TURN:
        return 1.5, 2.0, math.remainder(TURN_RATE * t, 2 * math.pi), 0.0, TURN_RATE
    if t < _TURN + _DRIVE:
        return 1.5 + SPEED * (t - _TURN), 2.0, 0.0, SPEED, 0.0
    t = min(t, DURATION) - _TURN - _DRIVE
    return 4.5, 2.0, math.remainder(TURN_RATE * t, 2 * math.pi), 0.0, TURN_RATE if t < _TURN else 0.0


@dataclass(frozen=True)
class Shot:
    """One rendered frame as a camera delivers it, and what the test knows about it."""

    captured: CapturedFrame
    true_pose: tuple[float, ...]  # world_T_camera where it really was taken


@dataclass(frozen=True)
class Recording:
    events: list[tuple[float, Odometry | Shot]]  # (host monotonic receipt time, message), in order
    shots: list[Shot]
    seen: np.ndarray  # map cells where the true surfaces the camera saw lie (obstacle band)


def surface_cells(depth_m: np.ndarray, k: Intrinsics, pose: tuple[float, ...], state: MapState
                  ) -> np.ndarray:
    """Cells of the points a depth image saw within the map's obstacle band, back-projected with
    a known pose: numpy only, independent of the mapping code under test."""
    c = state.config
    v, u = np.nonzero((depth_m >= c.depth_min) & (depth_m <= c.depth_max))
    z = depth_m[v, u].astype(np.float64)
    cam = np.stack([(u - k.cx) / k.fx * z, (v - k.cy) / k.fy * z, z, np.ones_like(z)])
    world = (np.asarray(pose).reshape(4, 4) @ cam)[:3]
    band = (world[2] >= c.min_obstacle_height) & (world[2] <= c.max_obstacle_height)
    rows, cols = state.grid.to_cell(world[0, band], world[1, band])
    inside = (rows >= 0) & (rows < state.grid.rows) & (cols >= 0) & (cols < state.grid.cols)
    cells = np.zeros(state.grid.shape, bool)
    cells[rows[inside], cols[inside]] = True
    return cells


@pytest.fixture(scope="module")
def recording() -> Recording:
    """The path rendered once (the frames do not depend on the mount under test)."""
    from ovamos.world.render import SceneRenderer  # MuJoCo (EGL): only when these tests run

    rng = np.random.default_rng(16)
    events: list[tuple[float, Odometry | Shot]] = []
    for k in range(int((DURATION + 0.5) * ODOM_HZ)):
        t = k / ODOM_HZ + rng.normal(0.0, 0.002)  # measured a little irregularly ...
        x, y, yaw, v, w = true_pose(t)
        msg = Odometry(seq=k, stamp=T0 + t + WALL_OFFSET, x=x, y=y, yaw=yaw, linear=v, angular=w)
        events.append((T0 + t + rng.uniform(0.002, 0.012), msg))  # ... and received late
    shots: list[Shot] = []
    seen = np.zeros(MapState(MAPPING).grid.shape, bool)
    geometry = MapState(MAPPING)
    with SceneRenderer(SCENE, WIDTH, HEIGHT) as renderer:
        for j in range(int(DURATION * FRAME_HZ)):
            t = j / FRAME_HZ
            x, y, yaw, _, _ = true_pose(t)
            frame = renderer.render(x, y, yaw)
            received = T0 + t + LATENCY_S + rng.uniform(0.0, 0.004)
            captured = CapturedFrame(
                rgb=frame.rgb, depth=np.round(frame.depth * 1000).astype(np.uint16), depth_scale=0.001,
                intrinsics=frame.intrinsics, device_time_s=(T0 + t + DEVICE_OFFSET) * (1 + DRIFT),
                host_time_s=received)
            shot = Shot(captured, frame.camera_pose)
            shots.append(shot)
            events.append((received, shot))
            seen |= surface_cells(frame.depth, frame.intrinsics, frame.camera_pose, geometry)
    events.sort(key=lambda e: e[0])
    return Recording(events, shots, seen)


@dataclass(frozen=True)
class Mapped:
    state: MapState
    core: CameraCore
    poses: dict[int, tuple[float, ...]]  # published seq -> camera_pose


def map_through_core(recording: Recording, mount: Mount) -> Mapped:
    """Feed the recording to a free-running core in receipt order, as the service's one thread
    would, and fuse every frame it publishes."""
    config = CameraConfig(lock_step=False, mount=mount, clock=ClockConfig(min_latency_s=LATENCY_S))
    core = CameraCore(config, T0, wall_offset=lambda: WALL_OFFSET)
    state = MapState(MAPPING)
    poses: dict[int, tuple[float, ...]] = {}
    now = T0
    for now, event in recording.events:
        if isinstance(event, Odometry):
            core.on_odom(event)
        else:
            core.on_frame(event.captured)
        frames, _ = core.poll(now)
        for frame in frames:
            state.integrate(frame)
            poses[frame.seq] = frame.camera_pose
    frames, _ = core.poll(now + 1.0)
    for frame in frames:
        state.integrate(frame)
        poses[frame.seq] = frame.camera_pose
    return Mapped(state, core, poses)


def _grow(cells: np.ndarray) -> np.ndarray:
    return cv2.dilate(cells.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)


def seen_iou(mapped: MapState, seen: np.ndarray) -> float:
    """IoU of the mapped obstacles and the true occupancy the camera saw, to one cell.

    The truth is the simulator's occupancy (walls, floor-standing furniture) restricted to the
    cells within a cell of a surface the camera saw (``seen``: its depth back-projected with the
    true poses), since an occupancy map cannot know the inside of a fridge or the back of a
    wall. One cell of tolerance both ways (a wall face lies on a cell border, so a millimetre
    decides its cell): a true cell counts as found with a mapped cell next to it, a mapped cell
    as right with a true one next to it. IoU = found / (true + wrong mapped).
    """
    truth = rasterize(SCENE, mapped.grid) & _grow(seen)
    obstacle = mapped.obstacle
    found = int((truth & _grow(obstacle)).sum())
    missed = int((truth & ~_grow(obstacle)).sum())
    wrong = int((obstacle & ~_grow(truth)).sum())
    return found / (found + missed + wrong)


@pytest.fixture(scope="module")
def correct(recording: Recording) -> Mapped:
    return map_through_core(recording, Mount(z=CAMERA_HEIGHT_M))


def test_frames_are_posed_where_they_were_taken(recording: Recording, correct: Mapped) -> None:
    """Every frame is published, posed within 3 mm and 0.3 deg of where it was rendered although
    the robot turns at 0.8 rad/s and drives at 0.4 m/s (interpolated odometry at the capture
    time mapped from the device clock)."""
    assert correct.core.published == len(recording.shots)
    assert not correct.core.skipped
    for seq, shot in enumerate(recording.shots):
        got, want = (np.asarray(p).reshape(4, 4) for p in (correct.poses[seq], shot.true_pose))
        assert np.abs(got[:3, 3] - want[:3, 3]).max() < 0.003, seq
        angle = math.acos(min(1.0, (np.trace(got[:3, :3].T @ want[:3, :3]) - 1) / 2))
        assert math.degrees(angle) < 0.3, seq


def test_correct_mount_maps_the_true_occupancy(recording: Recording, correct: Mapped) -> None:
    iou = seen_iou(correct.state, recording.seen)
    print(f"\nseen-area IoU, correct mount: {iou:.3f}")
    assert iou >= IOU_MIN, f"IoU {iou:.3f} with the correct mount"
    assert recording.seen.sum() > 500, "the path saw the house"


def test_a_mount_10_deg_off_in_yaw_breaks_the_map(recording: Recording, correct: Mapped) -> None:
    """The same frames with the mount's yaw 10 deg wrong: walls land up to ~0.5 m from where they
    are, the check fails clearly (so it can fail at all)."""
    wrong = map_through_core(recording, Mount(z=CAMERA_HEIGHT_M, yaw=10.0))
    iou = seen_iou(wrong.state, recording.seen)
    print(f"\nseen-area IoU, mount yaw 10 deg off: {iou:.3f}")
    assert iou < IOU_MIN
    assert iou < seen_iou(correct.state, recording.seen) - 0.3
