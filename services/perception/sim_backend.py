"""The simulator's perception behind the backend interface (tests, demo, benchmarks).

It needs the scene each simulated robot renders, only to know the class of each
instance id in a frame (see :mod:`ovamos.world.perception`); frames from a
real camera carry no instance ids and are refused with :class:`FrameRejected`.
A simulated fleet has one home per robot: ``robots`` in the config names each
robot's scene, the others use the default one.

Unlike a real model's, its vocabulary is closed: the classes of the object prior, the only
things a simulated house can hold. A target outside it (a typo: ``candel``) can never be seen;
:meth:`SimBackend.unknown_targets` says why in words a person acts on, and frames are scored for
the other targets only (looking an unknown class up in the prior raised on every frame, and the
task sat at step 0 for ever).
"""

from __future__ import annotations

import difflib
from collections.abc import Sequence

from ovamos.services.perception.backend import Job, Outcome, Seen
from ovamos.services.perception.config import SceneChoice, SimBackendConfig
from ovamos.services.perception.errors import BackendError, FrameRejected
from ovamos.shared.detections import Detection
from ovamos.shared.messages import RgbdFrame
from ovamos.world.perception import FrameLabels, SimPerception, SimPerceptionConfig
from ovamos.world.prior import ObjectPrior
from ovamos.world.scene import Scene, SceneError


def _scene(choice: SceneChoice, prior: ObjectPrior) -> Scene:
    """The chosen scene file, else the scene of episode (seed, index)."""
    if choice.scene_file is not None:
        try:
            return Scene.load(choice.scene_file)
        except SceneError as exc:
            raise BackendError(f"sim backend: {exc}") from None
    from ovamos.world.episodes import make_episode
    _, scene, _ = make_episode(choice.episode_seed, choice.episode_index, prior)
    return scene


class SimBackend:
    name = "sim"

    def __init__(self, scene: Scene, prior: ObjectPrior | None = None,
                 config: SimPerceptionConfig | None = None, robots: dict[str, Scene] | None = None) -> None:
        prior = prior or ObjectPrior.load()
        self.prior = prior
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

    def unknown_targets(self, targets: Sequence[str]) -> tuple[tuple[str, ...], str]:
        """The targets no simulated house can hold, and why in words (``unknown target 'candel'
        for the simulated house: did you mean 'candle'? it can have: ...``); ``((), "")`` when
        every one can be there."""
        unknown = tuple(t for t in targets if t not in self.prior)
        if not unknown:
            return (), ""
        guesses = [close[0] for t in unknown
                   if (close := difflib.get_close_matches(t, self.prior.classes, n=1))]
        named = ", ".join(repr(t) for t in unknown)
        guess = f" did you mean {', '.join(repr(g) for g in guesses)}?" if guesses else ""
        return unknown, (f"unknown target{'s' if len(unknown) > 1 else ''} {named} for the simulated "
                         f"house:{guess} it can have: {', '.join(self.prior.classes)}")

    def _known(self, targets: Sequence[str]) -> list[str]:
        return [t for t in targets if t in self.prior]

    def score(self, frame: RgbdFrame, targets: Sequence[str]) -> dict[str, float]:
        """Scores of the targets a simulated house can hold (see :meth:`unknown_targets`)."""
        self._require_ids(frame)
        return self.perception.score(frame, self._known(targets))

    def detect(self, frame: RgbdFrame, targets: Sequence[str]) -> list[Detection]:
        self._require_ids(frame)
        return self.perception.detect(frame, self._known(targets))

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
            targets = self._known(job.targets)
            outcomes.append(Seen(perception.score(job.frame, targets),
                                 perception.detect(job.frame, targets) if detect else []))
        return outcomes
