"""A robot boxed in by state carried on the map (obstacles that were not there when it drove in,
bumps, goals remembered as unreachable) recovers and reaches its goal; a failed task says why."""

from __future__ import annotations

import math

import cv2
import numpy as np

from ovamos.services.planner.agent import AgentConfig, BoxedIn, SearchAgent, Step
from ovamos.services.planner.task import SearchTask
from ovamos.services.sim.robot import SimRobot
from ovamos.shared.messages import MapSnapshot, Miss, ObjectInstance, TaskStatus
from ovamos.shared.motion import Pose
from tests.planner_maps import N, snapshot

HOME, FAR = (8.0, 5.0), (2.0, 5.0)


def in_room(x: float, y: float) -> bool:
    """The true free space: the 10 x 10 m room, nothing in it (what is drawn on the map is not)."""
    return 0.3 < x < 9.7 and 0.3 < y < 9.7


def drive(agent: SearchAgent, robot: SimRobot, snap: MapSnapshot, until, steps: int) -> list[Step]:
    """Run the agent on ``snap`` (the map does not change: the test's carried state stays), the
    kinematic robot executing, until ``until(robot.pose)`` or ``steps`` commands."""
    done: list[Step] = []
    while len(done) < steps and not until(robot.pose) and agent.task.state is TaskStatus.SEARCHING:
        pose = robot.pose
        step = agent.next_step(snap, pose)
        if step.action is None:
            break
        before = robot.distance
        blocked = not robot.apply(step.action)
        agent.executed(step, robot.distance - before, blocked, pose)
        done.append(step)
    return done


def near(xy: tuple[float, float], tol: float = 0.3):
    return lambda p: math.hypot(p.x - xy[0], p.y - xy[1]) <= tol


def ringed(snap: MapSnapshot, centre: tuple[float, float], radius_m: float) -> MapSnapshot:
    """``snap`` with a closed ring of obstacles around ``centre`` (people standing round the robot,
    a glitch of the depth camera: what the map keeps once seen)."""
    obstacle = snap.obstacle.copy().astype(np.uint8)
    c = (int(centre[0] / 0.05), int(centre[1] / 0.05))
    cv2.circle(obstacle, c, int(radius_m / 0.05), 1, thickness=2)
    return snap.model_copy(update={"obstacle": obstacle.astype(bool)})


def test_a_robot_walled_in_by_carried_obstacles_recovers_and_reaches_its_goal() -> None:
    agent = SearchAgent(SearchTask("t", ["cup"], max_steps=400), AgentConfig(initial_turns=0))
    robot = SimRobot(Pose(x=HOME[0], y=HOME[1], yaw=math.pi), in_room)
    # it drives in over a clean map to a frontier in the west
    drive(agent, robot, snapshot({}, [FAR]), near(FAR), 100)
    assert near(FAR)(robot.pose) and agent.boxed is None
    # then the map walls it in, and the only goal left is back where it came from
    boxed = ringed(snapshot({}, [HOME]), (robot.pose.x, robot.pose.y), 0.6)
    assert agent.navigator.reachable_share(agent._nav_map(boxed), robot.pose) < 0.05
    seen: list[BoxedIn] = []
    steps = drive(agent, robot, boxed, lambda p: seen.append(agent.boxed) or near(HOME)(p), 200)
    assert near(HOME)(robot.pose), f"still at ({robot.pose.x:.2f}, {robot.pose.y:.2f}) after {len(steps)} steps"
    boxed_states = [b for b in seen if b is not None]
    assert boxed_states and math.hypot(boxed_states[0].x - FAR[0], boxed_states[0].y - FAR[1]) < 0.3
    assert agent.boxed is None  # driving to a goal again ends the state


def test_being_boxed_in_is_a_state_with_a_reason_and_ends_a_failed_task_s_reason() -> None:
    agent = SearchAgent(SearchTask("t", ["cup", "bed"], max_steps=40), AgentConfig(initial_turns=0))
    robot = SimRobot(Pose(x=FAR[0], y=FAR[1], yaw=0.0), lambda x, y: math.hypot(x - FAR[0], y - FAR[1]) < 0.3)
    cup = ObjectInstance(label="cup", x=9.0, y=9.0, score=0.3, hits=3, confirmed=False)
    # walled in from the start: the way it came is no way out (it never drove anywhere)
    boxed = ringed(snapshot({}, [HOME], objects=[cup]), FAR, 0.6)
    conditions = []
    drive(agent, robot, boxed, lambda p: conditions.append(agent.condition) and False, 100)
    assert agent.task.state is TaskStatus.FAILED
    assert any(c.startswith("boxed in near (2.0, 5.0) since step") for c in conditions), conditions
    reason = agent.task.reason
    assert reason.startswith("step limit 40 reached: no reachable frontier or candidate since step 0 "
                             "(boxed in near (2.0, 5.0))"), reason
    assert reason.endswith("cup detected 3 times, never confirmed; bed never seen"), reason
    assert [(m.label, m.stage, m.detections) for m in agent.misses()] == \
        [("cup", Miss.NOT_CONFIRMED, 3), ("bed", Miss.NOT_DETECTED, 0)]


def test_a_confirmed_target_not_reached_is_named_as_such() -> None:
    agent = SearchAgent(SearchTask("t", ["cup"], max_steps=5), AgentConfig(initial_turns=0))
    cup = ObjectInstance(label="cup", x=9.0, y=9.0, score=0.9, hits=4, confirmed=True)
    robot = SimRobot(Pose(x=2.0, y=2.0, yaw=0.0), in_room)
    drive(agent, robot, snapshot({}, [], objects=[cup]), lambda p: False, 10)
    assert agent.task.reason == "step limit 5 reached: cup not reached"
    assert N == 200
