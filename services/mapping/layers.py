"""The value-map maths of the paper, as pure functions on arrays.

The map state fuses each frame's reading into its layers (:func:`fov_confidence`,
:func:`fuse`); snapshots carry those raw layers and the update counts. What the
planner decides on is :func:`value_map` (the layers normalised, decayed by the
counts and summed), and the map picture (:mod:`ovamos.services.mapping.render`) shows
that same function's result, so a person looks at the map the planner saw.
"""

from __future__ import annotations

from collections.abc import Callable, Collection, Iterable
from functools import partial

import numpy as np

from ovamos.shared.messages import MapSnapshot

DECAY_TAU = 6.0
"""Paper: the update count at which a value halves (tau)."""
DECAY_KAPPA = 2.0
"""Paper: how sharply a value fades around ``tau`` (kappa)."""

Window = tuple[slice, slice]
WHOLE: Window = (slice(None), slice(None))


def fov_confidence(theta: np.ndarray, hfov: float) -> np.ndarray:
    """c = cos^2(theta / (fov/2) * pi/2): 1 on the optical axis, 0 at the edge of the view."""
    ratio = np.clip(np.abs(theta) / (hfov / 2), 0.0, 1.0)
    return np.cos(ratio * (np.pi / 2)) ** 2


def fuse(value: np.ndarray, confidence: np.ndarray, new_value: float, new_confidence: np.ndarray
         ) -> tuple[np.ndarray, np.ndarray]:
    """Confidence-weighted fusion of one new reading into cells (paper, Sec. III):
    v = (c_new v_new + c_old v_old) / (c_new + c_old), c = (c_new^2 + c_old^2) / (c_new + c_old)."""
    total = new_confidence + confidence
    safe = np.where(total > 0, total, 1.0)
    fused_v = np.where(total > 0, (new_confidence * new_value + confidence * value) / safe, value)
    fused_c = np.where(total > 0, (new_confidence ** 2 + confidence ** 2) / safe, confidence)
    return fused_v.astype(np.float32), fused_c.astype(np.float32)


def decay(values: np.ndarray, counts: np.ndarray, tau: float, kappa: float) -> np.ndarray:
    """v' = v / (1 + exp((u - tau) / kappa)): places looked at often without success fade."""
    # exp saturates (to inf, harmlessly: v' -> 0) from an argument of 88 on in float32; clip
    # it so that a cell seen a few hundred times does not raise an overflow warning
    exponent = np.minimum((counts.astype(np.float32) - tau) / kappa, 80.0)
    return (values / (1.0 + np.exp(exponent))).astype(np.float32)


def aggregate(layers: Iterable[np.ndarray], fades: Iterable[Callable[[np.ndarray], np.ndarray]] | None = None
              ) -> np.ndarray | None:
    """Sum of the layers (one per remaining target), each divided by its own peak and then
    passed through its own ``fades`` function (the decay by that layer's counts); None without
    layers.

    Normalise first, decay second: normalising a decayed layer would undo the decay (a layer
    the robot has looked at everywhere would be scaled back up to a peak of 1), so places seen
    many times without success would stay candidates for ever, and the planner would shuttle
    between them instead of exploring.
    """
    total = None
    fade_of = iter(fades) if fades is not None else None
    for layer in layers:
        peak = float(layer.max(initial=0.0))
        norm = layer / peak if peak > 0 else np.zeros_like(layer)
        if fade_of is not None:
            norm = next(fade_of)(norm)
        total = norm if total is None else total + norm
    return total


def value_map(snapshot: MapSnapshot, targets: Collection[str], tau: float = DECAY_TAU,
              kappa: float = DECAY_KAPPA, *, decayed: bool = True, window: Window = WHOLE
              ) -> np.ndarray | None:
    """The value map the planner decides on, over ``window`` of the snapshot's grid.

    The layers of ``targets`` (in the snapshot's layer order), zero outside explored
    cells, aggregated by :func:`aggregate` with the count decay (each layer by its own counts) (``decayed=False``: without,
    the no-decay ablations). None when no layer is a target. The peaks are those of
    the explored cells, so a window that holds every explored cell gives the same
    values as the whole grid.
    """
    explored = snapshot.explored[window]
    picked = [i for i, name in enumerate(snapshot.layers) if name in targets]
    layers = [snapshot.values[i][window] * explored for i in picked]
    if not decayed:
        return aggregate(layers)
    return aggregate(layers, [partial(decay, counts=snapshot.counts[i][window], tau=tau, kappa=kappa)
                              for i in picked])
