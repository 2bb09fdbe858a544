"""Simulations per second: our POUCT (ovamos.services.planner.pouct) against pomdp_py's POUCT.

All planners solve the same POMDP, pomdp_py's own Tiger example
(``pomdp_py.problems.tiger``): listening costs 1 and is right 85% of the time, opening a door
pays +10 or -100 and puts the tiger back behind a random door (no terminal state), discount
0.95, from the uniform belief, same ``max_depth``, ``num_sims`` and UCB1 constant (110, the
reward range). Three rows:

- ``pomdp_py``: ``pomdp_py.POUCT`` (Cython) on pomdp_py's Tiger classes (states, actions and
  observations are objects; a step is three model calls, T, O and R).
- ``ours, pomdp_py's model``: our POUCT driving those very same pomdp_py model objects through
  a small adapter, so the model code is identical and the difference is the planner.
- ``ours``: our POUCT on the same dynamics written as our planner expects them (one ``step``
  call, strings for states and observations): what a model written for it costs.

Steps per simulation (model steps, tree and rollout) are counted in a separate untimed run,
because the two planners define ``max_depth`` slightly differently: ours caps a simulation at
``max_depth`` steps, pomdp_py's takes one more step when its tree is that deep.

pomdp_py is optional (``pip install pomdp-py``) and imported only here; without it only our
row is measured. Run: ``python -m ovamos.bench.pouct_compare``.
"""

from __future__ import annotations

import random
import statistics
import time
from collections.abc import Callable, Sequence
from typing import Any

from rich.console import Console
from rich.table import Table

from ovamos.services.planner.pouct import POUCT

MAX_DEPTH = 5
DISCOUNT = 0.95
EXPLORATION = 110.0   # the reward range, +10 - (-100): UCB1's constant is on the reward scale
SAME_MODEL = "ours, pomdp_py's model"
ROWS = ("pomdp_py", SAME_MODEL, "ours")
LISTEN, OPEN_LEFT, OPEN_RIGHT = "listen", "open-left", "open-right"
ACTIONS = (LISTEN, OPEN_LEFT, OPEN_RIGHT)


class TigerReset:
    """pomdp_py's Tiger dynamics for our planner: states and observations "tiger-left" /
    "tiger-right"; opening a door pays, then resets the tiger and yields a random growl.

    Written the way a model for this planner should be: one call per step, all outcomes
    prebuilt as tuples and picked by one uniform draw (no objects created per step)."""

    def __init__(self) -> None:
        sides = ("tiger-left", "tiger-right")
        other = {"tiger-left": "tiger-right", "tiger-right": "tiger-left"}
        # listen: (heard right, heard wrong); open: four equally likely (next state, growl)
        self._listen = {s: ((s, s, -1.0, False), (s, other[s], -1.0, False)) for s in sides}
        self._open = {(s, a): tuple((nxt, heard, -100.0 if tiger else 10.0, False)
                                    for nxt in sides for heard in sides)
                      for s in sides for a, tiger in ((OPEN_LEFT, s == "tiger-left"),
                                                      (OPEN_RIGHT, s == "tiger-right"))}

    def actions(self, state: str) -> Sequence[str]:
        return ACTIONS

    def step(self, state: str, action: str, rng: random.Random) -> tuple[str, str, float, bool]:
        u = rng.random()
        if action == LISTEN:
            return self._listen[state][u >= 0.85]
        return self._open[state, action][int(u * 4)]

    def rollout(self, state: str, rng: random.Random) -> str:
        return ACTIONS[int(rng.random() * 3)]


class PomdpPyTigerAdapter:
    """Our GenerativeModel over a pomdp_py agent's models (T, O, R and rollout policy).

    pomdp_py's models draw from the global ``random`` module, not from ``rng``: seed it for
    reproducible runs (the benchmark does)."""

    def __init__(self, agent: Any) -> None:
        self.transition = agent.transition_model.sample
        self.observation = agent.observation_model.sample
        self.reward = agent.reward_model.sample
        self.policy = agent.policy_model
        self._actions = list(agent.policy_model.get_all_actions())

    def actions(self, state: Any) -> Sequence[Any]:
        return self._actions

    def step(self, state: Any, action: Any, rng: random.Random) -> tuple[Any, Any, float, bool]:
        nxt = self.transition(state, action)
        return nxt, self.observation(nxt, action), self.reward(state, action, nxt), False

    def rollout(self, state: Any, rng: random.Random) -> Any:
        return self.policy.rollout(state)


class _CountingModel:
    """Wraps one of our models and counts its steps (untimed runs only)."""

    def __init__(self, model: Any) -> None:
        self.model = model
        self.steps = 0
        self.actions = model.actions
        self.rollout = model.rollout

    def step(self, state: Any, action: Any, rng: random.Random) -> Any:
        self.steps += 1
        return self.model.step(state, action, rng)


def _ours(model: Any, particles: list[Any], num_sims: int, seed: int) -> tuple[str, float]:
    planner = POUCT(model, num_sims=num_sims, max_depth=MAX_DEPTH, discount=DISCOUNT,
                    exploration=EXPLORATION, seed=seed)
    random.seed(seed)                 # pomdp_py's model objects draw from the global generator
    start = time.perf_counter()
    action = planner.plan(particles)
    return str(action), time.perf_counter() - start


def _pomdp_py_runner(pomdp_py: Any, tiger: Any, num_sims: int
                     ) -> Callable[[int, Any], tuple[str, float]]:
    def run(seed: int, agent: Any) -> tuple[str, float]:
        planner = pomdp_py.POUCT(max_depth=MAX_DEPTH, discount_factor=DISCOUNT, num_sims=num_sims,
                                 exploration_const=EXPLORATION,
                                 rollout_policy=agent.policy_model, show_progress=False)
        agent.tree = None             # a fresh tree per plan, as ours builds
        random.seed(seed)
        start = time.perf_counter()
        action = planner.plan(agent)
        return str(action), time.perf_counter() - start
    return run


