"""Transport benchmark: one 640x480 RGB-D frame, two processes, one router.

Each round trip sends a frame from this process to an echo process and waits
for a small acknowledgement. ``raw`` puts pre-encoded bytes with plain Zenoh
calls; ``ovamos`` goes through the service layer (encode, typed publisher,
latest-only subscription with its worker thread, validated decode, JSON ack).
Round trips alternate between the variants so drift on the machine hits both
alike, and start ``gap_ms`` apart as frames from a camera would: sent
back-to-back, a round trip finds the router's and peer's threads still spinning
from the previous one, and whichever variant does less work before its put
gets that fast path, which a robot streaming at 10-30 Hz never sees.
"""

from __future__ import annotations

import multiprocessing as mp
import statistics
import threading
import time
from typing import Any
from collections.abc import Callable

from rich.console import Console
from rich.table import Table

from services.diag.testpattern import pattern_frame
from shared import keys
from shared.bus import Bus
from shared.messages import JsonMessage, RgbdFrame
from shared.procs import free_port, loopback, start_cli, stop
from shared.zconfig import build_config, open_session

ROBOT = "bench"
RAW_FRAME, RAW_ACK = keys.bench(ROBOT, "raw-frame"), keys.bench(ROBOT, "raw-ack")
OVAMOS_FRAME, OVAMOS_ACK = keys.rgbd(ROBOT), keys.bench(ROBOT, "ack")
VARIANTS = ("raw", "ovamos")
WARMUP = 20


class Ack(JsonMessage):
    seq: int


def _echo(variant: str, endpoint: str, stop_event: Any) -> None:
    """Echo process: acknowledge every frame it receives."""
    cfg = build_config(connect=[endpoint])
    if variant == "raw":
        session = open_session(cfg)
        ack = session.declare_publisher(RAW_ACK)

        def on_frame(sample: Any) -> None:
            ack.put(len(sample.payload.to_bytes()).to_bytes(8, "little"))

        sub = session.declare_subscriber(RAW_FRAME, on_frame)
        stop_event.wait()
        sub.undeclare()
        session.close()
    else:
        with Bus.open(cfg, ROBOT, "bench-echo") as bus:
            ack_pub = bus.publisher(OVAMOS_ACK, Ack)
            bus.subscribe(OVAMOS_FRAME, RgbdFrame, lambda f: ack_pub.put(Ack(seq=f.seq)),
                          keep=1)
            stop_event.wait()


class AckedSender:
    """The measuring side of a round trip: :meth:`send` one frame, then wait for ``acked``
    (set by the subclass's ack subscriber)."""

    acked: threading.Event

    def send(self) -> None:
        raise NotImplementedError

    def round_trip(self, timeout: float) -> float | None:
        """Seconds from sending a frame to its ack; None when no ack came within ``timeout``."""
        self.acked.clear()
        start = time.perf_counter()
        self.send()
        if not self.acked.wait(timeout):
            return None
        return time.perf_counter() - start

    def wait_ready(self, timeout: float, probe_s: float, failure: str) -> None:
        """Probe until a round trip succeeds (routes and the echo are up); TimeoutError(failure)."""
        deadline = time.monotonic() + timeout
        while self.round_trip(probe_s) is None:
            if time.monotonic() > deadline:
                raise TimeoutError(failure)


class _Pinger(AckedSender):
    """One variant of this benchmark (raw Zenoh or through the Bus)."""

    def __init__(self, variant: str, endpoint: str, frame: RgbdFrame) -> None:
        self.acked = threading.Event()
        cfg = build_config(connect=[endpoint])
        if variant == "raw":
            self._session = open_session(cfg)
            payload = bytes(frame.to_bytes())
            pub = self._session.declare_publisher(RAW_FRAME)
            self._sub = self._session.declare_subscriber(RAW_ACK, lambda _s: self.acked.set())
            self.send = lambda: pub.put(payload)  # type: ignore[method-assign]
            self.close: Callable[[], None] = self._session.close
        else:
            bus = Bus.open(cfg, ROBOT, "bench-client")
            pub = bus.publisher(OVAMOS_FRAME, RgbdFrame)
            bus.subscribe(OVAMOS_ACK, Ack, lambda _a: self.acked.set())
            self.send = lambda: pub.put(frame)  # type: ignore[method-assign]
            self.close = bus.close



