"""ovamos-plus on hand-made maps: several frontiers weighed by path, detections to verify, the goal budget (off by default)."""

from __future__ import annotations

import random

import numpy as np
import pytest

from ovamos.services.planner.agent import AgentConfig, Reason, SearchAgent, Step
from ovamos.services.planner.candidates import Candidates
from ovamos.services.planner.decide import DecisionConfig, GoalKind, decide
from ovamos.services.planner.plus import ManyFrontierPOMDP, PlusConfig, frontier_bonuses, goal_budget
from ovamos.services.planner.pomdp import POMDPConfig
from ovamos.services.planner.task import SearchTask
from ovamos.shared.messages import ObjectInstance
from ovamos.shared.motion import Action, Pose
from tests.planner_maps import snapshot

PLUS = DecisionConfig(policy="ovamos-plus")


def plus(**changes: object) -> DecisionConfig:
    return PLUS.model_copy(update={"plus": PlusConfig(**changes)})


def test_of_two_equally_valued_frontiers_plus_takes_the_near_one_and_the_paper_the_first_best() -> None:
    # the far frontier's surroundings are a hair more valuable: the paper's single best frontier
    snap = snapshot({(9.5, 1.0): 0.21, (5.5, 5.0): 0.2}, [(9.5, 0.5), (6.0, 5.0)])
    no_cands = DecisionConfig().candidates.model_copy(update={"value_threshold": 10.0})
    paper = decide(snap, (5.0, 5.0), ["cup"], DecisionConfig(candidates=no_cands))
    assert paper.kind is GoalKind.FRONTIER and (paper.x, paper.y) == pytest.approx((9.5, 0.5))
    ours = decide(snap, (5.0, 5.0), ["cup"], plus().model_copy(update={"candidates": no_cands}))
    assert ours.kind is GoalKind.FRONTIER and (ours.x, ours.y) == pytest.approx((6.0, 5.0))
    assert [o.kind for o in ours.options] == ["frontier", "frontier"]
    one = decide(snap, (5.0, 5.0), ["cup"], plus(frontiers=1).model_copy(update={"candidates": no_cands}))
    assert (one.x, one.y) == pytest.approx((9.5, 0.5))


def test_frontier_bonuses_follow_value_with_a_floor() -> None:
    cands = Candidates(np.array([[1.0, 1.0]]), np.array([0.8]), np.array([1.0]))
    bonus = frontier_bonuses(np.array([0.4, 0.0, 0.8]), cands, PlusConfig(frontier_floor=0.25), 500.0)
    assert bonus.tolist() == pytest.approx([250.0, 125.0, 500.0])
    assert frontier_bonuses(np.array([0.0]), Candidates(np.zeros((0, 2)), np.zeros(0), np.zeros(0)),
                            PlusConfig(), 500.0).tolist() == [500.0]


def test_the_many_frontier_model_ends_at_a_frontier_with_its_own_bonus() -> None:
    d = np.array([[0.0, 2.0, 1.0, 4.0], [2.0, 0.0, 3.0, 5.0], [1.0, 3.0, 0.0, 5.0], [4.0, 5.0, 5.0, 0.0]])
    model = ManyFrontierPOMDP(d, [1], None, POMDPConfig(), frontier_rewards={2: 100.0, 3: 400.0})
    assert list(model.actions((0, 1))) == [1, 2, 3]
    assert model.step((0, 1), 3, random.Random(0)) == ((3, 1), 0, 400.0 - 20.0 * 4.0, True)
    assert model.step((0, 1), 1, random.Random(0))[1:] == (1, 500.0 - 40.0, True)  # the target, as the paper's


