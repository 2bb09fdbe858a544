"""The simulator's perception behind the backend interface (tests, demo, benchmarks).

It needs the scene the simulated robot renders, only to know the class of each
instance id in a frame (see :mod:`services.sim.perception`); frames from a
real camera carry no instance ids and are refused with :class:`FrameRejected`.
"""

from __future__ import annotations

from collections.abc import Sequence

from services.perception.errors import BackendError, FrameRejected
from services.perception.config import SimBackendConfig
from services.sim.perception import FrameLabels, SimPerception, SimPerceptionConfig
from services.sim.prior import ObjectPrior
from services.sim.world import Scene, SceneError
from shared.detections import Detection
from shared.messages import RgbdFrame


class SimBackend:
    name = "sim"

    def __init__(self, scene: Scene, prior: ObjectPrior | None = None,
                 config: SimPerceptionConfig | None = None) -> None:
        prior = prior or ObjectPrior.load()
        self.perception = SimPerception(FrameLabels.of(scene), prior, config)

    @classmethod
    def load(cls, config: SimBackendConfig) -> SimBackend:
        """From the configured scene file, else the scene of episode (seed, index)."""
        prior = ObjectPrior.load()
        if config.scene_file is not None:
            try:
                scene = Scene.load(config.scene_file)
            except SceneError as exc:
                raise BackendError(f"sim backend: {exc}") from None
        else:
            from services.sim.episodes import make_episode
            _, scene, _ = make_episode(config.episode_seed, config.episode_index, prior)
        return cls(scene, prior, config.perception)

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
