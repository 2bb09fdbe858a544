"""The value-map maths of the paper, as pure functions on arrays.

Kept apart from the map state so the planner (which reads snapshots) and the
mapping service apply exactly the same decay and aggregation.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable

import numpy as np


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


def aggregate(layers: Iterable[np.ndarray], fade: Callable[[np.ndarray], np.ndarray] | None = None
              ) -> np.ndarray | None:
    """Sum of the layers (one per remaining target), each divided by its own peak and then
    passed through ``fade`` (the decay); None without layers.

    Normalise first, decay second: normalising a decayed layer would undo the decay (a layer
    the robot has looked at everywhere would be scaled back up to a peak of 1), so places seen
    many times without success would stay candidates for ever, and the planner would shuttle
    between them instead of exploring.
    """
    total = None
    for layer in layers:
        peak = float(layer.max(initial=0.0))
        norm = layer / peak if peak > 0 else np.zeros_like(layer)
        if fade is not None:
            norm = fade(norm)
        total = norm if total is None else total + norm
    return total
