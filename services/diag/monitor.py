"""Per-key traffic statistics, like ``ros2 topic hz`` / ``bw`` for every key at once."""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from statistics import median


@dataclass
class _Stream:
    arrivals: deque[tuple[float, int]] = field(default_factory=lambda: deque(maxlen=200))
    latencies: deque[float] = field(default_factory=lambda: deque(maxlen=200))
    messages: int = 0
    bytes: int = 0


@dataclass(frozen=True)
class StreamReport:
    key: str
    messages: int
    rate_hz: float
    mbytes_per_s: float
    median_latency_ms: float | None


class TrafficStats:
    """Counts, rates over a sliding window, and sender-to-receiver latency per key."""

    def __init__(self, window_s: float = 5.0) -> None:
        self.window_s = window_s
        self._streams: dict[str, _Stream] = {}

    def observe(self, key: str, nbytes: int, now: float, latency_s: float | None = None) -> None:
        stream = self._streams.setdefault(key, _Stream())
        stream.messages += 1
        stream.bytes += nbytes
        stream.arrivals.append((now, nbytes))
        if latency_s is not None:
            stream.latencies.append(latency_s)

    def report(self, now: float) -> list[StreamReport]:
        rows = []
        for key, s in sorted(self._streams.items()):
            recent = [(t, n) for t, n in s.arrivals if now - t <= self.window_s]
            span = now - recent[0][0] if len(recent) > 1 else 0.0
            rate = (len(recent) - 1) / span if span > 0 else 0.0
            bandwidth = sum(n for _, n in recent[1:]) / span / 1e6 if span > 0 else 0.0
            latency = median(s.latencies) * 1e3 if s.latencies else None
            rows.append(StreamReport(key, s.messages, rate, bandwidth, latency))
        return rows
