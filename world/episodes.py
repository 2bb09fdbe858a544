"""Search episodes: a scene seed, a start pose and three target classes (the paper's protocol)."""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from ovamos.shared.motion import Pose
from ovamos.world.evaluator import GroundTruth
from ovamos.world.generate import HomeTier, generate_scene, home_tier
from ovamos.world.prior import ObjectPrior
from ovamos.world.scene import Scene, SceneError

TARGETS_PER_EPISODE = 3
MAX_STEPS = 500
_SCENE_TRIES = 20


class EpisodeSpec(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)
    episode_id: str
    scene_seed: int
    start: Pose
    targets: tuple[str, ...] = Field(min_length=1)
    max_steps: int = Field(default=MAX_STEPS, gt=0)
    homes: HomeTier = "default"


def make_episode(base_seed: int, index: int, prior: ObjectPrior | None = None,
                 homes: str = "default") -> tuple[EpisodeSpec, Scene, GroundTruth]:
    """Episode ``index`` of the set drawn from ``base_seed`` in homes of tier ``homes``
    (:data:`~ovamos.world.generate.HOME_TIERS`), with its scene and ground truth.

    Targets are distinct classes present in the scene that a STOP can succeed for (some place
    reachable from the start is within 1 m of an instance), at least one of them small (the
    hard case the method is about).
    """
    prior = prior or ObjectPrior.load()
    generator = home_tier(homes)
    rng = np.random.default_rng([base_seed, index])
    for _ in range(_SCENE_TRIES):
        scene = generate_scene(int(rng.integers(2**31)), prior, generator)
        truth = GroundTruth(scene)
        start = _random_free_pose(rng, truth)
        stoppable = truth.stoppable_classes(start.x, start.y)
        small = [c for c in stoppable if prior[c].small]
        if len(stoppable) < TARGETS_PER_EPISODE or not small:
            continue
        first = str(rng.choice(small))
        rest = [c for c in stoppable if c != first]
        others = [str(c) for c in rng.choice(rest, TARGETS_PER_EPISODE - 1, replace=False)]
        spec = EpisodeSpec(episode_id=f"{base_seed}-{index}", scene_seed=scene.seed or 0,
                           start=start, targets=(first, *others), homes=homes)
        return spec, scene, truth
    raise RuntimeError(f"no usable scene for episode {base_seed}-{index} in {_SCENE_TRIES} tries")


def _random_free_pose(rng: np.random.Generator, truth: GroundTruth) -> Pose:
    """A free pose in the largest free region (so most of the house is reachable)."""
    rows, cols = np.nonzero(truth.free & _largest_component(truth.free))
    i = int(rng.integers(len(rows)))
    x, y = truth.grid.to_world(rows[i], cols[i])
    return Pose(x=round(x, 3), y=round(y, 3), yaw=round(float(rng.uniform(-math.pi, math.pi)), 4))


def _largest_component(free: np.ndarray) -> np.ndarray:
    n, labels, stats, _ = cv2.connectedComponentsWithStats(free.astype(np.uint8), connectivity=8)
    if n <= 1:
        raise SceneError("the scene has no free space")
    biggest = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    return labels == biggest


def save_episodes(episodes: list[EpisodeSpec], path: str | Path) -> None:
    Path(path).write_text("".join(e.model_dump_json() + "\n" for e in episodes))


def load_episodes(path: str | Path) -> list[EpisodeSpec]:
    """Episodes from a JSON-lines file; a bad line is an error naming the line."""
    episodes = []
    for n, line in enumerate(Path(path).read_text().splitlines(), 1):
        if line.strip():
            try:
                episodes.append(EpisodeSpec.model_validate_json(line))
            except ValidationError as exc:
                raise SceneError(f"{path}:{n}: not an episode: {exc}") from None
    return episodes