def test_an_unconfirmed_detection_of_a_remaining_target_is_a_candidate_for_plus_only() -> None:
    seen_once = ObjectInstance(label="cup", x=8.0, y=8.0, score=0.5, hits=1, views=1, confirmed=False)
    other = ObjectInstance(label="bed", x=2.0, y=8.0, score=0.5, hits=1, views=1, confirmed=False)
    snap = snapshot({(6.0, 5.0): 0.3}, [], objects=[seen_once, other])
    paper = decide(snap, (5.0, 5.0), ["cup"], DecisionConfig())
    assert [(o.x, o.y) for o in paper.options] == [pytest.approx((6.0, 5.0), abs=0.1)]
    ours = decide(snap, (5.0, 5.0), ["cup"], plus())
    points = [(o.x, o.y) for o in ours.options if o.kind == "candidate"]
    assert (8.0, 8.0) in points and (2.0, 8.0) not in points and len(points) == 2
    assert decide(snap, (5.0, 5.0), ["cup"], plus(verify_detections=False)).options == paper.options
    visited = decide(snap, (5.0, 5.0), ["cup"], plus(), visited=np.array([[8.0, 8.1]]))
    assert (8.0, 8.0) not in [(o.x, o.y) for o in visited.options]


def test_a_goal_is_given_up_after_its_budget_even_across_redecisions() -> None:
    assert goal_budget(2.0, PlusConfig(goal_commands_min=10, goal_commands_per_m=3.0)) == 16
    assert goal_budget(2.0, PlusConfig(goal_commands_per_m=None)) is None
    config = AgentConfig(initial_turns=0, redecide_every=2, stuck_steps=100,
                         decision=plus(goal_commands_min=6, goal_commands_per_m=1.0))
    agent = SearchAgent(SearchTask("t", ["cup"]), config)
    snap, pose = snapshot({}, [(9.0, 5.0)]), Pose(x=2.0, y=5.0, yaw=0.0)  # 7 m: 13 commands (stuck: off)
    goals = []
    for _ in range(14):  # the robot never moves: every command leaves it where it was
        step = agent.next_step(snap, pose)
        goals.append(step.goal)
        assert step.action is not None
        agent.executed(step, 0.0, pose=pose)
    assert agent.decisions > 2  # re-decided every 2 commands, the same goal each time
    assert all((g.x, g.y) == (9.0, 5.0) for g in goals[:13])
    assert goals[13] is None and agent.unreachable.points(agent.task.steps) == [(9.0, 5.0)]
    paper = SearchAgent(SearchTask("t", ["cup"]), AgentConfig(initial_turns=0, redecide_every=2, stuck_steps=100))
    for _ in range(14):
        step = paper.next_step(snap, pose)
        paper.executed(step, 0.0, pose=pose)
    assert step.action is Action.MOVE_FORWARD and (step.goal.x, step.goal.y) == (9.0, 5.0)



def cup(hits: int, views: int, confirmed: bool = True, x: float = 5.5, y: float = 5.0) -> ObjectInstance:
    """A cup the map confirmed (by its rule: 2 hits in 30 % of the views) or not."""
    return ObjectInstance(label="cup", x=x, y=y, score=0.45, hits=hits, views=views, confirmed=confirmed)


def first_step(decision: DecisionConfig, obj: ObjectInstance) -> Step:
    """The first step of an agent at (5, 5) whose map holds ``obj`` and a weak value peak at (6, 5)."""
    agent = SearchAgent(SearchTask("t", ["cup"]), AgentConfig(initial_turns=0, decision=decision))
    return agent.next_step(snapshot({(6.0, 5.0): 0.3}, [], objects=[obj]), Pose(x=5.0, y=5.0, yaw=0.0))


STRICT = plus(strict_stop=True)


def test_a_strict_plus_stops_only_at_an_instance_detected_often_and_in_most_of_its_views() -> None:
    few = cup(hits=2, views=3)
    assert first_step(DecisionConfig(), few).action is Action.STOP
    assert first_step(PLUS, few).action is Action.STOP  # strict_stop is off by default
    ours = first_step(STRICT, few)
    assert ours.action is not Action.STOP and (ours.goal.x, ours.goal.y) == (5.5, 5.0)  # to verify: look again
    assert first_step(STRICT, cup(hits=3, views=7)).action is not Action.STOP  # 43 % < 50 %
    assert first_step(STRICT, cup(hits=4, views=7)).action is Action.STOP


