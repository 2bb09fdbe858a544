"""Free-running fusion: frames taken while the robot turns are posed at their capture time.

A 360 deg look-around on the simulated Kobuki in simulated time, the demo's episode: stepwise (a
frame at rest after each TURN primitive, the paper's) against free-running (the primitives back
to back, or chained into one rotation, a frame every 1 / ``frame_hz`` s whatever the wheels do), each frame posed by the
camera's own :class:`~ovamos.services.camera.pose.OdometryBuffer` from odometry at the driver's
publishing rate, and fused by the mapping core. The agreement measure is the map's obstacle
precision: the share of cells it marks as obstacles that lie within ``TOLERANCE_M`` of an
occupied cell of the simulator's true occupancy (a frame posed at the wrong heading smears walls
across free space). The control poses each frame at its receipt, ``RECEIPT_S`` after capture,
which is what interpolating at the capture time avoids.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.ndimage import binary_dilation

from ovamos.bench.episode import EpisodeConfig, EpisodeWorld
from ovamos.bench.jobs import load_episode, load_prior
from ovamos.services.base_driver.config import PublishingConfig
from ovamos.services.camera.pose import BasePose, OdometryBuffer, world_T_base
from ovamos.services.planner.navigator import NavMap
from ovamos.shared.messages import PerceptionResult, PlanCommand, RgbdFrame
from ovamos.shared.motion import Action, Pose, wrap_angle

pytestmark = pytest.mark.system  # renders a house: make test-all

EPISODE = (0, 4)  # the demo's
FRAME_HZ = EpisodeConfig().frame_hz
ODOM_HZ = PublishingConfig().odom_hz
TURNS = 12  # 30 deg each: the look-around
AHEAD_DEG = 15.0  # a chained turn is sent this near the end of the one before
TOLERANCE_M = 0.1  # two cells: a mapped wall is up to a cell thicker than the real one
RECEIPT_S = 0.1  # a frame's transfer and decoding before a naive camera would pose it


def _fuse(world: EpisodeWorld, frame: RgbdFrame, true: Pose | None = None, posed: BasePose | None = None) -> None:
    """Into the map; re-posed at ``posed`` when given (the frame was rendered from ``true``)."""
    if true is not None and posed is not None:
        moved = world_T_base(posed.x, posed.y, posed.yaw) @ np.linalg.inv(world_T_base(true.x, true.y, true.yaw))
        camera = moved @ np.asarray(frame.camera_pose, float).reshape(4, 4)
        frame = frame.model_copy(update={"camera_pose": tuple(camera.reshape(-1))})
    world.state.apply(frame, PerceptionResult.build(frame.seq, frame.stamp, {}, [], frame.depth.shape))


def _world() -> EpisodeWorld:
    spec, scene, truth = load_episode(*EPISODE)
    return EpisodeWorld(scene, truth, EpisodeConfig(base="kobuki"), spec.start, load_prior())


def _frame(world: EpisodeWorld, stamp: float) -> RgbdFrame:
    world.seq += 1
    p = world.robot.pose
    return world.renderer.render(p.x, p.y, p.yaw, seq=world.seq, stamp=stamp)


def stepwise_scan() -> EpisodeWorld:
    world = _world()
    for _ in range(TURNS):
        assert world.execute(Action.TURN_LEFT)
        _fuse(world, _frame(world, world.clock()))  # at rest: the true pose is the odometry's
    return world


def free_running_scan(pose_after_s: float, chained: bool = False) -> tuple[EpisodeWorld, int]:
    """The look-around with frames free-running, each posed from odometry at its capture time plus
    ``pose_after_s``; and how many frames were taken while the base turned. ``chained``: each turn
    sent within :data:`AHEAD_DEG` of the end of the one before (which the base chains, turning on
    without stopping: continuous motion's look-around), not once it has ended."""
    world = _world()
    clock, driver = world.clock, world.wheels.driver
    odometry = OdometryBuffer(window_s=5.0, tolerance_s=0.0)
    pending: list[tuple[float, Pose, RgbdFrame]] = []
    turning = 0

    def publish_odometry() -> None:
        odometry.add(driver.odometry().model_copy(update={"stamp": clock()}))

    def capture() -> None:
        nonlocal turning
        pending.append((clock(), world.robot.pose, _frame(world, clock())))
        turning += abs(driver.odometry().angular) > 0.1

    clock.every(1.0 / ODOM_HZ, publish_odometry)
    clock.every(1.0 / FRAME_HZ, capture, first_s=0.5 / FRAME_HZ)  # between odometry messages
    start = driver.odometry().yaw
    for n in range(1, TURNS + 1):
        command = world.command(Action.TURN_LEFT)
        assert driver.submit(command) == "accepted"
        goal = start + math.radians(n * 30)
        if chained and n < TURNS:
            clock.run_until(lambda: abs(wrap_angle(goal - driver.odometry().yaw)) <= math.radians(AHEAD_DEG),
                            10.0, 0.01, "a turn nearly done")
        else:
            clock.run_until(lambda: driver.state().last_completed >= command.action_id, 10.0, 0.01, "a turn")
        while pending and (odometry.newest or 0.0) >= pending[0][0] + pose_after_s:
            at, true, frame = pending.pop(0)
            posed = odometry.pose_at(at + pose_after_s)
            assert isinstance(posed, BasePose), posed
            _fuse(world, frame, true, posed)
    driver.submit(PlanCommand(action_id=world.commands + 1, stamp=clock(), action=Action.STOP))
    return world, turning


def obstacle_precision(world: EpisodeWorld) -> tuple[float, int]:
    """The share of the map's obstacle cells within :data:`TOLERANCE_M` of a truly occupied cell,
    and how many cells it marks."""
    nav = NavMap.from_snapshot(world.state.snapshot(0.0, with_confidence=False))
    rows, cols = np.nonzero(nav.obstacle)
    assert rows.size > 500, "the scan mapped next to nothing"
    truth = world.truth
    near = binary_dilation(truth.occupied, iterations=round(TOLERANCE_M / truth.grid.resolution))
    r, c = truth.grid.to_cell(*nav.grid.to_world(rows, cols))
    inside = (r >= 0) & (r < near.shape[0]) & (c >= 0) & (c < near.shape[1])
    hit = np.zeros(rows.size, bool)
    hit[inside] = near[r[inside], c[inside]]
    return float(hit.mean()), int(rows.size)


def test_frames_taken_while_turning_map_the_room_as_well_as_a_stepwise_scan() -> None:
    """Turn by turn, and chained as continuous motion's look-around does when its turns are decided
    ahead (each turn sent before the one before ends, the base turning on without stopping)."""
    stepwise, stepwise_cells = obstacle_precision(stepwise_scan())
    world, turning = free_running_scan(pose_after_s=0.0)
    free, free_cells = obstacle_precision(world)
    late_world, _ = free_running_scan(pose_after_s=RECEIPT_S)
    late, _ = obstacle_precision(late_world)
    chained_world, chained_turning = free_running_scan(pose_after_s=0.0, chained=True)
    chained, chained_cells = obstacle_precision(chained_world)
    print(f"obstacle precision: stepwise {stepwise:.3f} of {stepwise_cells} cells, free-running {free:.3f} of "
          f"{free_cells} ({turning} of {world.seq} frames while turning), posed at receipt {late:.3f}, chained "
          f"{chained:.3f} of {chained_cells} ({chained_turning} of {chained_world.seq} while turning) in "
          f"{chained_world.clock():.1f} s against {world.clock():.1f} s")
    assert turning >= world.seq // 2  # most frames were taken in motion
    assert free >= stepwise - 0.02 and free_cells >= 0.9 * stepwise_cells  # as clean, the same walls seen
    assert late < free - 0.05  # the measure sees a pose a tenth of a second late
    assert chained_world.wheels.driver.counters["chained_turns"] == TURNS - 1
    assert chained >= stepwise - 0.02 and chained_cells >= 0.9 * stepwise_cells
    assert chained_world.clock() < 0.8 * world.clock()  # the turns did not stop in between
