"""POUCT (Silver & Veness 2010, "Monte-Carlo Planning in Large POMDPs"): Partially Observable UCT.

A generic online planner for any POMDP that can be *simulated*: the model only has to sample
``(next state, observation, reward, terminal)`` for a state and an action, list the legal
actions, and pick rollout actions. No transition or observation probabilities are needed,
which is why the planner suits the search POMDP (path lengths, detection fall-off) as well as
textbook problems.

The search tree alternates belief nodes (one per history of ``(action, observation)`` pairs)
and action nodes (N visits, Q mean discounted return). Each simulation samples a state
uniformly from the root particles, walks down the tree choosing actions by UCB1, adds the first
new belief node it reaches, finishes with a rollout to ``max_depth``, and backs up the return.

Why the code looks the way it does: the planner runs thousands of simulations per decision
in plain Python, so the hot loop is one function with everything bound to locals, the
descent is iterative (no recursion, no per-step frames), the path is kept in preallocated
lists, nodes are ``__slots__`` objects holding parallel lists (counts, values, children)
indexed by action position, children dicts are created only when a transition first happens,
and UCB1's square roots and logarithms come from lookup tables. No numpy: array calls on 2-5
actions cost more than the arithmetic they would replace.
"""

from __future__ import annotations

import math
import random
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Generic, Protocol, TypeVar, runtime_checkable

S = TypeVar("S")
A = TypeVar("A")
O = TypeVar("O", covariant=True)  # noqa: E741 (observation; only ever returned by the model)


@runtime_checkable
class GenerativeModel(Protocol[S, A, O]):
    """What POUCT needs from a POMDP: a simulator, not probabilities.

    States, actions and observations may be any Python objects; actions and observations must
    be hashable (actions key :meth:`POUCT.action_values`, observations key the tree's belief
    nodes). All randomness must come from the ``rng`` argument, or planning is not reproducible.
    """

    def actions(self, state: S) -> Sequence[A]:
        """Legal actions. A belief node keeps the sequence returned for the first state that
        reached it (as in POMCP; do not mutate it afterwards), so it must depend only on what
        the agent knows (its history), not on the hidden part of the state. An empty
        sequence makes the state a dead end (value 0)."""
        ...

    def step(self, state: S, action: A, rng: random.Random) -> tuple[S, O, float, bool]:
        """Sample ``(next_state, observation, reward, terminal)``. ``terminal=True`` ends the
        simulated episode: nothing is simulated after it and no belief node is grown below it
        (its observation is ignored). Return terminal for a state with no legal action, or
        the rollout policy would be asked to choose from nothing."""
        ...

    def rollout(self, state: S, rng: random.Random) -> A:
        """Rollout (default) policy beyond the tree, e.g. ``rng.choice(self.actions(state))``."""
        ...


@dataclass(frozen=True)
class PlanStats:
    """What the last :meth:`POUCT.plan` did: simulations run and wall-clock seconds."""

    sims: int
    seconds: float
    tree_nodes: int

    @property
    def sims_per_s(self) -> float:
        return self.sims / self.seconds if self.seconds > 0 else float("inf")


class _Node:
    """A belief node (one history). Per legal action, by position: visit count, mean return,
    and a dict ``observation -> child node`` (None until the action was first taken here).

    ``tried`` counts the actions taken at least once; UCB1 is used only once all have been
    tried, so unvisited actions go first in the model's own order (deterministic)."""

    __slots__ = ("n", "tried", "k", "actions", "counts", "values", "children")

    def __init__(self, actions: Sequence[object]) -> None:
        k = len(actions)
        self.n = 0                                  # visits through this node (sum of counts)
        self.tried = 0
        self.k = k
        self.actions = actions
        self.counts = [0] * k
        self.values = [0.0] * k
        self.children: list[dict[object, _Node] | None] = [None] * k


# UCB1's bonus c * sqrt(ln N / n) is computed as c * _SQRT_LOG[N] * _INV_SQRT[n]: two list
# lookups instead of a log and a sqrt per node and a sqrt per action (about 12% of the
# planner's own time). Counts never exceed the simulations run, so a plan needs tables as long
# as its simulation count. Tables up to _SHARED_CAP entries are shared by all planners and
# built once per process (about 8 MB at most), so creating a planner per decision step costs
# nothing; longer plans copy and extend them privately, and that memory goes with the plan.
# Index 0 is never read: every action has a visit, and N >= 1, when UCB1 runs.
_SHARED_CAP = 1 << 17
_INV_SQRT: list[float] = [0.0]
_SQRT_LOG: list[float] = [0.0]
_TABLES_LOCK = threading.Lock()


