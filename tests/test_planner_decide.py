"""Decision steps on hand-made maps: the POMDP weighs distance against belief; greedy does not."""

from __future__ import annotations

import numpy as np
import pytest

from ovamos.services.planner.decide import ActionDistances, DecisionConfig, GoalKind, decide
from ovamos.shared.messages import ObjectInstance
from tests.planner_maps import snapshot


def test_a_near_likely_candidate_beats_a_far_frontier() -> None:
    snap = snapshot({(6.0, 5.0): 0.9}, [(9.5, 9.5)])
    d = decide(snap, (5.0, 5.0), ["cup"], DecisionConfig())
    assert d.kind is GoalKind.CANDIDATE and (d.x, d.y) == pytest.approx((6.0, 5.0), abs=0.1)


def test_weak_scattered_candidates_lose_to_a_near_frontier_but_not_for_greedy() -> None:
    weak = {(1.0, 1.0): 0.3, (9.0, 1.0): 0.3, (1.0, 9.0): 0.3, (9.0, 9.0): 0.32, (5.0, 9.5): 0.3}
    snap = snapshot(weak, [(5.6, 5.0)])
    full = decide(snap, (5.0, 5.0), ["cup"], DecisionConfig())
    assert full.kind is GoalKind.FRONTIER
    greedy = decide(snap, (5.0, 5.0), ["cup"], DecisionConfig(policy="ovamos-greedy"))
    assert greedy.kind is GoalKind.CANDIDATE and (greedy.x, greedy.y) == pytest.approx((9.0, 9.0), abs=0.1)


def test_a_confirmed_object_of_a_remaining_target_wins() -> None:
    cup = ObjectInstance(label="cup", x=2.0, y=3.0, score=0.8, hits=3, confirmed=True)
    snap = snapshot({(6.0, 5.0): 0.9}, [(9.5, 9.5)], objects=[cup])
    assert decide(snap, (5.0, 5.0), ["cup"], DecisionConfig()).kind is GoalKind.OBJECT
    assert decide(snap, (5.0, 5.0), ["bed"], DecisionConfig()).kind is not GoalKind.OBJECT


def test_of_several_confirmed_objects_the_nearest_target_first_each_at_its_best_evidenced_instance() -> None:
    """A repeated task starts with every target confirmed, the last found beside the robot: it goes
    there first, not across the house to what the map confirmed first. Of one target's instances
    it takes the most detected (a look-alike confirmed on a few frames is often nearer; a tie: the
    older); an avoided (unreachable) one gives way to the next."""
    cup = ObjectInstance(label="cup", x=9.0, y=9.0, score=0.9, hits=9, confirmed=True)
    bed = ObjectInstance(label="bed", x=5.5, y=4.0, score=0.7, hits=3, confirmed=True)
    look_alike = ObjectInstance(label="cup", x=3.0, y=5.0, score=0.8, hits=3, confirmed=True)
    twin = ObjectInstance(label="bed", x=2.0, y=2.0, score=0.7, hits=3, confirmed=True)
    snap = snapshot({}, [(1.0, 1.0)], objects=[cup, look_alike, bed, twin])
    cases = [((5.0, 5.0), ["cup", "bed"], None, bed), ((5.0, 5.0), ["cup"], None, cup),
             ((8.0, 8.0), ["cup", "bed"], None, cup), ((1.5, 1.5), ["bed"], None, bed),
             ((5.0, 5.0), ["cup", "bed"], [[5.5, 4.0]], twin), ((5.0, 5.0), ["cup"], [[9.0, 9.0]], look_alike)]
    for robot, remaining, avoid, want in cases:
        d = decide(snap, robot, remaining, DecisionConfig(), avoid=None if avoid is None else np.array(avoid))
        assert d.kind is GoalKind.OBJECT and (d.label, d.x, d.y) == (want.label, want.x, want.y), (robot, remaining)


def test_a_visited_place_blocks_candidates_there_but_not_an_object_confirmed_there() -> None:
    snap = snapshot({(6.0, 5.0): 0.9}, [(9.5, 9.5)])
    there = np.array([[6.1, 5.0]])
    d = decide(snap, (5.0, 5.0), ["cup"], DecisionConfig(), visited=there)
    assert (d.x, d.y) != pytest.approx((6.0, 5.0), abs=0.1)
    cup = ObjectInstance(label="cup", x=6.0, y=5.2, score=0.8, hits=3, confirmed=True)
    with_cup = snapshot({(6.0, 5.0): 0.9}, [(9.5, 9.5)], objects=[cup])
    d = decide(with_cup, (5.0, 5.0), ["cup"], DecisionConfig(), visited=there)
    assert d.kind is GoalKind.OBJECT
    assert decide(with_cup, (5.0, 5.0), ["cup"], DecisionConfig(), avoid=there).kind is not GoalKind.OBJECT


