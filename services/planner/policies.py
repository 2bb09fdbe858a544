"""The planner's policies: how each one picks the next goal, by name, in the benchmark's table order.

Every policy shares the decision step of :mod:`ovamos.services.planner.decide` (a confirmed
object of a remaining target wins; otherwise candidates and frontiers from the value map) and
differs in a few things, which are the attributes of its :class:`Policy`: which targets it
searches at once, whether its values decay, and how it chooses among candidates and frontiers.
The planner's config names a policy (``[agent.decision] policy = "ovamos-plus"``); the search
benchmark runs them all and labels its rows with :attr:`Policy.label`.

Adding a policy is adding an entry to :data:`POLICIES` (and, for a new way of choosing, a
:class:`Choice` and its branch in :func:`ovamos.services.planner.decide.decide`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from enum import Enum
from typing import Annotated

from pydantic import AfterValidator


class Choice(Enum):
    """How a policy chooses its goal when no confirmed object of a remaining target is there to go to."""

    WANDER = "wander"            # no goal: a random walk between confirmed objects
    BEST_FRONTIER = "frontier"   # always the frontier with the highest value nearby
    GREEDY = "greedy"            # the highest value among the candidates and that frontier
    POMDP = "pomdp"              # POUCT on the paper's POMDP over the candidates and that frontier
    PLUS = "plus"                # POUCT over candidates, detections to verify and several frontiers (plus.py)


@dataclass(frozen=True)
class Policy:
    """One policy: its name (what configs and benchmark results say), its label in the
    benchmark's tables, and what sets its decisions apart."""

    name: str
    label: str
    choice: Choice
    decays: bool = True        # the value map it decides on fades with repeated views (the paper's decay)
    one_target: bool = False   # a single-object method: searches for one target at a time

    def targets(self, remaining: Sequence[str]) -> list[str]:
        """The targets it looks for now, of the ``remaining`` ones. A single-object method (vlfm)
        runs once per target in the task's order: it reads that target's value layer and goes
        only to that target's objects (it keeps its map, so an object seen earlier is still known)."""
        return list(remaining[:1]) if self.one_target else list(remaining)

    @property
    def wanders(self) -> bool:
        """No goals of its own: the agent walks at random between confirmed objects."""
        return self.choice is Choice.WANDER

    @property
    def plus_switches(self) -> bool:
        """ovamos-plus's switches (:class:`ovamos.services.planner.plus.PlusConfig`) apply: its
        stricter stop, its look before a stop and its goal budget are the agent's too."""
        return self.choice is Choice.PLUS


RANDOM = Policy("random", "Random", Choice.WANDER)
VLFM = Policy("vlfm", "VLFM", Choice.BEST_FRONTIER, decays=False, one_target=True)
FINDER = Policy("finder", "Finder", Choice.BEST_FRONTIER, decays=False)
GREEDY = Policy("ovamos-greedy", "w/o POMDP", Choice.GREEDY)
NO_DECAY = Policy("ovamos-nodecay", "w/o value decay", Choice.POMDP, decays=False)
OVAMOS = Policy("ovamos", "OVAMOS", Choice.POMDP)
OVAMOS_PLUS = Policy("ovamos-plus", "OVAMOS-plus", Choice.PLUS)

#: Every policy by name, in the order the benchmark's tables list them: the paper's baselines,
#: its ablations and its method, then ours.
POLICIES: dict[str, Policy] = {p.name: p for p in (RANDOM, VLFM, FINDER, GREEDY, NO_DECAY, OVAMOS, OVAMOS_PLUS)}


def policy_named(name: str) -> Policy:
    """The policy called ``name``; a ValueError naming every policy if there is none."""
    try:
        return POLICIES[name]
    except KeyError:
        raise ValueError(f"unknown policy {name!r}: one of {', '.join(POLICIES)}") from None


def _known(name: str) -> str:
    policy_named(name)
    return name


#: A config field holding a policy's name: refused, naming every policy, unless one is called so.
PolicyName = Annotated[str, AfterValidator(_known)]
