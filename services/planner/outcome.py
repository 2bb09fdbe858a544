"""Why a task did not find a target, in words a person understands, from what the map holds.

The benchmark's funnel (bench/funnel.py) holds the ground truth and tells every stage apart;
the planner has only its map, which is enough for the stages an operator can act on: the robot
never detected the target (look elsewhere, or it is not there), detected it but never often
enough to confirm it (the detector, the views), or confirmed it and never got there (the map,
the step limit).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

from ovamos.shared.messages import Miss, ObjectInstance, TargetMiss


def target_misses(remaining: Sequence[str], objects: Iterable[ObjectInstance]) -> tuple[TargetMiss, ...]:
    """Each of ``remaining`` with the furthest stage the map shows its search reached."""
    hits: dict[str, int] = {}
    confirmed: set[str] = set()
    for obj in objects:
        hits[obj.label] = hits.get(obj.label, 0) + obj.hits
        if obj.confirmed:
            confirmed.add(obj.label)
    return tuple(TargetMiss(label=t, detections=hits.get(t, 0),
                            stage=Miss.NOT_REACHED if t in confirmed
                            else Miss.NOT_CONFIRMED if hits.get(t) else Miss.NOT_DETECTED)
                 for t in remaining)


def explain(misses: Sequence[TargetMiss]) -> str:
    """``bed never seen; fridge detected 3 times, never confirmed``."""
    return "; ".join(str(m) for m in misses)