def _extend_tables(inv_sqrt: list[float], sqrt_log: list[float], size: int) -> None:
    start = len(inv_sqrt)
    if size > start:
        numbers = range(start, size)
        inv_sqrt.extend([1.0 / math.sqrt(n) for n in numbers])
        sqrt_log.extend([math.sqrt(math.log(n)) for n in numbers])


def _ucb_tables(size: int) -> tuple[list[float], list[float]]:
    """(inv_sqrt, sqrt_log) with at least ``size`` entries (shared when small enough).

    The shared lists only ever grow, under a lock, so a search reading them in another
    thread never sees an entry change."""
    if size <= _SHARED_CAP:
        with _TABLES_LOCK:
            if len(_INV_SQRT) < size:
                _extend_tables(_INV_SQRT, _SQRT_LOG, min(_SHARED_CAP, max(size, 2 * len(_INV_SQRT))))
        return _INV_SQRT, _SQRT_LOG
    inv_sqrt, sqrt_log = _INV_SQRT[:], _SQRT_LOG[:]
    _extend_tables(inv_sqrt, sqrt_log, size)
    return inv_sqrt, sqrt_log


class POUCT(Generic[S, A, O]):
    """Partially Observable UCT over a root belief given as particles.

    Args:
        model: the generative model (see :class:`GenerativeModel`).
        num_sims: simulations per :meth:`plan`, or None for time-budget only.
        time_budget_s: wall-clock seconds per :meth:`plan`, or None for ``num_sims`` only.
            With both set, planning stops at whichever limit comes first. With a time budget
            the number of simulations depends on the machine, so results are reproducible
            only for ``num_sims`` alone.
        max_depth: the most steps in one simulated trajectory, tree and rollout together,
            counted from the root (the root's action is step 1). The horizon of the plan.
        discount: gamma applied per step.
        exploration: the UCB1 constant c in ``Q + c * sqrt(ln N / n)``. Q is a discounted
            return in reward units, so c must be on that scale: the default 1.0 suits returns
            within [0, 1]. With rewards in the hundreds (the search POMDP, the Tiger problem)
            set c to about the spread of a simulation's return, max - min: 110 for Tiger when
            opening a door ends the episode (+10 vs -100), several times that when rewards
            accumulate over ``max_depth`` steps. With c far too small exploration stops after
            one unlucky visit of an action; far too large, the search spreads evenly.
        seed: every :meth:`plan` starts a fresh ``random.Random(seed)``, so a plan is a pure
            function of (particles, settings): the same inputs give the same action and the
            same action values, and any decision can be replayed from its belief alone.
    """

    def __init__(self, model: GenerativeModel[S, A, O], *, num_sims: int | None = 500,
                 time_budget_s: float | None = None, max_depth: int = 5, discount: float = 0.95,
                 exploration: float = 1.0, seed: int = 0) -> None:
        if num_sims is None and time_budget_s is None:
            raise ValueError("POUCT needs a budget: set num_sims, time_budget_s, or both")
        if num_sims is not None and num_sims < 1:
            raise ValueError(f"num_sims must be >= 1, got {num_sims}")
        if time_budget_s is not None and not time_budget_s > 0:
            raise ValueError(f"time_budget_s must be > 0, got {time_budget_s}")
        if max_depth < 1:
            raise ValueError(f"max_depth must be >= 1, got {max_depth}")
        if not 0.0 < discount <= 1.0:
            raise ValueError(f"discount must be in (0, 1], got {discount}")
        if exploration < 0:
            raise ValueError(f"exploration must be >= 0, got {exploration}")
        self.model = model
        self.num_sims = num_sims
        self.time_budget_s = time_budget_s
        self.max_depth = max_depth
        self.discount = discount
        self.exploration = exploration
        self.seed = seed
        self._root: _Node | None = None
        self.last_stats: PlanStats | None = None

    @property
    def sims_per_s(self) -> float:
        """Simulations per second of the last :meth:`plan` (0 before any)."""
        return self.last_stats.sims_per_s if self.last_stats else 0.0

    def plan(self, particles: Sequence[S]) -> A:
        """Search from the belief represented by ``particles`` (each simulation draws one
        uniformly, so repeat a state to weight it) and return the action with the highest
        mean return Q among those visited (ties: more visits, then the model's order)."""
        if len(particles) == 0:
            raise ValueError("plan() needs at least one particle")
        rng = random.Random(self.seed)
        start = time.perf_counter()
        root = _Node(self.model.actions(particles[int(rng.random() * len(particles))]))
        if root.k == 0:
            raise ValueError("the model has no legal action in the root state")
        self._root = root
        sims, nodes = self._search(root, particles, rng, start)
        self.last_stats = PlanStats(sims=sims, seconds=time.perf_counter() - start, tree_nodes=nodes)
        best = -1
        for i in range(root.k):
            if root.counts[i] and (best < 0 or (root.values[i], root.counts[i])
                                   > (root.values[best], root.counts[best])):
                best = i
        return root.actions[best]

    def action_values(self) -> dict[A, tuple[float, int]]:
        """``{action: (Q, visits)}`` at the root of the last :meth:`plan`, in the model's
        action order (actions never tried have Q = 0.0 and 0 visits)."""
        root = self._root
        if root is None:
            raise RuntimeError("action_values() is only available after plan()")
        return {a: (root.values[i], root.counts[i]) for i, a in enumerate(root.actions)}

    def _search(self, root: _Node, particles: Sequence[S], rng: random.Random,
                start: float) -> tuple[int, int]:
        """The simulation loop. Returns (simulations run, belief nodes created).

        Everything the loop touches is a local: attribute and global lookups would cost more
        than the tree arithmetic itself."""
        model = self.model
        step = model.step
        actions_of = model.actions
        rollout_policy = model.rollout
        max_depth = self.max_depth
        gamma = self.discount
        c = self.exploration
        limit = self.num_sims if self.num_sims is not None else -1
        deadline = start + self.time_budget_s if self.time_budget_s is not None else None
        clock = time.perf_counter
        rand = rng.random
        node_cls = _Node
        npart = len(particles)
        # tables as long as the simulation count, grown by doubling as the search goes on
        # (never sized from num_sims alone: a huge num_sims with a time budget is legitimate)
        inv_sqrt, sqrt_log = _ucb_tables(min(limit + 1, _SHARED_CAP) if limit > 0 else 4096)
        table_size = len(inv_sqrt)
        # the path of the current simulation: node, action position, reward per tree step
        path_nodes: list[_Node] = [root] * max_depth
        path_actions = [0] * max_depth
        path_rewards = [0.0] * max_depth
        sims = 0
        nodes = 1
        while sims != limit:
            if deadline is not None and clock() >= deadline:
                break
            if sims >= table_size - 1:          # counts and N never exceed sims
                inv_sqrt, sqrt_log = _ucb_tables(2 * table_size)
                table_size = len(inv_sqrt)
            sims += 1
            state = particles[int(rand() * npart)]
            node = root
            t = 0                                   # tree steps taken (= depth in the tree)
            ret = 0.0                               # discounted return below the last tree step
            # --- descend the tree ---------------------------------------------------------
            while True:
                tried = node.tried
                k = node.k
                if tried < k:                       # unvisited actions first, in model order
                    i = tried
                    node.tried = tried + 1
                elif k == 0:                        # dead end: no legal action, value 0
                    break
                else:                               # UCB1
                    counts = node.counts
                    values = node.values
                    scale = c * sqrt_log[node.n]
                    i = 0
                    best = values[0] + scale * inv_sqrt[counts[0]]
                    for j in range(1, k):
                        u = values[j] + scale * inv_sqrt[counts[j]]
                        if u > best:
                            best = u
                            i = j
                state, obs, reward, terminal = step(state, node.actions[i], rng)
                path_nodes[t] = node
                path_actions[t] = i
                path_rewards[t] = reward
                t += 1
                if terminal or t >= max_depth:
                    break
                kids = node.children[i]
                if kids is None:
                    kids = node.children[i] = {}
                child = kids.get(obs)
                if child is None:
                    # a new belief node: add it, then estimate its value with a rollout
                    # (none from a dead end: a state without legal actions is worth 0)
                    legal = actions_of(state)
                    kids[obs] = node_cls(legal)
                    nodes += 1
                    depth = t if legal else max_depth
                    discount = 1.0
                    while depth < max_depth:
                        state, obs, reward, terminal = step(state, rollout_policy(state, rng), rng)
                        ret += discount * reward
                        if terminal:
                            break
                        depth += 1
                        discount *= gamma
                    break
                node = child
            # --- back up: G = r + gamma G from the leaf up; Q += (G - Q) / N ------------------
            while t:
                t -= 1
                ret = path_rewards[t] + gamma * ret
                node = path_nodes[t]
                i = path_actions[t]
                node.n += 1
                counts = node.counts
                cnt = counts[i] + 1
                counts[i] = cnt
                values = node.values
                q = values[i]
                values[i] = q + (ret - q) / cnt
        return sims, nodes
