"""Planner benchmark: POUCT simulations per second and decision latency.

A decision is what the planner does per step: candidates from the value map
(DBSCAN), the best frontier, path lengths between the robot and all action
points, and POUCT (500 simulations, depth 5). Instances are synthetic but
map-sized: a 15 x 15 m explored area with scattered obstacles on the default
1000 x 1000 grid, K value blobs (K = 5, 10, 20) and three frontiers, seeded; the paper's
decision and ovamos-plus's (all three frontiers as actions, services/planner/plus.py).
Simulations per second are also measured with pomdp_py's POUCT on the same
search POMDP when pomdp-py is installed (a benchmark-only dependency).
"""

from __future__ import annotations

import random
import statistics
import time
from typing import Any

import numpy as np
from rich.console import Console
from rich.table import Table

from ovamos.services.planner.decide import ActionDistances, DecisionConfig, decide
from ovamos.services.planner.policies import OVAMOS_PLUS
from ovamos.services.planner.pomdp import SearchPOMDP, root_particles
from ovamos.services.planner.pouct import POUCT
from ovamos.shared.messages import MapSnapshot

CANDIDATE_COUNTS = (5, 10, 20)
GRID = 1000
RES = 0.05


def instance(k: int, seed: int) -> tuple[MapSnapshot, tuple[float, float]]:
    rng = np.random.default_rng([seed, k])
    lo, hi = GRID // 2 - 150, GRID // 2 + 150  # 15 m square around the centre
    explored = np.zeros((GRID, GRID), bool)
    explored[lo:hi, lo:hi] = True
    obstacle = np.zeros((GRID, GRID), bool)
    for _ in range(25):
        r, c = rng.integers(lo, hi - 20, 2)
        obstacle[r:r + rng.integers(4, 20), c:c + rng.integers(4, 20)] = True
    values = np.zeros((GRID, GRID), np.float32)
    for _ in range(k):
        r, c = rng.integers(lo + 5, hi - 5, 2)
        values[r - 2:r + 3, c - 2:c + 3] = rng.uniform(0.1, 1.0)
    origin = -GRID * RES / 2
    frontiers = origin + (np.array([[lo, lo], [hi - 1, lo], [lo, hi - 1]]) + 0.5) * RES
    snap = MapSnapshot(seq=0, stamp=0.0, resolution=RES, origin=(origin, origin), layers=("t",),
                       obstacle=obstacle, explored=explored, counts=np.zeros((1, GRID, GRID), np.uint16),
                       values=values[None], frontiers=frontiers)
    return snap, (0.0, 0.0)


def _search_pomdp(k: int, config: DecisionConfig) -> tuple[SearchPOMDP, list[tuple[int, int]]]:
    snap, robot = instance(k, seed=0)
    from ovamos.services.planner.candidates import find_candidates
    from ovamos.shared.grid import GridGeometry
    grid = GridGeometry(RES, snap.origin[0], snap.origin[1], GRID, GRID)
    cands = find_candidates(snap.values[0], grid, config.candidates)
    points = np.vstack([np.array([robot]), cands.points, snap.frontiers[:1]])
    dist = ActionDistances(snap, config, include=points).matrix(points)
    model = SearchPOMDP(np.where(np.isfinite(dist), dist, 1e6), list(range(1, len(cands.points) + 1)),
                        len(points) - 1, config.pomdp)
    return model, root_particles(model.candidates, cands.belief, config.pomdp.particles, 0)


def ours_sims_per_s(model: SearchPOMDP, particles: list[tuple[int, int]], sims: int) -> float:
    c = model.config
    planner = POUCT(model, num_sims=sims, max_depth=c.max_depth, discount=c.gamma,
                    exploration=c.exploration, seed=0)
    planner.plan(particles)
    return planner.sims_per_s


