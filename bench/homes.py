"""``ovamos bench homes``: statistics of the generated homes beside ProcTHOR-10K's.

The object prior comes from ProcTHOR, so the homes it furnishes should look like ProcTHOR's
where it matters to a search: how many rooms, how big, how much furniture and how many small
objects. This prints both side by side; it measures, it does not change the generator.

Reference figures (ProcTHOR-10K) come from the ProcTHOR generator's own code
(allenai/procthor: ``generation/room_specs.py`` PROCTHOR10K_ROOM_SPEC_SAMPLER for the rooms per
house; ``generation/interior_boundaries.py`` and ``floorplan`` run on 4000 sampled houses for the
areas, gross of walls; ``utils/types.py`` SamplingVars for the floor objects per room). They are
the generator's distribution, not a census of the released houses (which were re-sampled until
they validated, keeping the room spec). Where no figure was found the column says so.
"""

from __future__ import annotations

import statistics
from collections import defaultdict
from collections.abc import Iterable
from typing import Any

from rich.console import Console
from rich.table import Table

from ovamos.world.generate import generate_scene, home_tier
from ovamos.world.prior import ObjectPrior
from ovamos.world.scene import Scene

PROCTHOR_10K: dict[str, float | None] = {
    "rooms per home (mean)": 4.05,
    "home area m2 (median)": 81.0,
    "home area m2 (mean)": 103.5,
    "living_room m2 (median)": 22.6,
    "kitchen m2 (median)": 26.5,
    "bedroom m2 (median)": 28.1,
    "bathroom m2 (median)": 15.7,
    "office m2 (median)": None,
    "dining_room m2 (median)": None,
    # at most 7 floor placements per room in 86.5 % of houses, 25 m2 median room
    "m2 per piece of furniture": 3.6,
    "small objects per room (mean)": None,
    "small objects per receptacle used (mean)": None,
}
"""ProcTHOR-10K's generator, by the statistic's name (None: no figure found)."""

BOUNDS = {"m2 per piece of furniture": ">="}
"""Reference figures that are a bound, not a typical value (7 placements per room is a cap)."""


def home_statistics(scenes: Iterable[Scene], prior: ObjectPrior) -> dict[str, float]:
    """The statistics :data:`PROCTHOR_10K` names, over ``scenes``."""
    rooms, areas, furniture, small = [], [], 0, []
    by_type: dict[str, list[float]] = defaultdict(list)
    per_receptacle: dict[tuple[int, int], int] = defaultdict(int)
    for n, scene in enumerate(scenes):
        rooms.append(len(scene.rooms))
        areas.append(scene.area)
        for room in scene.rooms:
            by_type[room.type].append(room.area)
            small.append(sum(1 for o in scene.objects if o.room == room.id and prior[o.cls].small))
        furniture += sum(1 for o in scene.objects if not prior[o.cls].small)
        for o in scene.objects:
            if o.on is not None:
                per_receptacle[(n, o.on)] += 1
    if not rooms:
        raise ValueError("no homes to measure")
    stats = {"rooms per home (mean)": statistics.fmean(rooms),
             "home area m2 (median)": statistics.median(areas),
             "home area m2 (mean)": statistics.fmean(areas)}
    for room_type in ("living_room", "kitchen", "bedroom", "bathroom", "office", "dining_room"):
        if by_type[room_type]:
            stats[f"{room_type} m2 (median)"] = statistics.median(by_type[room_type])
    stats["m2 per piece of furniture"] = sum(areas) / max(furniture, 1)
    stats["small objects per room (mean)"] = statistics.fmean(small)
    stats["small objects per receptacle used (mean)"] = (
        statistics.fmean(per_receptacle.values()) if per_receptacle else 0.0)
    return stats


def run(count: int, homes: str = "default", first_seed: int = 0) -> dict[str, Any]:
    """Statistics of ``count`` homes of a tier (seeds from ``first_seed``), with the reference."""
    if count < 1:
        raise ValueError(f"need at least one home (got {count})")
    prior, generator = ObjectPrior.load(), home_tier(homes)
    scenes = (generate_scene(seed, prior, generator) for seed in range(first_seed, first_seed + count))
    return {"homes": homes, "count": count, "first_seed": first_seed,
            "ours": home_statistics(scenes, prior), "procthor_10k": PROCTHOR_10K}


def print_table(console: Console, result: dict[str, Any]) -> None:
    table = Table("statistic", f"ours ({result['homes']}, {result['count']} homes)", "ProcTHOR-10K",
                  title="Generated homes against ProcTHOR-10K's generator")
    for name, value in result["ours"].items():
        ref = result["procthor_10k"].get(name)
        table.add_row(name, f"{value:.1f}", "n/a" if ref is None else f"{BOUNDS.get(name, '')}{ref:.1f}")
    console.print(table)
