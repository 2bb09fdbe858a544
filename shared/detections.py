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


def often_detected(hits: int, views: int, min_hits: int, min_ratio: float) -> bool:
    """``min_hits`` detections, in at least ``min_ratio`` of the frames that saw the place: the one
    evidence rule for an object, whether the map confirms it or a planner stops at it. A false
    positive recurs now and then, so its hits grow with time; its share of the views does not."""
    return hits >= min_hits and hits >= min_ratio * views