def _pomdp_py_agent(pomdp_py: Any, tiger: Any, transition_model: Any | None = None) -> Any:
    belief = pomdp_py.Histogram({tiger.TigerState("tiger-left"): 0.5,
                                 tiger.TigerState("tiger-right"): 0.5})
    return pomdp_py.Agent(belief, tiger.PolicyModel(), transition_model or tiger.TransitionModel(),
                          tiger.ObservationModel(0.15), tiger.RewardModel())


def _row(times: list[float], actions: list[str], num_sims: int, steps_per_sim: float) -> dict[str, Any]:
    rates = [num_sims / t for t in times]
    median = statistics.median(rates)
    return {"sims_per_s": round(median), "runs_sims_per_s": [round(r) for r in rates],
            "steps_per_sim": round(steps_per_sim, 2), "steps_per_s": round(median * steps_per_sim),
            "actions": sorted(set(actions))}


def compare(num_sims: int = 2000, repeats: int = 7) -> dict[str, Any]:
    """Median sims/s over ``repeats`` plans (seeds 0..repeats-1) of each planner on Tiger.

    The planners take turns, seed by seed, so that load from other processes on the machine
    falls on all of them alike."""
    result: dict[str, Any] = {"problem": "pomdp_py Tiger (reset on open), uniform belief",
                              "num_sims": num_sims, "max_depth": MAX_DEPTH, "discount": DISCOUNT,
                              "exploration": EXPLORATION, "repeats": repeats, "planners": {}}
    ours_model = TigerReset()
    particles = ["tiger-left", "tiger-right"]
    counting = _CountingModel(ours_model)
    _ours(counting, particles, num_sims, seed=0)
    steps = {"ours": counting.steps / num_sims}
    runners: dict[str, Callable[[int], tuple[str, float]]] = {
        "ours": lambda seed: _ours(ours_model, particles, num_sims, seed)}
    try:
        import pomdp_py
        from pomdp_py.problems.tiger import tiger_problem as tiger
    except ImportError as exc:
        result["pomdp_py"] = f"not installed ({exc})"
    else:
        result["pomdp_py"] = getattr(pomdp_py, "__version__", "installed")

        class CountingTransition(tiger.TransitionModel):
            steps = 0

            def sample(self, state: Any, action: Any) -> Any:
                CountingTransition.steps += 1
                return super().sample(state, action)

        run = _pomdp_py_runner(pomdp_py, tiger, num_sims)
        run(0, _pomdp_py_agent(pomdp_py, tiger, CountingTransition()))
        steps["pomdp_py"] = CountingTransition.steps / num_sims
        runners["pomdp_py"] = lambda seed: run(seed, _pomdp_py_agent(pomdp_py, tiger))

        belief_particles = [tiger.TigerState("tiger-left"), tiger.TigerState("tiger-right")]
        adapter = PomdpPyTigerAdapter(_pomdp_py_agent(pomdp_py, tiger))
        counting = _CountingModel(adapter)
        _ours(counting, belief_particles, num_sims, seed=0)
        steps[SAME_MODEL] = counting.steps / num_sims
        runners[SAME_MODEL] = lambda seed: _ours(adapter, belief_particles, num_sims, seed)

    runs: dict[str, list[tuple[str, float]]] = {name: [] for name in runners}
    for seed in range(repeats):
        for name, runner in runners.items():
            runs[name].append(runner(seed))
    for name in ROWS:
        if name in runs:
            result["planners"][name] = _row([t for _, t in runs[name]], [a for a, _ in runs[name]],
                                            num_sims, steps[name])
    if "pomdp_py" in result["planners"]:
        base = result["planners"]["pomdp_py"]
        for row in result["planners"].values():
            row["vs_pomdp_py"] = round(row["sims_per_s"] / base["sims_per_s"], 1)
            row["steps_vs_pomdp_py"] = round(row["steps_per_s"] / base["steps_per_s"], 1)
    return result


def print_table(console: Console, result: dict[str, Any]) -> None:
    table = Table("planner", "sims / s", "x pomdp_py", "model steps / sim", "model steps / s",
                  "x pomdp_py", "actions chosen",
                  title=f"POUCT on pomdp_py's Tiger: {result['num_sims']} sims per plan, "
                        f"max_depth {result['max_depth']}, discount {result['discount']}, "
                        f"c = {result['exploration']:g}; median of {result['repeats']} plans")
    for name in ROWS:
        row = result["planners"].get(name)
        if row is None:
            continue
        table.add_row(name, f"{row['sims_per_s']:,}", f"{row.get('vs_pomdp_py', '-')}",
                      f"{row['steps_per_sim']:.2f}", f"{row['steps_per_s']:,}",
                      f"{row.get('steps_vs_pomdp_py', '-')}", ", ".join(row["actions"]))
    console.print(table)
    if "pomdp_py" not in result["planners"]:
        console.print(f"pomdp_py: {result.get('pomdp_py')}; only our planner was measured")
    else:
        console.print("Actions: from the uniform belief every planner should listen; a door in "
                      "this column is a plan whose\nfirst visits of listen were unlucky (c = 110 is "
                      "small for a 5-step return that can reach -500), not a speed effect.")


if __name__ == "__main__":
    import sys
    print_table(Console(), compare(int(sys.argv[1]) if len(sys.argv) > 1 else 2000))
