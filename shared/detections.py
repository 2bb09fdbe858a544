"""What a detector reports for one object in one frame (every perception backend's output)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Detection:
    """``box`` is (x0, y0, x1, y1) in pixels, end-exclusive; ``mask`` is H x W bool."""

    label: str
    score: float
    box: tuple[int, int, int, int]
    mask: np.ndarray