def _measure(pingers: dict[str, _Pinger], frames: int, gap_s: float) -> dict[str, float]:
    """Median round trip per variant over ``frames`` interleaved round trips."""
    samples: dict[str, list[float]] = {v: [] for v in pingers}
    for i in range(WARMUP + frames):
        for variant, pinger in pingers.items():
            time.sleep(gap_s)
            rtt = pinger.round_trip(2.0)
            if rtt is None:
                raise RuntimeError(f"{variant}: a frame was not acknowledged within 2 s")
            if i >= WARMUP:
                samples[variant].append(rtt)
    return {v: statistics.median(s) for v, s in samples.items()}


def run_benchmark(frames: int = 200, runs: int = 5, gap_ms: float = 5.0,
                  progress: Console | None = None) -> dict[str, Any]:
    endpoint = loopback(free_port())
    frame = pattern_frame(0, time.time())
    ctx = mp.get_context("spawn")
    stop_echo = ctx.Event()
    router = start_cli(["router", "--listen", endpoint, "--log-level", "WARNING"])
    echoes = [ctx.Process(target=_echo, args=(v, endpoint, stop_echo)) for v in VARIANTS]
    pingers: dict[str, _Pinger] = {}
    medians: dict[str, list[float]] = {v: [] for v in VARIANTS}
    try:
        for proc in echoes:
            proc.start()
        pingers = {v: _Pinger(v, endpoint, frame) for v in VARIANTS}
        for pinger in pingers.values():
            pinger.wait_ready(30.0, 0.2, "the echo process never answered")
        for run in range(runs):
            for variant, median in _measure(pingers, frames, gap_ms / 1e3).items():
                medians[variant].append(median)
            if progress:
                progress.print(f"run {run + 1}/{runs}: " + ", ".join(
                    f"{v} {m[-1] * 1e6:.0f} us" for v, m in medians.items()))
    finally:
        for pinger in pingers.values():
            pinger.close()
        stop_echo.set()
        for proc in echoes:
            proc.join(10)
            if proc.is_alive():
                proc.kill()
        stop(router)
    raw, ours = (statistics.median(medians[v]) for v in VARIANTS)
    raw_us, ours_us = round(raw * 1e6, 1), round(ours * 1e6, 1)
    size = len(frame.to_bytes())
    return {
        "frame_bytes": size, "frames_per_run": frames, "runs": runs, "gap_ms": gap_ms,
        "raw_median_us": raw_us, "ovamos_median_us": ours_us,
        # From the printed medians, so a reader dividing the two table cells gets the same ratio.
        "overhead_ratio": round(ours_us / raw_us, 3),
        "raw_frames_per_s": round(1 / raw, 1), "ovamos_frames_per_s": round(1 / ours, 1),
        "raw_mb_per_s": round(size / raw / 1e6, 1), "ovamos_mb_per_s": round(size / ours / 1e6, 1),
        "run_medians_us": {v: [round(m * 1e6, 1) for m in ms] for v, ms in medians.items()},
    }


def print_table(console: Console, result: dict[str, Any]) -> None:
    table = Table("path", "median round trip (us)", "frames/s", "MB/s",
                  title=f"RGB-D frame {result['frame_bytes']} B through a router, median of "
                        f"{result['runs']} runs x {result['frames_per_run']} frames, "
                        f"{result['gap_ms']:g} ms apart")
    for v in VARIANTS:
        table.add_row(v, f"{result[f'{v}_median_us']:.0f}", f"{result[f'{v}_frames_per_s']:.0f}",
                      f"{result[f'{v}_mb_per_s']:.0f}")
    console.print(table)
    console.print(f"overhead ratio (ovamos / raw): {result['overhead_ratio']:.3f}")