def pomdp_py_sims_per_s(model: SearchPOMDP, particles: list[tuple[int, int]], sims: int) -> float | None:
    """The same POMDP through pomdp_py's POUCT (None when pomdp-py is not installed)."""
    try:
        import pomdp_py
    except ImportError:
        return None

    class St(pomdp_py.State):
        def __init__(self, robot: int, target: int, done: bool = False) -> None:
            self.robot, self.target, self.done = robot, target, done

        def __hash__(self) -> int:
            return hash((self.robot, self.target, self.done))

        def __eq__(self, other: object) -> bool:
            return isinstance(other, St) and (self.robot, self.target, self.done) == (
                other.robot, other.target, other.done)

    class Act(pomdp_py.Action):
        def __init__(self, point: int) -> None:
            self.point = point

        def __hash__(self) -> int:
            return self.point

        def __eq__(self, other: object) -> bool:
            return isinstance(other, Act) and other.point == self.point

    class Obs(pomdp_py.Observation):
        def __init__(self, seen: int) -> None:
            self.seen = seen

        def __hash__(self) -> int:
            return self.seen

        def __eq__(self, other: object) -> bool:
            return isinstance(other, Obs) and other.seen == self.seen

    rng = random.Random(0)
    actions = [Act(a) for a in model.actions((0, 0))]

    class Blackbox(pomdp_py.BlackboxModel):
        def sample(self, state: St, action: Act) -> tuple[St, Obs, float, int]:
            # pomdp_py knows no terminal states: an ended search is absorbing, with reward 0
            if state.done:
                return state, Obs(0), 0.0, 1
            (robot, target), seen, reward, done = model.step((state.robot, state.target),
                                                             action.point, rng)
            return St(robot, target, done), Obs(seen), reward, 1

    class Rollout(pomdp_py.RolloutPolicy):
        def rollout(self, state: St, history: Any = None) -> Act:
            return rng.choice(actions)

        def get_all_actions(self, state: Any = None, history: Any = None) -> list[Act]:
            return actions

    belief = pomdp_py.Particles([St(r, t) for r, t in particles])
    agent = pomdp_py.Agent(belief, Rollout(), None, None, None, blackbox_model=Blackbox())
    c = model.config
    planner = pomdp_py.POUCT(max_depth=c.max_depth, discount_factor=c.gamma, num_sims=sims,
                             exploration_const=c.exploration, rollout_policy=agent.policy_model,
                             show_progress=False)
    start = time.perf_counter()
    planner.plan(agent)
    return sims / (time.perf_counter() - start)


def run_benchmark(runs: int = 5, sims: int = 500, progress: Console | None = None) -> dict[str, Any]:
    config = DecisionConfig()
    result: dict[str, Any] = {"runs": runs, "num_sims": sims, "max_depth": config.pomdp.max_depth,
                              "decision_ms": {}, "plus_decision_ms": {}}
    for key, policy_config in (("decision_ms", config), ("plus_decision_ms",
                                                          DecisionConfig(policy=OVAMOS_PLUS.name))):
        for k in CANDIDATE_COUNTS:
            times = []
            for run in range(runs):
                snap, robot = instance(k, seed=run)
                start = time.perf_counter()
                decide(snap, robot, ["t"], policy_config)
                times.append((time.perf_counter() - start) * 1e3)
            result[key][str(k)] = round(statistics.median(times), 2)
            if progress:
                progress.print(f"{policy_config.policy}, {k} candidates: {result[key][str(k)]:.1f} ms "
                               "per decision")
    model, particles = _search_pomdp(20, config)
    result["sims_per_s"] = round(statistics.median(
        ours_sims_per_s(model, particles, 5000) for _ in range(runs)))
    theirs = pomdp_py_sims_per_s(model, particles, 2000)
    result["pomdp_py_sims_per_s"] = None if theirs is None else round(theirs)
    if theirs:
        result["speedup_vs_pomdp_py"] = round(result["sims_per_s"] / theirs, 1)
    return result


def print_table(console: Console, result: dict[str, Any]) -> None:
    table = Table("candidates", "median decision (ms)", "ovamos-plus (ms)",
                  title=f"Decision = candidates + path lengths + POUCT ({result['num_sims']} sims, "
                        f"depth {result['max_depth']}); median of {result['runs']} instances")
    for k in CANDIDATE_COUNTS:
        table.add_row(str(k), f"{result['decision_ms'][str(k)]:.1f}", f"{result['plus_decision_ms'][str(k)]:.1f}")
    console.print(table)
    theirs = result.get("pomdp_py_sims_per_s")
    console.print(f"POUCT simulations/s on the search POMDP (20 candidates): ours {result['sims_per_s']}"
                  + (f", pomdp_py {theirs} ({result['speedup_vs_pomdp_py']}x)" if theirs
                     else ", pomdp_py not installed (pip install pomdp-py to compare)"))
