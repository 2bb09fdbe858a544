"""The one interface every perception backend implements, and the factory that picks one.

The service only ever calls :meth:`PerceptionBackend.process` (a batch of
frames, each from its robot with that robot's targets), so the simulator's
backend and the real models are interchangeable by config, and benchmarks time
exactly what the service runs. :meth:`PerceptionBackend.score` and
:meth:`PerceptionBackend.detect` are the same for one frame. A backend raises
:class:`~.errors.FrameRejected` for a frame it cannot use (in a batch: that
job's outcome, the others go on) and :class:`~.errors.BackendError` when it
cannot start.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

from ovamos.services.perception.config import PerceptionServiceConfig
from ovamos.services.perception.errors import FrameRejected
from ovamos.shared.detections import Detection
from ovamos.shared.messages import RgbdFrame


@dataclass(frozen=True)
class Job:
    """One frame to look at: from which robot, for that robot's targets."""

    robot_id: str
    frame: RgbdFrame
    targets: tuple[str, ...]


@dataclass(frozen=True)
class Seen:
    """What a backend made of one job's frame."""

    scores: dict[str, float]
    detections: list[Detection] = field(default_factory=list)


Outcome = Seen | FrameRejected


@runtime_checkable
class PerceptionBackend(Protocol):
    #: shown in the service's info (``ovamos status``)
    name: str

    def score(self, frame: RgbdFrame, targets: Sequence[str]) -> dict[str, float]:
        """Value score per target for the whole frame, keys in the order of ``targets``."""
        ...

    def detect(self, frame: RgbdFrame, targets: Sequence[str]) -> list[Detection]:
        """Detections of the targets; boxes end-exclusive in pixels, masks of the image's size."""
        ...

    def process(self, jobs: Sequence[Job], detect: bool) -> list[Outcome]:
        """Each job's outcome, in the jobs' order (detections only when ``detect``); the models
        see the frames together as far as they can."""
        ...

    def unknown_targets(self, targets: Sequence[str]) -> tuple[tuple[str, ...], str]:
        """Of ``targets``, those it can never see and why in words a person acts on; ``((), "")``
        for an open vocabulary (a real model's: any word goes)."""
        ...


def load_backend(config: PerceptionServiceConfig) -> PerceptionBackend:
    """The configured backend; modules are imported here so an unused backend costs nothing."""
    if config.backend == "sim":
        from ovamos.services.perception.sim_backend import SimBackend
        return SimBackend.load(config.sim)
    from ovamos.services.perception.hf.backend import HfBackend
    return HfBackend.load(config.hf)
