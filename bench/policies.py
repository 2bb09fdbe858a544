"""The policies the search benchmark compares: their order, names and the paper's numbers."""

from __future__ import annotations

#: Every policy, in the order the paper's tables list them (baselines, ablations, the method).
POLICY_ORDER = ("random", "vlfm", "finder", "ovamos-greedy", "ovamos-nodecay", "ovamos")
LABELS = {"random": "Random", "vlfm": "VLFM", "finder": "Finder", "ovamos": "OVAMOS",
          "ovamos-greedy": "w/o POMDP", "ovamos-nodecay": "w/o value decay"}
#: The paper's numbers: (SR in %, MSPL).
PAPER = {"random": (0.0, 0.0), "vlfm": (12.5, 0.075), "finder": (28.3, 0.198),
         "ovamos": (55.0, 0.497), "ovamos-greedy": (27.5, 0.154), "ovamos-nodecay": (45.0, 0.410)}


def policy_rank(policy: str) -> int:
    """A policy's place in :data:`POLICY_ORDER` (unknown ones last)."""
    return POLICY_ORDER.index(policy) if policy in POLICY_ORDER else len(POLICY_ORDER)