def test_a_strict_plus_leaves_alone_an_instance_seen_often_and_rarely_detected() -> None:
    assert first_step(DecisionConfig(), cup(hits=3, views=8, x=8.0, y=8.0)).goal.kind is GoalKind.OBJECT
    verify = first_step(STRICT, cup(hits=3, views=7, x=8.0, y=8.0)).goal  # too few views to call it false
    assert verify.kind is GoalKind.CANDIDATE and (8.0, 8.0) in [(o.x, o.y) for o in verify.options]
    rejected = first_step(STRICT, cup(hits=3, views=8, x=8.0, y=8.0)).goal
    assert rejected.kind is GoalKind.CANDIDATE and (8.0, 8.0) not in [(o.x, o.y) for o in rejected.options]


LOOK = plus(look_before_stop=3)


def looking_agent() -> SearchAgent:
    return SearchAgent(SearchTask("t", ["cup"]), AgentConfig(initial_turns=0, decision=LOOK))


def test_a_looking_plus_faces_the_object_and_stops_once_it_is_detected_again() -> None:
    agent, snap = looking_agent(), snapshot({}, [(9.0, 9.0)], objects=[cup(hits=2, views=3)])
    back_to_it = Pose(x=5.0, y=5.0, yaw=np.pi * 0.75)  # the cup at (5.5, 5) is behind, to the right
    step = agent.next_step(snap, back_to_it)
    assert step.action is Action.TURN_RIGHT and step.reason is Reason.CHECK and step.goal.kind is GoalKind.OBJECT
    agent.executed(step, 0.0, pose=back_to_it)
    facing = Pose(x=5.0, y=5.0, yaw=0.1)
    step = agent.next_step(snap, facing)  # facing it, no new hit yet: swing off for another view
    assert step.action is Action.TURN_LEFT and step.reason is Reason.CHECK
    agent.executed(step, 0.0, pose=facing)
    seen_again = snapshot({}, [(9.0, 9.0)], objects=[cup(hits=3, views=5)])
    step = agent.next_step(seen_again, facing)
    assert step.action is Action.STOP and step.reason is Reason.FOUND


def test_a_looking_plus_leaves_alone_an_object_seen_again_from_close_by_without_a_detection() -> None:
    agent, facing = looking_agent(), Pose(x=5.0, y=5.0, yaw=0.0)
    for views in (3, 4):  # the views of its place grow, its hits do not
        step = agent.next_step(snapshot({}, [(9.0, 9.0)], objects=[cup(hits=2, views=views)]), facing)
        assert step.reason is Reason.CHECK
        agent.executed(step, 0.0, pose=facing)
    snap = snapshot({}, [(9.0, 9.0)], objects=[cup(hits=2, views=5)])
    step = agent.next_step(snap, facing)  # two views from close by, no new hit: not the cup
    assert step.action is not Action.STOP and step.goal.kind is GoalKind.FRONTIER
    assert agent.rejected == [(5.5, 5.0)]
    agent.executed(step, 0.25, pose=facing)
    for _ in range(5):  # still confirmed on the map, but not chosen again
        step = agent.next_step(snap, facing)
        assert step.goal.kind is GoalKind.FRONTIER
        agent.executed(step, 0.25, pose=facing)


def test_a_looking_plus_stops_when_its_turns_add_no_view() -> None:
    """Too close to see it (under the depth camera's range, above its view): the look is no evidence."""
    agent, facing = looking_agent(), Pose(x=5.0, y=5.0, yaw=0.0)
    snap = snapshot({}, [(9.0, 9.0)], objects=[cup(hits=2, views=3)])
    for _ in range(3):
        step = agent.next_step(snap, facing)
        assert step.reason is Reason.CHECK
        agent.executed(step, 0.0, pose=facing)
    step = agent.next_step(snap, facing)
    assert step.action is Action.STOP and step.reason is Reason.FOUND and agent.rejected == []


def test_only_plus_looks_before_a_stop() -> None:
    paper = DecisionConfig().model_copy(update={"plus": PlusConfig(look_before_stop=3)})
    assert first_step(paper, cup(hits=2, views=3)).action is Action.STOP
    assert first_step(LOOK, cup(hits=2, views=3)).reason is Reason.CHECK
