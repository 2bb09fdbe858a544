"""The simulated robot service over real Zenoh: lock-step frames, both motion modes, blocked moves."""

from __future__ import annotations

import math
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest

from ovamos.services.sim.config import SimServiceConfig
from ovamos.services.sim.service import SimRobotService
from ovamos.shared import keys
from ovamos.shared.bus import Bus
from ovamos.shared.bus.zconfig import build_config
from ovamos.shared.messages import DriverMode, PlanCommand, RgbdFrame
from ovamos.shared.motion import Action, Pose
from tests.polling import wait_for
from tests.service_helpers import ROBOT, Planner, Running
from tests.sim_scenes import two_rooms

pytestmark = pytest.mark.system  # processes, routers, browsers or real-time devices: make test-all


@pytest.fixture
def scene_file(tmp_path: Path) -> Path:
    path = tmp_path / "scene.json"
    two_rooms().save(path)
    return path


class Robot(Planner):
    """The planner's view plus the camera frames."""

    def __init__(self, bus: Bus) -> None:
        super().__init__(bus)
        self.frames: list[RgbdFrame] = []
        bus.subscribe(keys.rgbd(ROBOT), RgbdFrame, self.frames.append)

    def frame(self, seq: int) -> RgbdFrame:
        return wait_for(lambda: next((f for f in self.frames if f.seq == seq), None), 20,
                        f"frame {seq}")

    def frame_after(self, action_id: int) -> RgbdFrame:
        """The first frame rendered after command ``action_id`` completed."""
        return wait_for(lambda: next((f for f in self.frames if f.after_action == action_id), None), 20,
                        f"a frame after command {action_id}")


@contextmanager
def _start(inproc_router: str, config: SimServiceConfig) -> Iterator[Robot]:
    running = Running(SimRobotService, inproc_router, config)
    try:
        with Bus.open(build_config(connect=[inproc_router]), ROBOT, "test-planner") as bus:
            robot = Robot(bus)
            wait_for(lambda: (s := robot.state()) and s.mode is DriverMode.READY, 60, "sim ready")
            yield robot
    finally:
        running.close()


def _config(scene_file: Path, **kw: object) -> SimServiceConfig:
    return SimServiceConfig(scene_file=scene_file, start=Pose(x=1.5, y=2.0, yaw=0.0), width=96, height=72,
                            republish_s=0.3, **kw)


@pytest.fixture
def kinematic(inproc_router: str, scene_file: Path) -> Iterator[Robot]:
    with _start(inproc_router, _config(scene_file)) as robot:
        yield robot


def _camera_xy(frame: RgbdFrame) -> tuple[float, float]:
    m = frame.pose_matrix
    return float(m[0, 3]), float(m[1, 3])


def test_lock_step_kinematic_a_command_yields_one_new_frame_that_says_it_follows_it(kinematic: Robot
                                                                                   ) -> None:
    first = kinematic.frame(0)  # published at start-up, re-published for late subscribers
    assert first.after_action == 0 and first.instance_ids is not None
    assert _camera_xy(first) == pytest.approx((1.5, 2.0))
    state = kinematic.execute(PlanCommand(action_id=1, stamp=0.0, action=Action.MOVE_FORWARD))
    assert state.last_outcome == "done"
    after = kinematic.frame_after(1)
    assert after.seq == 1 and _camera_xy(after) == pytest.approx((1.75, 2.0))
    odom = wait_for(lambda: (o := kinematic.odoms[-1]) and o.after_action == 1 and o, 10, "odometry")
    assert odom.x == pytest.approx(1.75)  # exact, and measured after command 1
    kinematic.execute(PlanCommand(action_id=2, stamp=0.0, action=Action.TURN_LEFT))
    assert kinematic.frame_after(2).seq == 2
    assert kinematic.frame(2).pose_matrix[:3, 2] == pytest.approx(  # optical axis turned 30 deg
        (math.cos(math.radians(30)), math.sin(math.radians(30)), 0.0), abs=1e-6)
    # a re-sent command runs once: no new frame, the same state
    for _ in range(3):
        kinematic.commands.put(PlanCommand(action_id=2, stamp=0.0, action=Action.TURN_LEFT))
    wait_for(lambda: len([f for f in kinematic.frames if f.seq == 2]) >= 2, 10, "frame 2 re-published")
    assert max(f.seq for f in kinematic.frames) == 2