def test_nothing_to_go_to_is_none_and_only_a_frontier_is_the_frontier() -> None:
    assert decide(snapshot({}, []), (5.0, 5.0), ["cup"], DecisionConfig()) is None
    d = decide(snapshot({}, [(1.0, 1.0)]), (5.0, 5.0), ["cup"], DecisionConfig())
    assert d.kind is GoalKind.FRONTIER


def test_path_lengths_go_around_walls() -> None:
    wall = (slice(0, 180), slice(100, 102))  # x = 5.0 .. 5.1, from y = 0 to 9 m
    snap = snapshot({}, [], obstacles=[wall])
    d = ActionDistances(snap, DecisionConfig()).matrix(np.array([[4.0, 1.0], [6.0, 1.0]]))
    assert d[0, 0] == 0 and d[0, 1] == pytest.approx(d[1, 0])
    assert d[0, 1] > 2 * 8.0  # up and over the wall's end at y = 9 m, and back down
    assert np.isfinite(d).all()


def test_decisions_are_deterministic_for_a_seed() -> None:
    weak = {(1.0, 1.0): 0.3, (9.0, 1.0): 0.35, (3.0, 8.0): 0.3}
    snap = snapshot(weak, [(5.6, 7.0)])
    first = decide(snap, (5.0, 5.0), ["cup"], DecisionConfig(seed=3))
    assert decide(snap, (5.0, 5.0), ["cup"], DecisionConfig(seed=3)) == first


def test_baselines_go_to_frontiers_and_vlfm_reads_one_target() -> None:
    snap = snapshot({(6.0, 5.0): 0.9}, [(9.5, 9.5), (1.0, 1.0)])
    for policy in ("finder", "vlfm"):
        d = decide(snap, (5.0, 5.0), ["cup"], DecisionConfig(policy=policy))
        assert d.kind is GoalKind.FRONTIER
    assert decide(snap, (5.0, 5.0), ["cup"], DecisionConfig(policy="random")) is None
    # value only near the (1, 1) frontier, in the cup layer: vlfm searching for "bed" first
    # (no layer) has no preference, finder (all targets) goes to (1, 1)
    near = snapshot({(1.2, 1.2): 0.9}, [(9.5, 9.5), (1.0, 1.0)])
    assert (decide(near, (5.0, 5.0), ["bed", "cup"], DecisionConfig(policy="finder")).x
            == pytest.approx(1.0))
    assert (decide(near, (5.0, 5.0), ["bed", "cup"], DecisionConfig(policy="vlfm")).x
            == pytest.approx(9.5))
    assert (decide(near, (5.0, 5.0), ["cup", "bed"], DecisionConfig(policy="vlfm")).x
            == pytest.approx(1.0))


def test_vlfm_goes_only_to_objects_of_its_current_target() -> None:
    """VLFM is a single-object method run once per target: a confirmed object of a later target
    waits its turn, where finder (multi-object) goes to it at once."""
    cup = ObjectInstance(label="cup", x=2.0, y=3.0, score=0.8, hits=3, confirmed=True)
    snap = snapshot({}, [(9.5, 9.5)], objects=[cup])
    assert decide(snap, (5.0, 5.0), ["bed", "cup"], DecisionConfig(policy="finder")).kind is GoalKind.OBJECT
    vlfm = decide(snap, (5.0, 5.0), ["bed", "cup"], DecisionConfig(policy="vlfm"))
    assert vlfm.kind is GoalKind.FRONTIER
    assert decide(snap, (5.0, 5.0), ["cup", "bed"], DecisionConfig(policy="vlfm")).kind is GoalKind.OBJECT


def test_the_trace_holds_every_option_with_belief_path_and_pouct_statistics() -> None:
    snap = snapshot({(6.0, 5.0): 0.9, (2.0, 8.0): 0.4}, [(9.5, 9.5)])
    d = decide(snap, (5.0, 5.0), ["cup"], DecisionConfig())
    kinds = [o.kind for o in d.options]
    assert kinds.count("frontier") == 1 and kinds.count("candidate") == d.candidates == 2
    candidates = [o for o in d.options if o.kind == "candidate"]
    assert sum(o.belief for o in candidates) == pytest.approx(1.0)
    near = min(candidates, key=lambda o: (o.x - 6.0) ** 2 + (o.y - 5.0) ** 2)
    assert near.path_m == pytest.approx(1.0, abs=0.5)   # 1 m from the robot, open floor
    chosen = next(o for o in d.options if (o.x, o.y) == (d.x, d.y))
    visited = [o for o in d.options if o.visits]
    assert chosen.q == max(o.q for o in visited) and sum(o.visits for o in d.options) > 0
    assert d.reason.startswith("POUCT")
    greedy = decide(snap, (5.0, 5.0), ["cup"], DecisionConfig(policy="ovamos-greedy"))
    assert greedy.reason and all(o.q is None and o.path_m is None for o in greedy.options)
