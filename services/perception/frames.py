"""Checks a frame must pass before any model sees it, and the hand-off queue to the worker.

A decodable :class:`~shared.messages.RgbdFrame` already has a uint8 H x W x 3
image and a depth image of the same size (the bus drops, and counts, any
other); :func:`frame_problem` adds what the models need on top: a usable size.
"""

from __future__ import annotations

import threading
from collections import deque
from collections.abc import Callable
from typing import Generic, TypeVar

from services.perception.config import FrameLimits
from shared.messages import RgbdFrame

T = TypeVar("T")


def frame_problem(frame: RgbdFrame, limits: FrameLimits) -> str | None:
    """Why ``frame`` cannot be processed, or None when it can."""
    height, width = frame.depth.shape
    if limits.size is not None and (width, height) != limits.size:
        return f"frame is {width}x{height}, the camera is configured for {limits.size[0]}x{limits.size[1]}"
    if min(width, height) < limits.min_side or max(width, height) > limits.max_side:
        return (f"frame is {width}x{height}, sides must be within "
                f"{limits.min_side}..{limits.max_side} pixels")
    return None


class BoundedQueue(Generic[T]):
    """Frames waiting for the worker; when full the oldest gives way (``on_drop`` is told).

    With capacity 1 this is the latest-only hand-off the design asks of frame
    consumers: a slow model never makes memory grow or work on stale frames.
    """

    def __init__(self, capacity: int, on_drop: Callable[[T], object]) -> None:
        self._items: deque[T] = deque()
        self._capacity, self._on_drop = capacity, on_drop
        self._cond = threading.Condition()
        self._closed = False

    def put(self, item: T) -> None:
        with self._cond:
            if len(self._items) >= self._capacity:
                self._on_drop(self._items.popleft())
            self._items.append(item)
            self._cond.notify()

    def get(self) -> T | None:
        """The oldest waiting item; None once closed."""
        with self._cond:
            while not self._items and not self._closed:
                self._cond.wait()
            return None if self._closed else self._items.popleft()

    def close(self) -> None:
        with self._cond:
            self._closed = True
            self._cond.notify_all()
