"""Simulated time for the wheeled robot: a clock that moves only when the benchmark runs it, and
a serial line that lives in one process.

With them the real base controller and a base's simulated device run without a thread of their
own and without waiting: the benchmark schedules the controller's tick at its control rate and
the device's firmware loop at its period on one :class:`SimClock`, and every hardware interface
reads what has arrived when the controller asks for feedback (``polled``). Nothing runs between
two events, so an episode gives the same result every time, and a primitive that takes 1.5 s on
the robot costs the milliseconds its ticks take to compute.
"""

from __future__ import annotations

import heapq
import itertools
import math
from collections.abc import Callable
from dataclasses import dataclass, field

__all__ = ["MemoryLine", "SimClock", "SimTimeError"]


class SimTimeError(RuntimeError):
    """Simulated time ran out before what was waited for happened."""


@dataclass(order=True)
class _Event:
    at: float
    seq: int                                   # ties: in the order they were scheduled
    period: float = field(compare=False)
    action: Callable[[], None] = field(compare=False)
    running: bool = field(default=False, compare=False)


class SimClock:
    """Simulated seconds since the start. Calling it reads the time (it is a ``clock`` for the
    controller and the hardware); :meth:`sleep` is a blocking wait for code that waits (a
    hardware's ``open`` waiting for its first feedback): it runs what falls due meanwhile, except
    an event that is itself waiting."""

    def __init__(self) -> None:
        self._now = 0.0
        self._events: list[_Event] = []
        self._seq = itertools.count()

    def __call__(self) -> float:
        return self._now

    def every(self, period_s: float, action: Callable[[], None], first_s: float = 0.0) -> None:
        """Run ``action`` every ``period_s`` from ``first_s`` on."""
        if not (period_s > 0 and math.isfinite(period_s)):
            raise ValueError(f"a period must be a positive number of seconds, got {period_s}")
        heapq.heappush(self._events, _Event(self._now + first_s, next(self._seq), period_s, action))

    def sleep(self, seconds: float) -> None:
        """Advance by ``seconds``, running every event due on the way."""
        until = self._now + max(0.0, seconds)
        skipped: list[_Event] = []
        while self._events and self._events[0].at <= until:
            event = heapq.heappop(self._events)
            if event.running:  # the event that is waiting now: it runs again when it returns
                skipped.append(event)
                continue
            self._now = max(self._now, event.at)
            event.running = True
            try:
                event.action()
            finally:
                event.running = False
                event.at += event.period
                heapq.heappush(self._events, event)
        for event in skipped:
            heapq.heappush(self._events, event)
        self._now = until

    def run_until(self, done: Callable[[], bool], limit_s: float, step_s: float, what: str) -> float:
        """Advance in steps of ``step_s`` until ``done()``; the simulated seconds it took. Raises
        :class:`SimTimeError` after ``limit_s``."""
        started = self._now
        while not done():
            if self._now - started >= limit_s:
                raise SimTimeError(f"{what}: not within {limit_s:g} simulated seconds")
            self.sleep(step_s)
        return self._now - started


class MemoryLine:
    """A serial line with both ends in one process, with the subset of pyserial's ``Serial`` the
    base clients use. What the host writes reaches the device at once (``to_device`` runs inside
    :meth:`write`, and may answer through :meth:`put`); what the device sends waits in the host's
    input until read. Reads never wait: in simulated time nothing arrives while one waits."""

    def __init__(self, to_device: Callable[[bytes], None], name: str = "simtime") -> None:
        self.to_device = to_device
        self.name = self.port = name
        self.is_open = True
        self._input = bytearray()

    # -- the host's side (pyserial's) ------------------------------------------------------------
    def write(self, data: bytes | bytearray | list[int]) -> int:
        payload = bytes(data)
        self.to_device(payload)
        return len(payload)

    def flush(self) -> None:
        """Written bytes are delivered in :meth:`write`: nothing to flush."""

    def read(self, size: int = 1) -> bytes:
        data = bytes(self._input[:size])
        del self._input[:size]
        return data

    @property
    def in_waiting(self) -> int:
        return len(self._input)

    def reset_input_buffer(self) -> None:
        self._input.clear()

    def close(self) -> None:
        self.is_open = False

    # -- the device's side -----------------------------------------------------------------------
    def put(self, data: bytes) -> None:
        """Bytes from the device, for the host's next read."""
        self._input += data
