"""A fleet on one laptop: which services run once per robot, and what each process is told of it.

Mapping, the planner and a robot's own services (the simulated robot, base
driver, camera) hold one robot's state, so a fleet runs one of each per robot.
Perception and the gateway serve every robot from one process (perception with
its replicas): one set of models in GPU memory, one HTTP API. A simulated fleet
puts each robot in its own home: robot i of the fleet gets the episode after
robot i-1's, and perception reads each robot's frames in that robot's scene.

Both ``ovamos up`` (a profile with ``robots = [...]``, :mod:`ovamos.profiles`)
and ``ovamos demo --robots N`` (:mod:`ovamos.demo`) build their processes from
these rules.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

#: services that serve the whole fleet from one process, told its robots (``robots`` in their config)
FLEET_WIDE = frozenset({"perception", "gateway"})


def scene(seed: int, index: int, scene_file: Any = None) -> dict[str, Any]:
    """A simulated robot's home as perception's config names it (``SceneChoice``)."""
    return {"scene_file": None if scene_file is None else str(scene_file), "episode_seed": seed,
            "episode_index": index}


def scenes(sim: Any, robots: Sequence[str]) -> dict[str, dict[str, Any]]:
    """Each simulated robot's home, from the simulated robot's config ``sim`` (a
    ``SimServiceConfig``): the episodes after its own, one per robot; with a scene file, that
    scene for every robot (one home, one robot in each copy of it)."""
    step = 0 if sim.scene_file is not None else 1
    return {robot: scene(sim.episode_seed, sim.episode_index + step * i, sim.scene_file)
            for i, robot in enumerate(robots)}


def fleet_wide_settings(service: str, config: Any, robots: Sequence[str],
                        robot_scenes: dict[str, dict[str, Any]]) -> dict[str, Any]:
    """Settings of a fleet-wide service (its ``config`` model as loaded): its robots, and for a
    simulated perception each robot's scene."""
    settings: dict[str, Any] = {"robots": list(robots)}
    if service == "perception" and config.backend == "sim" and robot_scenes:
        settings["sim"] = {**config.sim.model_dump(mode="json"), "robots": robot_scenes}
    return settings


def robot_settings(service: str, scene: dict[str, Any] | None) -> dict[str, Any]:
    """Settings of one robot's instance of a per-robot service: a simulated robot's home."""
    if service != "sim" or scene is None:
        return {}
    return {"episode_seed": scene["episode_seed"], "episode_index": scene["episode_index"]}
