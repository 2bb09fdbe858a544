"""Continuous motion in the planner's protocol, message by message: a navigation step goes out as a
path, kept alive while the driver runs it and decided on again every ``decide_every_s`` (or at
once when a target is confirmed, or at the object the path goes to) without waiting for the robot
to stop, or when the path ahead is walled off or a much better frontier appears); every other step
stays a primitive; a path being backed off from a bump is waited for; a path names the mapped
obstacles near it."""

from __future__ import annotations

import math

import numpy as np
import pytest

from ovamos.services.planner.agent import AgentConfig
from ovamos.services.planner.continuous import PathWatch, _gaps, _sampled, obstacles_near
from ovamos.services.planner.executive import BLIND, Executive, ExecutiveConfig
from ovamos.shared.grid import GridGeometry
from ovamos.shared.gridpaths import traversable
from ovamos.shared.messages import MAX_PATH_OBSTACLES, DriverState, MapSnapshot, ObjectInstance, PlanCommand
from ovamos.shared.motion import Action, Pose
from ovamos.shared.robot import ROBOT
from tests.test_base_driver_follow import BASES, Base, _speeds
from tests.test_planner_executive import commands, driver, odom, snapshot, spec


def scanned(every_s: float = 1.0, careful: int = 5, careful_path_m: float = 0.5) -> tuple[Executive, float]:
    """A continuous executive past its one-turn look-around, its first path just sent; the time."""
    ex = Executive(ExecutiveConfig(agent=AgentConfig(initial_turns=1, motion="continuous", decide_every_s=every_s,
                                                     careful_steps=careful, careful_path_m=careful_path_m),
                                   resend_s=0.3))
    ex.on_task(spec())
    ex.on_driver(driver())
    ex.on_snapshot(snapshot(0))
    ex.on_odom(odom())
    [turn] = commands(ex.poll(0.0))
    assert turn.action is Action.TURN_LEFT and not turn.path  # the look-around: primitives
    ex.on_driver(driver(completed=1, outcome="done"))
    ex.on_odom(odom(yaw=0.5, after=1))
    ex.on_snapshot(snapshot(1))
    [path] = commands(ex.poll(0.1))
    assert path.action is None and len(path.path) >= 1
    return ex, 0.1


def test_a_navigation_step_goes_out_as_the_navigators_path_to_the_goal() -> None:
    ex, _ = scanned()
    [command] = commands([ex.in_flight.command])  # type: ignore[union-attr]
    goal = ex.agent.goal  # type: ignore[union-attr]
    end = command.path[-1]
    assert goal is not None and abs(end[0] - goal.x) < 0.3 and abs(end[1] - goal.y) < 0.3
    assert ex.task.steps == 1  # type: ignore[union-attr]  # the turn; the path is booked when decided on again


def test_the_path_is_kept_alive_then_decided_on_again_while_the_robot_drives() -> None:
    ex, t = scanned(every_s=1.0)
    first = ex.in_flight.command  # type: ignore[union-attr]
    ex.on_driver(driver(completed=1, active=first.action_id, outcome="done"))
    resent = commands(ex.poll(t + 0.35))
    assert resent == [first]  # the keep-alive: the same id
    ex.on_odom(odom(x=1.2, yaw=0.5, after=1))
    ex.on_snapshot(snapshot(2, after=1))  # the robot still moving: no frame after a completion
    assert commands(ex.poll(t + 0.6)) == []  # not yet due (nor a keep-alive)
    [second] = commands(ex.poll(t + 1.05))
    assert second.action_id == first.action_id + 1 and second.path
    assert ex.task.steps == 2 and ex.task.distance == pytest.approx(0.2)  # type: ignore[union-attr]


