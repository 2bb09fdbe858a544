"""When was a frame captured, on this host's monotonic clock?

A camera stamps its frames on its own clock (a RealSense's hardware counter, a
recording's timestamps: any epoch, any drift). Odometry is matched by time, so
the core needs every capture time on the host's clock. The device cannot tell
us the offset; the frames can:

    receipt_host - device_stamp = offset + delay,    delay >= 0

Transport delay (exposure readout, USB, the SDK's queues, our own loop) only
ever *adds*, so over a window of frames the smallest (receipt - device) belongs
to the least-delayed frame and is the best offset estimate there is: one
unusually slow frame cannot move it, and it is never later than any frame's
receipt. Its one bias is that least delay itself, which no timestamp reveals;
``min_latency_s`` subtracts it when it has been measured. The window is short
enough (seconds) that the two clocks' drift does not pile up in it.

A device clock can also jump: a camera re-plugged restarts its counter, a
recording loops, a host's wall clock (RealSense global time) is stepped. A
device time that runs backwards, or a frame that looks *earlier* than the
estimate allows (a negative delay), restarts the estimate at once; a frame
that looks much *later* is first taken as one slow frame and only restarts the
estimate when ``reset_confirm`` frames in a row agree (a clock that paused).
While such a jump is unconfirmed the capture time is unknown: ``to_host``
returns None and the frame is not posed, rather than posed with a guess.
"""

from __future__ import annotations

from collections import deque
from typing import Protocol

from ovamos.services.camera.config import ClockConfig

__all__ = ["CaptureClock", "DeviceClock", "HostClock", "make_clock"]


class CaptureClock(Protocol):
    """Maps a frame's (device time, receipt time) to its capture time on the host's monotonic
    clock, or None when that time cannot be trusted (a clock jump being confirmed)."""

    resets: int

    def to_host(self, device_time_s: float, host_time_s: float) -> float | None: ...

    def reset(self) -> None: ...


class DeviceClock:
    """Offset of a device clock to the host's monotonic clock: the least (receipt - device) time
    over a sliding window of frames (see the module docstring for why the least)."""

    def __init__(self, window_s: float = 10.0, reset_s: float = 0.5, reset_confirm: int = 3,
                 min_latency_s: float = 0.0) -> None:
        if window_s <= 0 or reset_s <= 0 or reset_confirm < 1 or min_latency_s < 0:
            raise ValueError("DeviceClock needs window_s > 0, reset_s > 0, reset_confirm >= 1, "
                             "min_latency_s >= 0")
        self.window_s, self.reset_s = window_s, reset_s
        self.reset_confirm, self.min_latency_s = reset_confirm, min_latency_s
        # (receipt time, receipt - device), the differences increasing from front to back: the
        # front is the window's least, and a sample that can never become the least (an older
        # one with a larger difference) is dropped as soon as a smaller one arrives.
        self._window: deque[tuple[float, float]] = deque()
        self._jump: list[tuple[float, float]] = []  # later-looking samples awaiting confirmation
        self._last_device: float | None = None
        self.resets = 0  # clock jumps detected (not counting the first frame)

    @property
    def offset(self) -> float | None:
        """Current estimate of (host - device) plus the least delay; None before any frame."""
        return self._window[0][1] if self._window else None

    def reset(self) -> None:
        """Forget the estimate (the backend restarted: its clock may have restarted too)."""
        self._window.clear()
        self._jump.clear()
        self._last_device = None

    def _push(self, host: float, diff: float) -> None:
        while self._window and self._window[-1][1] >= diff:
            self._window.pop()
        self._window.append((host, diff))
        while self._window[0][0] < host - self.window_s:
            self._window.popleft()

    def _restart(self, samples: list[tuple[float, float]]) -> None:
        samples = list(samples)  # may be self._jump, cleared below
        self._window.clear()
        self._jump.clear()
        self.resets += 1
        for host, diff in samples:
            self._push(host, diff)

    def to_host(self, device_time_s: float, host_time_s: float) -> float | None:
        """Take one frame's stamps (in receipt order) and return its capture time on the host's
        monotonic clock, or None while a later-looking clock jump is unconfirmed."""
        diff = host_time_s - device_time_s
        backwards = self._last_device is not None and device_time_s < self._last_device
        self._last_device = device_time_s
        estimate = self.offset
        if estimate is None:
            self._push(host_time_s, diff)
        elif backwards or diff < estimate - self.reset_s:
            self._restart([(host_time_s, diff)])
        elif diff > estimate + self.reset_s:
            self._jump.append((host_time_s, diff))
            if len(self._jump) < self.reset_confirm:
                return None
            self._restart(self._jump)
        else:
            self._jump.clear()
            self._push(host_time_s, diff)
        offset = self.offset
        assert offset is not None
        return device_time_s + offset - self.min_latency_s


class HostClock:
    """For backends that already stamp frames on this host's monotonic clock (depthai): the
    device time is the capture time."""

    resets = 0

    def to_host(self, device_time_s: float, host_time_s: float) -> float | None:
        return device_time_s

    def reset(self) -> None:
        """Nothing to forget."""


def make_clock(config: ClockConfig) -> CaptureClock:
    """The clock mapping the config asks for."""
    if config.source == "host":
        return HostClock()
    return DeviceClock(config.window_s, config.reset_s, config.reset_confirm, config.min_latency_s)
