"""Transport benchmark: one 640x480 RGB-D frame, two processes, one router.

Each round trip sends a frame from this process to an echo process and waits
for a small acknowledgement. ``raw`` puts pre-encoded bytes with plain Zenoh
calls; ``ovamos`` goes through the service layer (encode, typed publisher,
latest-only subscription, one hand-off from Zenoh's thread to the node's event
loop in each process, validated decode, JSON ack; the measuring thread is the
sender's event loop, as a service's main thread is).
Each comes in three transports (:data:`VARIANTS`), all in the same run through the same
router (shared memory on, as shipped): shared memory off in both clients (the
network path, as between two hosts); on, with the frame in a buffer of the
sender's own shared-memory provider (``+shm``: raw Zenoh's ``ShmProvider``, the
bus's :mod:`ovamos.shared.bus.shm`); and, for raw, on with a plain put of bytes
(``+zpool``: Zenoh's own pool for payloads over 3 KB, what a session does by default).
Round trips alternate between the variants so drift on the machine hits all alike, and start
``gap_ms`` apart as frames from a camera would: sent back-to-back, a round trip
finds the router's and peer's threads still spinning from the previous one, and
whichever variant does less work before its put gets that fast path, which a
robot streaming at 10-30 Hz never sees.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import statistics
import threading
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any, TypeVar

import zenoh
from rich.console import Console
from rich.table import Table

from ovamos.services.diag.testpattern import pattern_frame
from ovamos.shared import keys
from ovamos.shared.bus import Bus
from ovamos.shared.bus.shm import ShmPool
from ovamos.shared.bus.zconfig import build_config, open_session
from ovamos.shared.messages import JsonMessage, RgbdFrame
from ovamos.shared.procs import (
    deferred_signals,
    free_port,
    loopback,
    run_dying_with_parent,
    signals_unwind,
    start_cli,
    stop,
    stop_spawned,
)

WARMUP = 20
#: a frame not acknowledged within this is lost (a full queue dropped it): counted, not in the medians
LOST_AFTER_S = 2.0
T = TypeVar("T")


@dataclass(frozen=True)
class Variant:
    """One way across: ``path`` raw or ovamos; ``shm`` off, ``provider`` (the sender's own pool) or
    ``zpool`` (shared memory on, bytes put: Zenoh copies them into its own pool)."""

    name: str
    path: str
    shm: str

    @property
    def robot(self) -> str:
        """A key chunk of its own, so each variant's echo hears only its frames."""
        return "bench-" + self.name.replace("+", "-")

    def raw_wrap(self) -> Callable[[bytes], bytes | zenoh.shm.ZShmMut]:
        """How raw Zenoh's sender of this variant hands its payload to ``put``: in a buffer of its
        own shared-memory pool (the bus's allocation and copy, without the bus), or as it is."""
        return ShmPool().wrap if self.shm == "provider" else (lambda payload: payload)

    def config(self, endpoint: str) -> zenoh.Config:
        cfg = build_config(connect=[endpoint])
        cfg.insert_json5("transport/shared_memory/enabled", "false" if self.shm == "off" else "true")
        return cfg


VARIANTS = (Variant("raw", "raw", "off"), Variant("ovamos", "ovamos", "off"),
            Variant("raw+shm", "raw", "provider"), Variant("ovamos+shm", "ovamos", "provider"),
            Variant("raw+zpool", "raw", "zpool"))
#: the ratios reported: ours over raw Zenoh on the same transport
RATIOS = {"overhead_ratio": ("ovamos", "raw"), "shm_overhead_ratio": ("ovamos+shm", "raw+shm")}


class Ack(JsonMessage):
    seq: int


def _echo(variant: Variant, endpoint: str, stop_event: Any) -> None:
    """Echo process: acknowledge every frame it receives."""
    cfg = variant.config(endpoint)
    if variant.path == "raw":
        session = open_session(cfg)
        ack = session.declare_publisher(keys.bench(variant.robot, "ack"))

        def on_frame(sample: Any) -> None:
            ack.put(len(sample.payload.to_bytes()).to_bytes(8, "little"))

        sub = session.declare_subscriber(keys.rgbd(variant.robot), on_frame)
        stop_event.wait()
        sub.undeclare()
        session.close()
    else:
        with Bus.open(cfg, variant.robot, "bench-echo") as bus:
            ack_pub = bus.publisher(keys.bench(variant.robot, "ack"), Ack)
            bus.subscribe(keys.rgbd(variant.robot), RgbdFrame, lambda f: ack_pub.put(Ack(seq=f.seq)),
                          keep=1)
            stop_event.wait()


class AckedSender:
    """The measuring side of a round trip: :meth:`send` one frame, then wait for ``acked``
    (set by the subclass's ack subscriber)."""

    acked: threading.Event

    def send(self) -> None:
        raise NotImplementedError

    def wait_ack(self, timeout: float) -> bool:
        """Wait until ``acked`` is set (by a Zenoh callback); False after ``timeout``."""
        return self.acked.wait(timeout)

    def round_trip(self, timeout: float) -> float | None:
        """Seconds from sending a frame to its ack; None when no ack came within ``timeout``."""
        self.acked.clear()
        start = time.perf_counter()
        self.send()
        if not self.wait_ack(timeout):
            return None
        return time.perf_counter() - start

    def wait_ready(self, timeout: float, probe_s: float, failure: str) -> None:
        """Probe until a round trip succeeds (routes and the echo are up); TimeoutError(failure)."""
        wait_ready(self.round_trip, timeout, probe_s, failure)


def wait_ready(round_trip: Callable[[float], object | None], timeout: float, probe_s: float,
               failure: str) -> None:
    """Probe ``round_trip(probe_s)`` until it gives a result; TimeoutError(failure) after ``timeout``."""
    deadline = time.monotonic() + timeout
    while round_trip(probe_s) is None:
        if time.monotonic() > deadline:
            raise TimeoutError(failure)


def loop_waiter(bus: Bus, event: threading.Event) -> Callable[[float], bool]:
    """Wait for ``event`` as a service's event loop does (a ``dispatch="caller"`` bus): this
    thread takes the bus's events itself until a handler sets it; False after the timeout."""
    def wait(timeout: float) -> bool:
        bus.inbox.run_until(time.monotonic() + timeout, event)
        return event.is_set()

    return wait


class _Pinger(AckedSender):
    """One variant of this benchmark (raw Zenoh or through the Bus)."""

    def __init__(self, variant: Variant, endpoint: str, frame: RgbdFrame) -> None:
        self.acked = threading.Event()
        cfg = variant.config(endpoint)
        frame_key, ack_key = keys.rgbd(variant.robot), keys.bench(variant.robot, "ack")
        if variant.path == "raw":
            self._session = open_session(cfg)
            payload = bytes(frame.to_bytes())
            pub = self._session.declare_publisher(frame_key)
            self._sub = self._session.declare_subscriber(ack_key, lambda _s: self.acked.set())
            wrap = variant.raw_wrap()
            self.send = lambda: pub.put(wrap(payload))  # type: ignore[method-assign]
            self.close: Callable[[], None] = self._session.close
        else:
            # As a service runs (ovamos.shared.service): the measuring thread is the node's event loop and
            # takes the ack from the inbox itself, one thread hand-off as raw's callback -> waiter.
            bus = Bus.open(cfg, variant.robot, "bench-client", dispatch="caller")
            pub = bus.publisher(frame_key, RgbdFrame)
            bus.subscribe(ack_key, Ack, lambda _a: self.acked.set())
            self.send = lambda: pub.put(frame)  # type: ignore[method-assign]
            self.wait_ack = loop_waiter(bus, self.acked)  # type: ignore[method-assign]
            self.close = bus.close


def interleave(round_trips: Mapping[str, Callable[[float], T | None]], frames: int, gap_s: float,
               lost: dict[str, int], max_lost: int) -> dict[str, list[T]]:
    """One run: ``frames`` measured round trips per sender after :data:`WARMUP` unmeasured ones,
    interleaved between the senders, ``gap_s`` apart; each sender's results in order. A round trip
    without an ack in :data:`LOST_AFTER_S` is counted in ``lost``; more than ``max_lost`` lost by one
    sender fails the run: its median would describe the survivors, not the path."""
    samples: dict[str, list[T]] = {v: [] for v in round_trips}
    for i in range(WARMUP + frames):
        for variant, round_trip in round_trips.items():
            time.sleep(gap_s)
            result = round_trip(LOST_AFTER_S)
            if result is None:
                lost[variant] += 1
                if lost[variant] > max_lost:
                    raise RuntimeError(f"{variant}: over 10 % of the frames lost")
            elif i >= WARMUP:
                samples[variant].append(result)
    return samples


def measure(senders: Mapping[str, AckedSender], frames: int, runs: int, gap_s: float,
            progress: Console | None, show: Callable[[float], str]) -> tuple[dict[str, list[float]], dict[str, int]]:
    """Each sender's median round trip per run (:func:`interleave`), and how many frames each lost;
    over 10 % of all one sender sent lost fails."""
    medians: dict[str, list[float]] = {v: [] for v in senders}
    lost = {v: 0 for v in senders}
    round_trips = {v: sender.round_trip for v, sender in senders.items()}
    for run in range(runs):
        samples = interleave(round_trips, frames, gap_s, lost, (WARMUP + frames) * runs // 10)
        for variant, s in samples.items():
            medians[variant].append(statistics.median(s))
        if progress:
            progress.print(f"run {run + 1}/{runs}: " + ", ".join(f"{v} {show(m[-1])}" for v, m in medians.items()))
    return medians, lost


def print_lost(console: Console, lost: dict[str, int]) -> None:
    if any(lost.values()):
        console.print(f"frames lost (no ack within {LOST_AFTER_S:g} s, not in the medians): {lost}")


@contextmanager
def echo_processes(echo: Callable[[Variant, str, Any], None], variants: Sequence[Variant]) -> Iterator[str]:
    """A router on a free loopback port and a spawned ``echo(variant, endpoint, stop_event)``
    process per variant; yields the router's endpoint, and stops the echoes and the router on
    exit (close the senders first), SIGTERM and SIGINT included (:func:`~ovamos.shared.procs.signals_unwind`;
    each child also dies with this process if it is killed outright)."""
    endpoint = loopback(free_port())
    ctx = mp.get_context("spawn")
    stop_echo = ctx.Event()
    router: Any = None
    echoes: list[Any] = []
    with signals_unwind():
        try:
            with deferred_signals():  # a signal now waits until the child's handle is kept
                router = start_cli(["router", "--listen", endpoint, "--log-level", "WARNING"])
            for v in variants:
                with deferred_signals():
                    echoes.append(ctx.Process(target=run_dying_with_parent,
                                              args=(os.getpid(), echo, v, endpoint, stop_echo)))
                    echoes[-1].start()
            yield endpoint
        finally:
            with deferred_signals():
                stop_echo.set()
                for proc in echoes:
                    stop_spawned(proc)
                if router is not None:
                    stop(router)


def run_benchmark(frames: int = 200, runs: int = 5, gap_ms: float = 5.0,
                  progress: Console | None = None) -> dict[str, Any]:
    frame = pattern_frame(0, time.time())
    with echo_processes(_echo, VARIANTS) as endpoint:
        pingers: dict[str, _Pinger] = {}
        try:
            for v in VARIANTS:  # one by one: those made before a failure are closed too
                pingers[v.name] = _Pinger(v, endpoint, frame)
            for pinger in pingers.values():
                pinger.wait_ready(30.0, 0.2, "the echo process never answered")
            medians, lost = measure(pingers, frames, runs, gap_ms / 1e3, progress, lambda s: f"{s * 1e6:.0f} us")
        finally:
            for pinger in pingers.values():
                pinger.close()
    size = len(frame.to_bytes())
    result: dict[str, Any] = {"frame_bytes": size, "frames_per_run": frames, "runs": runs, "gap_ms": gap_ms}
    for name, ms in medians.items():
        median = statistics.median(ms)
        prefix = name.replace("+", "_")
        result[f"{prefix}_median_us"] = round(median * 1e6, 1)
        result[f"{prefix}_frames_per_s"] = round(1 / median, 1)
        result[f"{prefix}_mb_per_s"] = round(size / median / 1e6, 1)
    for ratio, (ours, raw) in RATIOS.items():
        # From the printed medians, so a reader dividing the two table cells gets the same ratio.
        result[ratio] = round(result[f"{ours.replace('+', '_')}_median_us"]
                              / result[f"{raw.replace('+', '_')}_median_us"], 3)
    result["run_medians_us"] = {v: [round(m * 1e6, 1) for m in ms] for v, ms in medians.items()}
    result["lost"] = lost
    return result


def print_table(console: Console, result: dict[str, Any]) -> None:
    table = Table("path", "median round trip (us)", "frames/s", "MB/s",
                  title=f"RGB-D frame {result['frame_bytes']} B through a router, median of "
                        f"{result['runs']} runs x {result['frames_per_run']} frames, "
                        f"{result['gap_ms']:g} ms apart")
    for v in VARIANTS:
        prefix = v.name.replace("+", "_")
        table.add_row(v.name, f"{result[f'{prefix}_median_us']:.0f}", f"{result[f'{prefix}_frames_per_s']:.0f}",
                      f"{result[f'{prefix}_mb_per_s']:.0f}")
    console.print(table)
    print_lost(console, result["lost"])
    console.print(f"overhead ratio (ovamos / raw): {result['overhead_ratio']:.3f} without shared memory, "
                  f"{result['shm_overhead_ratio']:.3f} with (ovamos+shm / raw+shm)")
