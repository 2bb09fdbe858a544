"""Per-key traffic statistics, like ``ros2 topic hz`` / ``bw`` for every key at once."""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from statistics import median


class _Arrival:
    __slots__ = ("t", "nbytes", "latency")

    def __init__(self, t: float, nbytes: int, latency: float | None) -> None:
        self.t, self.nbytes, self.latency = t, nbytes, latency


@dataclass
class _Stream:
    arrivals: deque[_Arrival] = field(default_factory=lambda: deque(maxlen=1000))
    messages: int = 0


@dataclass(frozen=True)
class StreamReport:
    """One key's traffic. ``median_latency_ms`` subtracts the sender's stamp (its host's wall clock)
    from this host's: a latency only where the two clocks agree; ``latency_note`` says when they
    cannot (a median below zero)."""

    key: str
    messages: int
    rate_hz: float
    mbytes_per_s: float
    median_latency_ms: float | None
    latency_note: str = ""


class TrafficStats:
    """Counts, and over a sliding window: rate, bandwidth and sender-to-receiver latency.

    Rates are measured between the first and last arrival in the window, so a
    slow stream reads its true rate between messages, not a decaying one.
    """

    def __init__(self, window_s: float = 5.0) -> None:
        self.window_s = window_s
        self._streams: dict[str, _Stream] = {}

    def observe(self, key: str, nbytes: int, now: float, latency_s: float | None = None) -> None:
        stream = self._streams.setdefault(key, _Stream())
        stream.messages += 1
        stream.arrivals.append(_Arrival(now, nbytes, latency_s))

    def report(self, now: float) -> list[StreamReport]:
        rows = []
        for key, s in sorted(self._streams.items()):
            recent = [a for a in s.arrivals if now - a.t <= self.window_s]
            span = recent[-1].t - recent[0].t if len(recent) > 1 else 0.0
            rate = (len(recent) - 1) / span if span > 0 else 0.0
            bandwidth = sum(a.nbytes for a in recent[1:]) / span / 1e6 if span > 0 else 0.0
            latencies = [a.latency for a in recent if a.latency is not None]
            latency = median(latencies) * 1e3 if latencies else None
            note = "" if latency is None or latency >= 0 else (
                f"the sender's clock is at least {-latency:.0f} ms ahead of this host's: not a latency "
                "(sync the clocks; ovamos doctor --other-host measures the offset)")
            rows.append(StreamReport(key, s.messages, rate, bandwidth, latency, note))
        return rows
