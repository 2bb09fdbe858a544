"""The policies the search benchmark compares: their order, names, the paper's numbers, and the
ablations of our own planner."""

from __future__ import annotations

from typing import Any

#: Every policy, in the order the tables list them: the paper's (baselines, ablations, the method),
#: then ours and its ablations.
POLICY_ORDER = ("random", "vlfm", "finder", "ovamos-greedy", "ovamos-nodecay", "ovamos", "ovamos-plus",
                "ovamos-plus-1frontier", "ovamos-plus-noverify", "ovamos-plus-strictstop", "ovamos-plus-look",
                "ovamos-plus-budget")
#: What ``ovamos bench search`` runs unless told: the paper's Tables I and II and ours.
DEFAULT_POLICIES = POLICY_ORDER[:7]
LABELS = {"random": "Random", "vlfm": "VLFM", "finder": "Finder", "ovamos": "OVAMOS",
          "ovamos-greedy": "w/o POMDP", "ovamos-nodecay": "w/o value decay", "ovamos-plus": "OVAMOS-plus",
          "ovamos-plus-1frontier": "plus w/o frontiers", "ovamos-plus-noverify": "plus w/o verifying",
          "ovamos-plus-strictstop": "plus with a stricter stop", "ovamos-plus-look": "plus looking before a stop",
          "ovamos-plus-budget": "plus with a goal budget"}
#: The paper's numbers: (SR in %, MSPL).
PAPER = {"random": (0.0, 0.0), "vlfm": (12.5, 0.075), "finder": (28.3, 0.198),
         "ovamos": (55.0, 0.497), "ovamos-greedy": (27.5, 0.154), "ovamos-nodecay": (45.0, 0.410)}
#: ovamos-plus with one idea switched off, or the one that is off by default on (services/planner/plus.py):
#: the PlusConfig fields changed.
PLUS_ABLATIONS: dict[str, dict[str, Any]] = {
    "ovamos-plus-1frontier": {"frontiers": 1, "frontier_floor": 1.0},  # the paper's one frontier, full bonus
    "ovamos-plus-noverify": {"verify_detections": False},
    "ovamos-plus-budget": {"goal_commands_per_m": 12.0},
    "ovamos-plus-strictstop": {"strict_stop": True},
    "ovamos-plus-look": {"look_before_stop": 4},
}


def policy_rank(policy: str) -> int:
    """A policy's place in :data:`POLICY_ORDER` (unknown ones last)."""
    return POLICY_ORDER.index(policy) if policy in POLICY_ORDER else len(POLICY_ORDER)


def base_policy(name: str) -> tuple[str, dict[str, Any]]:
    """The planner policy a benchmark policy runs, and the PlusConfig changes of an ablation."""
    return ("ovamos-plus", PLUS_ABLATIONS[name]) if name in PLUS_ABLATIONS else (name, {})
