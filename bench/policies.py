"""The policies the search benchmark compares: every planner policy
(:data:`ovamos.services.planner.policies.POLICIES`), then the ablations of ovamos-plus, and the
paper's numbers for its own.

An ablation is a benchmark row, not a policy of the planner's: ovamos-plus with some of its
switches (:class:`ovamos.services.planner.plus.PlusConfig`) changed, which a planner service runs
as ``policy = "ovamos-plus"`` with those values under ``[agent.decision.plus]``.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from ovamos.services.planner.policies import OVAMOS_PLUS, POLICIES, Policy


@dataclass(frozen=True)
class Ablation:
    """ovamos-plus with one idea switched off, or one that is off by default on (services/planner/plus.py)."""

    name: str
    label: str
    plus: Mapping[str, Any]  # the PlusConfig fields changed


ABLATIONS: dict[str, Ablation] = {a.name: a for a in (
    Ablation("ovamos-plus-1frontier", "plus w/o frontiers",
             {"frontiers": 1, "frontier_floor": 1.0}),  # the paper's one frontier, full bonus
    Ablation("ovamos-plus-noverify", "plus w/o verifying", {"verify_detections": False}),
    Ablation("ovamos-plus-strictstop", "plus with a stricter stop", {"strict_stop": True}),
    Ablation("ovamos-plus-look", "plus looking before a stop", {"look_before_stop": 4}),
    Ablation("ovamos-plus-budget", "plus with a goal budget", {"goal_commands_per_m": 12.0}),
)}
#: Every policy the benchmark runs, in the order the tables list them.
POLICY_ORDER = (*POLICIES, *ABLATIONS)
#: What ``ovamos bench search`` runs unless told: the paper's Tables I and II and ours.
DEFAULT_POLICIES = tuple(POLICIES)
#: Each policy's name in the tables.
LABELS = {**{p.name: p.label for p in POLICIES.values()}, **{a.name: a.label for a in ABLATIONS.values()}}
#: The paper's numbers: (SR in %, MSPL). Benchmark data, not a property of a policy: the tables
#: and the chart show them beside ours.
PAPER = {"random": (0.0, 0.0), "vlfm": (12.5, 0.075), "finder": (28.3, 0.198),
         "ovamos": (55.0, 0.497), "ovamos-greedy": (27.5, 0.154), "ovamos-nodecay": (45.0, 0.410)}


def policy_rank(policy: str) -> int:
    """A policy's place in :data:`POLICY_ORDER` (unknown ones last)."""
    return POLICY_ORDER.index(policy) if policy in POLICY_ORDER else len(POLICY_ORDER)


def planner_policy(name: str) -> tuple[Policy, Mapping[str, Any]]:
    """The planner policy a benchmark policy runs, and the PlusConfig changes of an ablation;
    a ValueError naming every benchmark policy if there is none called ``name``."""
    if name in ABLATIONS:
        return OVAMOS_PLUS, ABLATIONS[name].plus
    if name in POLICIES:
        return POLICIES[name], {}
    raise ValueError(f"unknown policy {name!r}: one of {', '.join(POLICY_ORDER)}")
