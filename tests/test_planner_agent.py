"""The search agent's goal keeping on hand-made maps: macro actions, visited candidates, STOP checks."""

from __future__ import annotations

import numpy as np
import pytest

from ovamos.services.mapping.layers import aggregate, decay
from ovamos.services.planner.agent import AgentConfig, Reason, SearchAgent
from ovamos.services.planner.decide import GoalKind
from ovamos.services.planner.task import SearchTask
from ovamos.shared.messages import ObjectInstance
from ovamos.shared.motion import Action, Pose
from tests.planner_maps import snapshot


def agent(**config: object) -> SearchAgent:
    return SearchAgent(SearchTask("t", ["cup"]), AgentConfig(initial_turns=0, **config))


def test_a_candidate_is_kept_until_reached_even_when_a_better_one_appears() -> None:
    a, pose = agent(redecide_every=2), Pose(x=2.0, y=5.0, yaw=0.0)
    first = a.next_step(snapshot({(8.0, 5.0): 0.9}, []), pose)
    assert first.goal.kind is GoalKind.CANDIDATE and (first.goal.x, first.goal.y) == pytest.approx((8.0, 5.0), abs=0.1)
    a.executed(first, 0.25, pose=pose)
    better = snapshot({(8.0, 5.0): 0.2, (2.5, 6.0): 1.0}, [])
    for _ in range(6):  # well past redecide_every
        step = a.next_step(better, pose)
        assert (step.goal.x, step.goal.y) == (first.goal.x, first.goal.y)
        a.executed(step, 0.25, pose=pose)
    assert a.decisions == 1


def test_a_frontier_goal_is_decided_again_every_few_commands() -> None:
    a, pose = agent(redecide_every=2), Pose(x=2.0, y=5.0, yaw=0.0)
    for _ in range(5):
        a.executed(a.next_step(snapshot({}, [(8.0, 5.0)]), pose), 0.25, pose=pose)
    assert a.decisions == 3


def test_a_reached_candidate_is_not_chosen_again() -> None:
    a = agent()
    snap = snapshot({(5.0, 5.0): 0.9}, [(9.0, 9.0)])
    at_candidate = Pose(x=5.0, y=5.0, yaw=0.0)
    step = a.next_step(snap, at_candidate)  # reached at once: the next decision leaves it out
    assert step.goal.kind is GoalKind.FRONTIER
    assert a.visited == [pytest.approx((5.0, 5.0), abs=0.1)]
    a.executed(step, 0.0, pose=at_candidate)
    for _ in range(4):
        step = a.next_step(snap, Pose(x=6.0, y=6.0, yaw=0.0))
        a.executed(step, 0.25)
    assert step.goal.kind is GoalKind.FRONTIER


def test_a_stop_needs_the_object_still_confirmed_on_arrival() -> None:
    cup = ObjectInstance(label="cup", x=5.0, y=5.0, score=0.8, hits=2, confirmed=True)
    near = Pose(x=4.3, y=5.0, yaw=0.0)
    a = agent()
    assert a.next_step(snapshot({}, [(9.0, 9.0)], objects=[cup]), Pose(x=2.0, y=5.0, yaw=0.0)).goal.kind \
        is GoalKind.OBJECT
    # the views on the way in did not show it again: no longer confirmed, so no STOP
    doubtful = cup.model_copy(update={"confirmed": False})
    step = a.next_step(snapshot({}, [(9.0, 9.0)], objects=[doubtful]), near)
    assert step.action is not Action.STOP and step.goal.kind is GoalKind.FRONTIER
    confirmed = agent()
    confirmed.next_step(snapshot({}, [(9.0, 9.0)], objects=[cup]), Pose(x=2.0, y=5.0, yaw=0.0))
    step = confirmed.next_step(snapshot({}, [(9.0, 9.0)], objects=[cup]), near)
    assert step.action is Action.STOP and step.reason is Reason.FOUND


def test_the_decay_is_not_undone_by_normalising() -> None:
    """A layer looked at everywhere many times fades below the candidate threshold (0.05) although
    its shape is unchanged: normalising after the decay would scale it back to a peak of 1."""
    layer = np.array([0.2, 0.4, 0.8], np.float32)
    seen = np.full(3, 14, np.uint16)
    faded = aggregate([layer], [lambda v: decay(v, seen, 6.0, 2.0)])
    assert faded.max() < 0.05
    assert aggregate([layer]) == pytest.approx([0.25, 0.5, 1.0])


def test_bumps_and_unreachable_goals_are_forgotten_after_memory_steps() -> None:
    """A narrow doorway bumped into on both sides would otherwise stay closed for ever, and every
    goal behind it with it (a robot restarted on an older map bumps a lot)."""
    a, pose = agent(memory_steps=3), Pose(x=2.0, y=5.0, yaw=0.0)
    snap = snapshot({}, [(8.0, 5.0)])
    step = a.next_step(snap, pose)
    assert step.action is Action.MOVE_FORWARD
    a.executed(step, 0.0, blocked=True, pose=pose)
    bump = a._nav_map(snap).grid.to_cell(2.0 + a.config.bump_depth_m, 5.0)
    assert a._nav_map(snap).obstacle[bump]
    a._give_up_goal()  # the only frontier, found unreachable: nowhere to go for now
    step = a.next_step(snap, pose)
    assert step.reason is Reason.IDLE
    for _ in range(3):
        a.executed(step, 0.0, pose=pose)
        step = a.next_step(snap, pose)
    assert step.reason is Reason.NAVIGATE and step.goal.kind is GoalKind.FRONTIER
    assert not a._nav_map(snap).obstacle[bump]
