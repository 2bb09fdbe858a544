"""Path commands (``PlanCommand.path``) on each simulated base, in simulated time: the real base
controller follows the path closed-loop on odometry through the base's simulated device, the
planner's keep-alive re-sending the command, and ends it done at the last point, blocked on a bump,
aborted on an e-stop, a newer command or a keep-alive that stopped (the deadman), slowing near the
obstacles the command names."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import pytest

from ovamos.services.base_driver.config import DriverConfig
from ovamos.services.base_driver.follower import PathFollower
from ovamos.services.sim.robot import MotionConfig, SimRobot
from ovamos.services.sim.wheels import SerialSimRobot, WheeledSimRobot, base_motion, wheeled
from ovamos.shared.messages import MAX_PATH_POINTS, DriverMode, PlanCommand
from ovamos.shared.motion import Action, Pose
from ovamos.shared.simtime import SimClock

BASES = ("odrive", "kobuki", "opencr")
RESEND_S = 0.2  # the planner's keep-alive


class Base:
    """A simulated base in simulated time, with the pose the robot truly took on every tick."""

    def __init__(self, base: str, is_free: Callable[[float, float], bool] = lambda x, y: True,
                 start: Pose = Pose(x=0.0, y=0.0, yaw=0.0)) -> None:
        self.clock = SimClock()
        robot = SimRobot(start, is_free, base_motion(MotionConfig(), base, DriverConfig()))
        self.wheels: SerialSimRobot | WheeledSimRobot = wheeled(robot, base, clock=self.clock).start()
        self.wheels.wait_ready()
        self.driver = self.wheels.driver
        self.trace: list[tuple[float, Pose]] = []
        self.keep_alive_until = math.inf
        self._sent: list[PlanCommand] = []
        self.clock.every(1.0 / self.driver.config.control_hz, lambda: self.trace.append((self.clock(), self.wheels.pose)))
        self.clock.every(RESEND_S, self._resend)

    def _resend(self) -> None:
        if self._sent and self.clock() < self.keep_alive_until:
            self.driver.submit(self._sent[-1])

    def send(self, path: Sequence[tuple[float, float]], obstacles: Sequence[tuple[float, float]] = (),
             speed_m_s: float | None = None) -> PlanCommand:
        command = PlanCommand(action_id=len(self._sent) + 1, stamp=self.clock(), path=tuple(path),
                              obstacles=tuple(obstacles), speed_m_s=speed_m_s)
        assert self.driver.submit(command) == "accepted"
        self._sent.append(command)
        return command

    def until(self, done: Callable[[], bool], what: str, limit_s: float = 60.0) -> None:
        self.clock.run_until(done, limit_s, 1.0 / self.driver.config.control_hz, what)

    def completed(self, command: PlanCommand) -> bool:
        return self.driver.state().last_completed >= command.action_id

    def at_rest(self) -> bool:
        return all(abs(w) < 1e-3 for w in self.driver.wheel_speeds())

    def stop(self) -> None:
        self.wheels.stop()


@pytest.fixture(params=BASES)
def base_name(request: pytest.FixtureRequest) -> str:
    return request.param


def _off_path(pose: Pose, path: Sequence[tuple[float, float]]) -> float:
    """How far ``pose`` is from the polyline ``path``."""
    best = math.inf
    for (ax, ay), (bx, by) in zip(path, path[1:]):
        dx, dy = bx - ax, by - ay
        t = max(0.0, min(1.0, ((pose.x - ax) * dx + (pose.y - ay) * dy) / (dx * dx + dy * dy)))
        best = min(best, math.hypot(ax + t * dx - pose.x, ay + t * dy - pose.y))
    return best


def test_a_straight_path_ends_done_at_its_last_point_and_stays_on_the_line(base_name: str) -> None:
    base = Base(base_name)
    try:
        path = [(0.0, 0.0), (1.5, 0.0)]
        command = base.send(path)
        base.until(lambda: base.completed(command), "the path done")
        assert base.driver.state().last_outcome == "done"
        end = base.wheels.pose
        assert math.hypot(end.x - 1.5, end.y) <= base.driver.config.follow.goal_tolerance_m + 0.02
        assert max(_off_path(p, path) for _, p in base.trace) < 0.02
        assert max(abs(a.x - b.x) for (_, a), (_, b) in zip(base.trace, base.trace[1:])) > 0  # it moved
    finally:
        base.stop()


def test_a_90_degree_corner_is_turned_near_the_path(base_name: str) -> None:
    base = Base(base_name)
    try:
        path = [(0.0, 0.0), (1.0, 0.0), (1.0, 1.0)]
        command = base.send(path)
        base.until(lambda: base.completed(command), "the path done")
        assert base.driver.state().last_outcome == "done"
        end = base.wheels.pose
        assert math.hypot(end.x - 1.0, end.y - 1.0) <= base.driver.config.follow.goal_tolerance_m + 0.02
        assert max(_off_path(p, path) for _, p in base.trace) < 0.15  # a lookahead cuts the corner
        assert abs(math.degrees(end.yaw) - 90) < 20
    finally:
        base.stop()


def test_a_path_through_a_doorway_touches_no_wall(base_name: str) -> None:
    """A wall across x = 1 with a doorway: its centre may pass |y| < 0.12 (a 0.6 m door less the
    robot's 0.18 m radius each side)."""
    def is_free(x: float, y: float) -> bool:
        return not (0.82 < x < 1.18) or abs(y) < 0.12
    base = Base(base_name, is_free, Pose(x=0.0, y=-0.8, yaw=0.0))
    try:
        command = base.send([(0.0, -0.8), (0.6, 0.0), (1.4, 0.0), (2.0, 0.0)])
        base.until(lambda: base.completed(command), "the path done")
        assert base.driver.state().last_outcome == "done" and base.driver.counters["bumps"] == 0
        assert base.wheels.pose.x > 1.9
    finally:
        base.stop()


def _speeds(trace: list[tuple[float, Pose]], lo: float, hi: float, ticks: int = 1) -> list[float]:
    """The robot's speed (m/s) between trace poses ``ticks`` apart while lo <= x <= hi (over several
    ticks, the one tick whose pose caught up with two ticks' motion averages out)."""
    return [math.hypot(b.x - a.x, b.y - a.y) / (tb - ta) for (ta, a), (tb, b) in zip(trace, trace[ticks:])
            if lo <= a.x <= hi and tb > ta]


def test_the_follower_slows_beside_a_named_obstacle_and_not_elsewhere(base_name: str) -> None:
    """A post 0.25 m beside a straight path: a 0.07 m gap to the footprint, so beside it the robot
    drives at most 0.07 / slow_clearance_m of its top speed (or near_obstacle_m_s, the floor); well
    before it, at full speed. The
    same path without the post named: full speed beside it too (the robot has no map)."""
    top = {}
    for named in ((1.5, 0.25),), ():
        base = Base(base_name)
        f, c = base.driver.config.follow, base.driver.config
        try:
            command = base.send([(0.0, 0.0), (3.0, 0.0)], obstacles=named)
            base.until(lambda: base.completed(command), "the path done")
            assert base.driver.state().last_outcome == "done"
            top[bool(named)] = (max(_speeds(base.trace, 0.5, 0.8)), max(_speeds(base.trace, 1.45, 1.55)))
        finally:
            base.stop()
    cap = max(f.near_obstacle_m_s, c.max_linear_m_s * (0.25 - f.footprint_m) / f.slow_clearance_m)
    full = top[False][0]  # the base's cruising speed (a simulated OpenCR's wheels fall short of the limit)
    assert top[True][1] <= cap + 0.01 < full - 0.05  # beside the post: slowed
    assert top[True][0] == pytest.approx(full, abs=0.01)  # before it: full speed
    assert top[False][1] == pytest.approx(full, abs=0.01)  # not named: not slowed


def test_a_path_with_a_top_speed_is_driven_no_faster(base_name: str) -> None:
    """A careful path's ``speed_m_s`` caps the follower's speed all along; the same path without it
    cruises faster."""
    top = {}
    for speed in (0.1, None):
        base = Base(base_name)
        try:
            command = base.send([(0.0, 0.0), (1.0, 0.0)], speed_m_s=speed)
            base.until(lambda: base.completed(command), "the path done")
            assert base.driver.state().last_outcome == "done"
            top[speed] = max(_speeds(base.trace, 0.0, 1.0, ticks=5))
        finally:
            base.stop()
    assert top[0.1] <= 0.1 + 0.01 < top[None] - 0.05


def test_a_newer_path_replaces_the_one_being_followed(base_name: str) -> None:
    base = Base(base_name)
    try:
        first = base.send([(0.0, 0.0), (3.0, 0.0)])
        base.until(lambda: base.wheels.pose.x > 0.5, "half a metre along the first path")
        second = base.send([(0.8, 0.0), (0.8, 1.0)])
        state = base.driver.state()
        assert (state.last_completed, state.last_outcome) == (first.action_id, "aborted")
        base.until(lambda: base.completed(second), "the second path done")
        end = base.wheels.pose
        assert base.driver.state().last_outcome == "done" and math.hypot(end.x - 0.8, end.y - 1.0) < 0.1
        assert max(p.x for _, p in base.trace) < 1.3  # it did not go on along the first
    finally:
        base.stop()


def test_a_stopped_keep_alive_aborts_the_path_and_the_wheels_stop_within_the_deadman_bound(base_name: str) -> None:
    base = Base(base_name)
    c = base.driver.config
    try:
        command = base.send([(0.0, 0.0), (5.0, 0.0)])
        base.until(lambda: base.wheels.pose.x > 0.5, "moving")
        base.keep_alive_until = base.clock()
        last_copy = base.keep_alive_until - RESEND_S  # the newest copy went out at most this long ago
        base.until(lambda: base.completed(command), "the path aborted")
        assert base.driver.state().last_outcome == "aborted" and base.driver.counters["deadman"] == 1
        base.until(base.at_rest, "wheels at rest")
        assert base.clock() - last_copy <= c.deadman_s + c.max_linear_m_s / c.max_linear_accel_m_s2 + RESEND_S + 0.1
    finally:
        base.stop()


def test_a_bump_mid_path_ends_it_blocked_with_the_wheels_stopped(base_name: str) -> None:
    base = Base(base_name, lambda x, y: x < 1.0)
    try:
        command = base.send([(0.0, 0.0), (2.0, 0.0)])
        base.until(lambda: base.completed(command), "the path ended")
        assert base.driver.state().last_outcome == "blocked"
        base.until(base.at_rest, "wheels at rest", 2.0)
        assert base.wheels.pose.x < 1.0
    finally:
        base.stop()


def test_an_estop_mid_path_aborts_it_and_holds_the_wheels(base_name: str) -> None:
    base = Base(base_name)
    try:
        command = base.send([(0.0, 0.0), (3.0, 0.0)])
        base.until(lambda: base.wheels.pose.x > 0.5, "moving")
        base.driver.engage_estop("test", "mid-path")
        assert base.driver.state().last_outcome == "aborted" and base.completed(command)
        base.until(base.at_rest, "wheels at rest", 2.0)
        held = base.wheels.pose
        base.clock.sleep(2.0)  # the keep-alive goes on: copies of a finished id change nothing
        assert base.driver.state().mode is DriverMode.ESTOP and base.wheels.pose == held
    finally:
        base.stop()


def test_a_path_command_is_one_kind_and_bounded() -> None:
    with pytest.raises(ValueError, match="one of a discrete action, a velocity or a path"):
        PlanCommand(action_id=1, stamp=0.0, action=Action.MOVE_FORWARD, path=((1.0, 0.0),))
    with pytest.raises(ValueError, match="at most 512 items"):
        PlanCommand(action_id=1, stamp=0.0, path=tuple((0.01 * i, 0.0) for i in range(MAX_PATH_POINTS + 1)))
    with pytest.raises(ValueError, match="at least one waypoint"):
        PathFollower((), DriverConfig())
    for extra in ({"obstacles": ((1.0, 0.0),)}, {"speed_m_s": 0.1}):
        with pytest.raises(ValueError, match="obstacles and a top speed come with a path command only"):
            PlanCommand(action_id=1, stamp=0.0, action=Action.MOVE_FORWARD, **extra)