def test_a_blocked_move_reports_blocked(inproc_router: str, scene_file: Path) -> None:
    config = _config(scene_file).model_copy(update={"start": Pose(x=2.6, y=1.0, yaw=0.0)})  # wall at x=3
    with _start(inproc_router, config) as robot:
        state = robot.execute(PlanCommand(action_id=1, stamp=0.0, action=Action.MOVE_FORWARD))
        assert state.last_outcome == "blocked"
        assert _camera_xy(robot.frame_after(1)) == pytest.approx((2.6, 1.0))


def test_free_running_publishes_frames_at_a_rate(inproc_router: str, scene_file: Path) -> None:
    with _start(inproc_router, _config(scene_file, lock_step=False, frame_hz=10.0)) as robot:
        wait_for(lambda: len({f.seq for f in robot.frames}) >= 3, 20, "three distinct frames")


def test_odrive_motion_moves_the_robot_with_its_wheels(inproc_router: str, scene_file: Path) -> None:
    with _start(inproc_router, _config(scene_file, motion="odrive")) as robot:
        state = robot.execute(PlanCommand(action_id=1, stamp=0.0, action=Action.MOVE_FORWARD))
        assert state.last_outcome == "done"
        x, y = _camera_xy(robot.frame_after(1))  # rendered from the true pose
        assert (x, y) == pytest.approx((1.75, 2.0), abs=0.01)
        odom = wait_for(lambda: (o := robot.odoms[-1]) and abs(o.x - 1.75) < 0.01 and o, 10, "odometry")
        assert odom.y == pytest.approx(2.0, abs=0.01)


@pytest.mark.parametrize("motion", ["kobuki", "opencr"])
def test_a_turtlebot_base_moves_the_robot_through_its_serial_client(inproc_router: str, scene_file: Path,
                                                                     motion: str) -> None:
    """The real pyserial / dynamixel-sdk client on a pseudo-terminal, against a simulated Kobuki /
    OpenCR board whose wheels move the simulated robot."""
    with _start(inproc_router, _config(scene_file, motion=motion)) as robot:
        state = robot.execute(PlanCommand(action_id=1, stamp=0.0, action=Action.MOVE_FORWARD))
        assert state.last_outcome == "done"
        x, y = _camera_xy(robot.frame_after(1))  # rendered from the true pose
        assert (x, y) == pytest.approx((1.75, 2.0), abs=0.01)
        state = robot.execute(PlanCommand(action_id=2, stamp=0.0, action=Action.TURN_LEFT))
        assert state.last_outcome == "done"
        axis = robot.frame_after(2).pose_matrix[:3, 2]
        assert math.degrees(math.atan2(axis[1], axis[0])) == pytest.approx(30.0, abs=1.0)


def test_config_refuses_a_scene_without_a_start_and_unknown_keys(scene_file: Path) -> None:
    from pydantic import ValidationError
    with pytest.raises(ValidationError, match="start pose"):
        SimServiceConfig(scene_file=scene_file)
    with pytest.raises(ValidationError, match="extra"):
        SimServiceConfig.model_validate({"motion": "kinematic", "speed": 2})
    with pytest.raises(ValidationError):
        SimServiceConfig.model_validate({"motion": "teleport"})


def test_the_kinematic_base_advertises_its_primitive_sizes_and_runs_an_id_once() -> None:
    from ovamos.services.sim.kinematic import KinematicBase
    from ovamos.services.sim.robot import MotionConfig, SimRobot
    from ovamos.shared.messages import PlanCommand
    from ovamos.shared.motion import Action, Pose
    from ovamos.shared.robot import PRIMITIVES, Primitives

    base = KinematicBase(SimRobot(Pose(x=0.0, y=0.0), lambda x, y: True))
    assert base.state().primitives == PRIMITIVES
    wide = KinematicBase(SimRobot(Pose(x=0.0, y=0.0), lambda x, y: True, MotionConfig(turn_deg=45.0)))
    assert wide.state().primitives == Primitives(turn_deg=45.0)
    move = PlanCommand(action_id=1, stamp=0.0, action=Action.MOVE_FORWARD)
    assert [base.submit(move), base.submit(move)] == ["accepted", "duplicate"]
    base.execute()
    assert base.robot.pose.x == PRIMITIVES.forward_m and base.state().last_completed == 1