def test_a_path_due_on_a_map_that_fused_no_frame_since_is_left_to_stop_and_the_next_waits_for_one(
        caplog: pytest.LogCaptureFixture) -> None:
    """A camera that stopped, or takes a frame only after each command (lock-stepped): the period
    comes with nothing new on the map. Deciding again would send the robot on blind, so the
    keep-alive stops (the driver's deadman ends the path), the planner says why, and the next
    decision waits for a frame taken after the path; then it goes on. Logged once a task."""
    caplog.set_level("WARNING", logger="ovamos.planner")
    ex, t = scanned(every_s=1.0)
    first = ex.in_flight.command  # type: ignore[union-attr]
    ex.on_driver(driver(completed=1, active=first.action_id, outcome="done"))
    assert commands(ex.poll(t + 0.35)) == [first]  # kept alive while it is not due
    ex.on_odom(odom(x=1.2, yaw=0.5, after=1))
    for now in (t + 1.05, t + 1.4, t + 2.0):  # due, but the map is the decision's: no command at all
        assert commands(ex.poll(now)) == []
    assert ex.waiting == BLIND and ex.blind_stops == 1
    assert caplog.text.count("has fused no frame since the path was decided") == 1
    ex.on_driver(driver(completed=first.action_id, outcome="aborted"))  # the deadman
    ex.on_odom(odom(x=1.25, yaw=0.5, after=first.action_id))
    assert commands(ex.poll(t + 2.1)) == []
    assert ex.waiting == f"waiting for the map to fuse a frame taken after command {first.action_id}"
    ex.on_snapshot(snapshot(2, after=first.action_id))  # the frame a lock-stepped camera takes now
    [second] = commands(ex.poll(t + 2.2))
    assert second.action_id == first.action_id + 1 and second.path and ex.waiting == ""
    ex.on_driver(driver(completed=first.action_id, active=second.action_id, outcome="aborted"))
    assert commands(ex.poll(t + 3.3)) == [] and ex.blind_stops == 2  # the same again, not logged again
    assert caplog.text.count("has fused no frame since the path was decided") == 1


def test_a_target_confirmed_on_the_way_is_decided_on_at_once() -> None:
    ex, t = scanned(every_s=10.0)
    first = ex.in_flight.command  # type: ignore[union-attr]
    ex.on_driver(driver(completed=1, active=first.action_id, outcome="done"))
    cup = ObjectInstance(label="cup", x=4.0, y=4.0, score=0.9, hits=3, views=3, confirmed=True)
    ex.on_snapshot(snapshot(2, objects=(cup,), after=1))
    [second] = commands(ex.poll(t + 0.2))
    goal = ex.agent.goal  # type: ignore[union-attr]
    assert second.action_id == first.action_id + 1 and goal is not None and goal.label == "cup"


def bumped(careful: int = 5, careful_path_m: float = 0.5) -> tuple[Executive, PlanCommand]:
    """A continuous executive whose first path was blocked (the driver backing off, then reporting
    it), and the command it sent next."""
    ex, t = scanned(every_s=0.5, careful=careful, careful_path_m=careful_path_m)
    first = ex.in_flight.command  # type: ignore[union-attr]
    backing = DriverState(**{**driver(completed=1, active=first.action_id, outcome="done").model_dump(),
                             "backing_off": True})
    ex.on_driver(backing)
    ex.on_snapshot(snapshot(2, after=1))
    assert commands(ex.poll(t + 1.0)) == [first]  # due by the clock, but its outcome is coming: kept alive
    ex.on_driver(driver(completed=first.action_id, outcome="blocked"))
    ex.on_odom(odom(x=1.1, yaw=0.5, after=first.action_id))
    ex.on_snapshot(snapshot(3, after=first.action_id))
    [second] = commands(ex.poll(t + 1.1))
    assert second.action_id == first.action_id + 1
    assert ex.agent.bumps.points(ex.task.steps)  # type: ignore[union-attr]  # the bump was marked
    return ex, second


@pytest.mark.parametrize(("careful", "careful_path_m", "sent"),
                         [(0, 0.5, "path"), (5, 0.5, "careful path"), (5, 0.0, "primitive")])
def test_a_path_backing_off_from_a_bump_is_waited_for_and_booked_blocked(careful: int, careful_path_m: float,
                                                                           sent: str) -> None:
    """Then, within ``careful_steps`` of the bump, the way on is a careful path: at most
    ``careful_path_m`` long, no faster than ``careful_m_s``, the bump named first; with careful paths
    off, primitives, each checked on the map with the bump in it."""
    ex, second = bumped(careful, careful_path_m)
    config = ex.config.agent
    [bump] = ex.agent.bumps.points(ex.task.steps)  # type: ignore[union-attr]
    if sent == "primitive":
        assert second.action is not None and not second.path
        return
    assert second.path and second.action is None
    if sent == "path":
        assert second.speed_m_s is None and bump not in second.obstacles
        return
    assert second.speed_m_s == config.careful_m_s and second.obstacles[0] == pytest.approx(bump, abs=1e-3)
    here = np.array(second.path)
    assert here[0] == pytest.approx((1.1, 1.0))  # from where the robot stands
    assert np.hypot(*np.diff(here, axis=0).T).sum() <= config.careful_path_m + 1e-3  # (rounded to 0.1 mm)


