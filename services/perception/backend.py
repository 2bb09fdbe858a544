"""The one interface every perception backend implements, and the factory that picks one.

The service only ever calls :meth:`PerceptionBackend.score` and
:meth:`PerceptionBackend.detect`, so the simulator's backend and the real
models are interchangeable by config, and benchmarks time exactly what the
service runs. A backend raises :class:`~.errors.FrameRejected` for a frame it
cannot use and :class:`~.errors.BackendError` when it cannot start.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Protocol, runtime_checkable

from services.perception.config import PerceptionServiceConfig
from shared.detections import Detection
from shared.messages import RgbdFrame


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


def load_backend(config: PerceptionServiceConfig) -> PerceptionBackend:
    """The configured backend; modules are imported here so an unused backend costs nothing."""
    if config.backend == "sim":
        from services.perception.sim_backend import SimBackend
        return SimBackend.load(config.sim)
    from services.perception.hf.backend import HfBackend
    return HfBackend.load(config.hf)
