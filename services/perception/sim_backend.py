"""The simulator's perception behind the backend interface (tests, demo, benchmarks).

It needs the scene each simulated robot renders, only to know the class of each
instance id in a frame (see :mod:`services.sim.perception`); frames from a
real camera carry no instance ids and are refused with :class:`FrameRejected`.
A simulated fleet has one home per robot: ``robots`` in the config names each
robot's scene, the others use the default one.
"""

from __future__ import annotations

from collections.abc import Sequence

from services.perception.backend import Job, Outcome, Seen
from services.perception.errors import BackendError, FrameRejected
from services.perception.config import SceneChoice, SimBackendConfig
from services.sim.perception import FrameLabels, SimPerception, SimPerceptionConfig
from services.sim.prior import ObjectPrior
from services.sim.world import Scene, SceneError
from shared.detections import Detection
from shared.messages import RgbdFrame


def _scene(choice: SceneChoice, prior: ObjectPrior) -> Scene:
    """The chosen scene file, else the scene of episode (seed, index)."""
    if choice.scene_file is not None:
        try:
            return Scene.load(choice.scene_file)
        except SceneError as exc:
            raise BackendError(f"sim backend: {exc}") from None
    from services.sim.episodes import make_episode
    _, scene, _ = make_episode(choice.episode_seed, choice.episode_index, prior)
    return scene


class SimBackend:
    name = "sim"

    def __init__(self, scene: Scene, prior: ObjectPrior | None = None,
                 config: SimPerceptionConfig | None = None, robots: dict[str, Scene] | None = None) -> None:
        prior = prior or ObjectPrior.load()
        self.perception = SimPerception(FrameLabels.of(scene), prior, config)
        self.robots = {robot: SimPerception(FrameLabels.of(s), prior, config)
                       for robot, s in (robots or {}).items()}

    @classmethod
    def load(cls, config: SimBackendConfig) -> SimBackend:
        """From the configured scenes (files or episodes)."""
        prior = ObjectPrior.load()
        return cls(_scene(config, prior), prior, config.perception,
                   {robot: _scene(choice, prior) for robot, choice in config.robots.items()})

    @staticmethod
    def _require_ids(frame: RgbdFrame) -> None:
        if frame.instance_ids is None:
            raise FrameRejected("frame has no instance ids: the sim backend only reads simulated frames; "
                                "run perception with backend = \"hf\" for a real camera")

    def score(self, frame: RgbdFrame, targets: Sequence[str]) -> dict[str, float]:
        self._require_ids(frame)
        return self.perception.score(frame, targets)

    def detect(self, frame: RgbdFrame, targets: Sequence[str]) -> list[Detection]:
        self._require_ids(frame)
        return self.perception.detect(frame, targets)

    def process(self, jobs: Sequence[Job], detect: bool) -> list[Outcome]:
        """One frame at a time (nothing to batch on the CPU), each read in its robot's scene."""
        outcomes: list[Outcome] = []
        for job in jobs:
            perception = self.robots.get(job.robot_id, self.perception)
            try:
                self._require_ids(job.frame)
            except FrameRejected as exc:
                outcomes.append(exc)
                continue
            outcomes.append(Seen(perception.score(job.frame, job.targets),
                                 perception.detect(job.frame, job.targets) if detect else []))
        return outcomes