@pytest.mark.parametrize("base_name", BASES)
def test_the_careful_path_after_a_bump_never_touches_the_obstacle_it_was_told_of(base_name: str) -> None:
    """The robot backed off a bump that nothing on the map shows; the goal lies past it, so the straight
    way on would drive the footprint over the bumped point. The careful path the planner sends, followed
    by the real controller on each simulated base (whose collision check is that point), goes round it:
    no contact, the footprint kept off it, no faster than ``careful_m_s``."""
    ex, command = bumped()
    config = ex.config.agent
    [(bx, by)] = ex.agent.bumps.points(ex.task.steps)  # type: ignore[union-attr]
    goal = ex.agent.goal  # type: ignore[union-attr]
    assert goal is not None and command.speed_m_s is not None
    straight = np.array([[1.1, 1.0], [goal.x, goal.y]])
    assert _gaps(np.array([[bx, by]]), _sampled(straight, 0.01)).min() < ROBOT.radius_m  # the way it would touch

    def is_free(x: float, y: float) -> bool:
        return math.hypot(x - bx, y - by) > ROBOT.radius_m
    base = Base(base_name, is_free, Pose(x=1.1, y=1.0, yaw=0.5))
    try:
        sent = base.send(command.path, command.obstacles, command.speed_m_s)
        base.until(lambda: base.completed(sent), "the careful path done")
        assert base.driver.state().last_outcome == "done" and base.driver.counters["bumps"] == 0
        gaps = [math.hypot(p.x - bx, p.y - by) for _, p in base.trace]
        assert min(gaps) >= ROBOT.radius_m + config.careful_clearance_m - 0.05  # half a cell and tracking
        assert max(_speeds(base.trace, -math.inf, math.inf, ticks=5)) <= config.careful_m_s + 0.01
    finally:
        base.stop()


def test_a_look_around_is_decided_turn_by_turn_ahead_of_each_turns_end_and_what_follows_waits_for_it() -> None:
    """Each turn's next step is decided while the turn runs (the driver chains a turn the same way
    onto it); the first path after the look-around is decided as the last turn runs, and sent when
    it ends."""
    ex = Executive(ExecutiveConfig(agent=AgentConfig(initial_turns=3, motion="continuous", turn_ahead_deg=15.0)))
    ex.on_task(spec())
    ex.on_driver(driver())
    ex.on_snapshot(snapshot(0))
    ex.on_odom(odom())
    [first] = commands(ex.poll(0.0))
    assert first.action is Action.TURN_LEFT
    ex.on_driver(driver(active=1))
    ex.on_odom(odom(yaw=math.radians(10)))
    ex.on_snapshot(snapshot(1, after=0))
    assert commands(ex.poll(0.2)) == []  # 20 degrees to go: not yet
    ex.on_odom(odom(yaw=math.radians(20)))
    [second] = commands(ex.poll(0.4))
    assert second.action is Action.TURN_LEFT and ex.task.steps == 1  # type: ignore[union-attr]
    ex.on_driver(driver(completed=1, outcome="done", active=2))  # chained: the first is done, the robot turning on
    ex.on_odom(odom(yaw=math.radians(50), after=1))  # decided for 30 degrees, not for where it stood (20)
    assert commands(ex.poll(0.5)) == []  # 10 degrees to go, but no map newer than the decision's
    ex.on_snapshot(snapshot(3, after=1))
    [third] = commands(ex.poll(0.6))
    assert third.action is Action.TURN_LEFT and ex.in_flight.pose.yaw == pytest.approx(math.radians(60))  # type: ignore[union-attr]
    ex.on_driver(driver(completed=2, outcome="done", active=3))
    ex.on_odom(odom(yaw=math.radians(80), after=2))
    ex.on_snapshot(snapshot(4, after=2))
    assert commands(ex.poll(0.8)) == []  # the path after the look-around is decided, held for the turn's end
    assert ex.task.steps == 3 and ex.in_flight.after == 3  # type: ignore[union-attr]
    assert commands(ex.poll(1.5)) == []  # no keep-alive of what was not sent
    ex.on_driver(driver(completed=3, outcome="done"))
    [path] = commands(ex.poll(1.6))
    assert path.path and path.action_id == 4


def test_stepwise_sends_primitives_only() -> None:
    ex = Executive(ExecutiveConfig(agent=AgentConfig(initial_turns=0)))
    ex.on_task(spec())
    ex.on_driver(driver())
    ex.on_snapshot(snapshot(0))
    ex.on_odom(odom())
    [command] = commands(ex.poll(0.0))
    assert command.action is not None and not command.path


def _wall(snap: MapSnapshot, cells: tuple[slice, slice]) -> MapSnapshot:
    """``snap`` with obstacle cells at ``cells`` (rows, cols), explored."""
    obstacle = snap.obstacle.copy()
    obstacle[cells] = True
    return snap.model_copy(update={"obstacle": obstacle})


def test_a_path_walled_off_by_the_newest_map_is_decided_on_at_once_and_the_new_one_goes_round(
        caplog: pytest.LogCaptureFixture) -> None:
    """The first path runs (1, 1) -> (5, 5) over an empty map; a wall seen across it (x = 3, y 2-4)
    makes the next decision come before the period (logged with why), and the new path goes round
    the wall. A wall as long seen off the path (x = 5.5) changes nothing."""
    caplog.set_level("INFO", logger="ovamos.planner")
    ex, t = scanned(every_s=10.0)
    first = ex.in_flight.command  # type: ignore[union-attr]
    ex.on_driver(driver(completed=1, active=first.action_id, outcome="done"))
    ex.on_snapshot(_wall(snapshot(2, after=1), (slice(10, 30), slice(110, 114))))  # x 5.5-5.7, y 0.5-1.5
    assert commands(ex.poll(t + 0.2)) == []  # not on the path: keep following
    wall = (slice(40, 80), slice(58, 62))  # x 2.9-3.1, y 2-4
    ex.on_snapshot(_wall(snapshot(3, after=1), wall))
    [second] = commands(ex.poll(t + 0.4))
    assert second.action_id == first.action_id + 1 and second.path
    assert f"path of command {first.action_id} decided on again: the path walled off" in caplog.text
    xs, ys = zip(*[(x, y) for x, y in [(1.0, 1.0), *second.path]])
    crossings = [(x0, y0, x1, y1) for x0, y0, x1, y1 in zip(xs, ys, xs[1:], ys[1:]) if min(x0, x1) < 3.0 < max(x0, x1)]
    for x0, y0, x1, y1 in crossings:  # where the new path crosses x = 3, it is clear of the wall
        y = y0 + (3.0 - x0) * (y1 - y0) / (x1 - x0)
        assert not 1.85 < y < 4.15
    assert second.obstacles  # the wall near the new path goes with it
    assert all(2.5 < x < 3.5 and 1.5 < y < 4.5 for x, y in second.obstacles)


def test_a_much_better_frontier_is_decided_on_at_once() -> None:
    """Going to the frontier (5, 5) of a map without values, a frontier at (1, 5) whose
    surroundings now score high (the cup's layer) is decided on before the period; the same map
    again (a later frame, nothing new) is not."""
    ex, t = scanned(every_s=10.0)
    first = ex.in_flight.command  # type: ignore[union-attr]
    assert ex.agent.goal is not None and ex.agent.goal.kind.value == "frontier"  # type: ignore[union-attr]
    ex.on_driver(driver(completed=1, active=first.action_id, outcome="done"))
    ex.on_snapshot(snapshot(2, after=1))
    assert commands(ex.poll(t + 0.2)) == []
    richer = snapshot(3, after=1)
    values = richer.values.copy()
    values[0, 95:105, 15:25] = 0.8  # the cup's layer, around (1, 5)
    ex.on_snapshot(richer.model_copy(update={"values": values, "frontiers": np.array([[5.0, 5.0], [1.0, 5.0]])}))
    [second] = commands(ex.poll(t + 0.4))
    assert second.action_id == first.action_id + 1


def test_the_obstacles_near_a_path_are_those_within_reach_nearest_first() -> None:
    snap = _wall(_wall(snapshot(0), (slice(58, 62), slice(20, 100))), (slice(0, 4), slice(0, 120)))
    # a wall along y = 3 (x 1-5) 0.1 m from the path, one along y = 0 (1 m away)
    near = obstacles_near(snap, [(1.0, 2.9), (5.0, 2.9)], Pose(x=0.8, y=2.9, yaw=0.0), 0.5)
    assert near and all(2.85 < y < 3.15 and 0.3 < x < 5.6 for x, y in near)
    d = [math.hypot(x - 0.8, y - 2.9) for x, y in near]
    assert d == sorted(d)
    assert obstacles_near(snap, [(1.0, 2.9), (5.0, 2.9)], Pose(x=0.8, y=2.9, yaw=0.0), 0.0) == ()
    long = _wall(snapshot(0), (slice(0, 120), slice(0, 120)))  # everything an obstacle: capped
    assert len(obstacles_near(long, [(0.5, 0.5), (5.5, 5.5)], Pose(x=0.5, y=0.5, yaw=0.0), 0.5)) == MAX_PATH_OBSTACLES


def test_a_path_watch_counts_only_what_is_newly_blocked_ahead() -> None:
    """A robot that starts beside a wall (inside the navigator's radius of it: it drives out along
    the path) is not walled off by that wall; an obstacle seen since ahead of it is, and one behind
    it is not."""
    beside = _wall(snapshot(0), (slice(16, 18), slice(18, 22)))  # y 0.8-0.9, by the start (1, 1)
    path, radius = [(3.0, 1.0), (5.0, 1.0)], 0.15
    watch = PathWatch.start(path, Pose(x=1.0, y=1.0, yaw=0.0), beside, radius)
    assert not watch.clear.all()
    assert not watch.walled_off(beside, Pose(x=1.0, y=1.0, yaw=0.0), radius)
    ahead = _wall(beside, (slice(19, 21), slice(79, 81)))  # on the path at x = 4
    assert watch.walled_off(ahead, Pose(x=1.5, y=1.0, yaw=0.0), radius)
    assert not watch.walled_off(ahead, Pose(x=4.5, y=1.0, yaw=0.0), radius)  # already past it


@pytest.mark.parametrize("radius", [0.15, 0.18, 0.3])
def test_a_path_watch_calls_clear_exactly_where_the_navigator_may_plan(radius: float) -> None:
    """The watch's footprint is the navigator's (``shared.grid.disc``): a sample is clear just
    where ``traversable`` lets a plan go, on a map of scattered obstacles."""
    rng = np.random.default_rng(7)
    snap = snapshot(0)
    snap = snap.model_copy(update={"obstacle": rng.random(snap.obstacle.shape) < 0.02})
    path = [(float(x), float(y)) for x, y in rng.uniform(0.5, 5.5, (12, 2))]
    watch = PathWatch.start(path, Pose(x=1.0, y=1.0, yaw=0.0), snap, radius)
    rows, cols = np.floor(watch.samples[:, ::-1] / snap.resolution).astype(int).T
    free = traversable(snap.obstacle, snap.explored, snap.resolution, radius)
    assert 0 < watch.clear.sum() < len(watch.clear)
    assert (watch.clear == free[rows, cols]).all()


def test_a_band_reaches_one_cell_past_its_half_width_either_side_of_the_polyline() -> None:
    grid = GridGeometry(0.05, 0.0, 0.0, 40, 60)  # 3 m x 2 m
    band = grid.band(np.array([[0.5, 1.0], [2.5, 1.0], [2.5, 1.9]]), 2)
    rows, cols = np.nonzero(band)
    assert band[20, 10] and band[20, 50] and band[38, 50]  # the vertices' cells
    assert list(np.nonzero(band[:, 30])[0]) == [17, 18, 19, 20, 21, 22, 23]
    assert list(np.nonzero(band[30, :])[0]) == [47, 48, 49, 50, 51, 52, 53]
    assert not band[30, 20] and rows.min() == 17 and cols.min() == 7 and cols.max() == 53


def test_a_localized_map_is_planned_in_and_the_path_goes_to_the_base_in_its_odometry_frame() -> None:
    """With ``map_T_odom`` (localization's correction) the robot is where the map has it: its
    odometry placed in the map; the path is decided there and sent back in the odometry frame,
    where the base follows it."""
    shift = Pose(x=0.4, y=-0.3, yaw=0.2)
    ex = Executive(ExecutiveConfig(agent=AgentConfig(initial_turns=0, motion="continuous"), resend_s=0.3))
    ex.on_task(spec())
    ex.on_driver(driver())
    ex.on_snapshot(snapshot(0).model_copy(update={"map_T_odom": shift}))
    ex.on_odom(odom(x=1.0, y=1.5))
    [path] = commands(ex.poll(0.0))
    in_map = shift.compose(Pose(x=1.0, y=1.5))
    assert ex.in_flight is not None and ex.in_flight.pose == in_map  # decided where the map has the robot
    event = ex.event()
    assert (event.x, event.y) == (in_map.x, in_map.y)  # and reported there
    goal = ex.agent.goal  # type: ignore[union-attr]
    assert goal is not None
    end_in_map = shift.apply(*path.path[-1])  # the base's last waypoint, placed in the map
    assert abs(end_in_map[0] - goal.x) < 0.3 and abs(end_in_map[1] - goal.y) < 0.3
    end = path.path[-1]
    assert math.hypot(end[0] - goal.x, end[1] - goal.y) > 0.3  # as sent it is not in the map's frame
