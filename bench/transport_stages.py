"""Where a frame round trip's time goes, stage by stage: raw Zenoh beside the ovamos bus.

``ovamos bench transport`` gives one number per path; this splits the round trip of four of
its variants (``raw`` and ``ovamos``, with shared memory off and with the sender's own pool) into stages
timed across the two processes with ``time.perf_counter`` (CLOCK_MONOTONIC on Linux: one
clock for every process of the host). The echo sends its own timestamps back in the ack, so
each round trip's stages come from one frame. The bus is timed through its transport hooks
(:class:`StageBus` overrides ``_listen`` and ``_publish``), so the bus code measured is the
one the services run, plus two clock reads per message.

Stages (raw has no encode, hand-off or decode; its "to handler" is the payload copy its
callback makes, as the bus's read does):

* ``encode``: the sender's ``put`` call until the payload reaches Zenoh's put;
* ``put``: Zenoh's put of the 2.15 MB payload (fragments queued for the link; with shared memory,
  the allocation and copy into the pool, and a reference queued);
* ``to echo``: Zenoh's put started until the echo's subscriber callback ran;
* ``to handler``: the echo's callback until its handler has the decoded frame (hand-off to the
  node's thread, payload copy, decode and validation);
* ``ack``: the echo's handler until the sender's ack callback (encode and put the ack, the link);
* ``to waiter``: the sender's ack callback until the waiting thread runs again (for the bus:
  the sender's event loop has taken the ack from the inbox and decoded it).
"""

from __future__ import annotations

import statistics
import threading
import time
from collections.abc import Callable
from typing import Any

import zenoh
from rich.console import Console
from rich.table import Table

from ovamos.bench.transport import (
    LOST_AFTER_S,
    RATIOS,
    VARIANTS,
    WARMUP,
    Variant,
    echo_processes,
    interleave,
    loop_waiter,
    wait_ready,
)
from ovamos.services.diag.testpattern import pattern_frame
from ovamos.shared import keys
from ovamos.shared.bus import Bus
from ovamos.shared.bus.zconfig import open_session
from ovamos.shared.messages import JsonMessage, RgbdFrame

__all__ = ["STAGES", "StageBus", "run_stages", "print_stages"]

STAGES = ("encode", "put", "to echo", "to handler", "ack", "to waiter")
#: raw Zenoh and the bus, on the network path and through the sender's own shared-memory pool
_PATHS = tuple(v for v in VARIANTS if v.shm in ("off", "provider"))


class StampedAck(JsonMessage):
    """The echo's acknowledgement with its timestamps: callback ran, handler ran."""

    arrived: float
    handled: float


class StageBus(Bus):
    """The bus with clock reads at its transport hooks: when each key's latest sample arrived
    (before the inbox), and when each payload reached and left Zenoh's put."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        self.arrived: dict[str, float] = {}
        self.put_started = self.put_ended = 0.0
        super().__init__(*args, **kwargs)

    def _listen(self, key_expr: str, on_payload: Callable[[str, Callable[[], bytes]], None]
                ) -> Callable[[], None]:
        def stamped(key: str, read: Callable[[], bytes]) -> None:
            self.arrived[key] = time.perf_counter()
            on_payload(key, read)

        return super()._listen(key_expr, stamped)

    def _publish(self, key: str, block: bool = False
                 ) -> tuple[Callable[[bytes | bytearray], None], Callable[[], None]]:
        put, undeclare = super()._publish(key, block)

        def stamped(payload: bytes | bytearray) -> None:
            self.put_started = time.perf_counter()
            put(payload)
            self.put_ended = time.perf_counter()

        return stamped, undeclare


def _echo(variant: Variant, endpoint: str, stop_event: Any) -> None:
    """Acknowledge every frame with the times its callback and its handler ran."""
    cfg = variant.config(endpoint)
    frame_key, ack_key = keys.rgbd(variant.robot), keys.bench(variant.robot, "ack")
    if variant.path == "raw":
        session = open_session(cfg)
        ack = session.declare_publisher(ack_key)

        def on_frame(sample: zenoh.Sample) -> None:
            arrived = time.perf_counter()
            sample.payload.to_bytes()
            ack.put(StampedAck(arrived=arrived, handled=time.perf_counter()).to_bytes())

        sub = session.declare_subscriber(frame_key, on_frame)
        stop_event.wait()
        sub.undeclare()
        session.close()
        return
    with StageBus.open(cfg, variant.robot, "bench-echo") as bus:
        pub = bus.publisher(ack_key, StampedAck)
        bus.subscribe(frame_key, RgbdFrame, lambda _f: pub.put(StampedAck(
            arrived=bus.arrived[frame_key], handled=time.perf_counter())), keep=1)
        stop_event.wait()


class _StageSender:
    """Sends frames on one path and splits each round trip into :data:`STAGES`."""

    def __init__(self, variant: Variant, endpoint: str, frame: RgbdFrame) -> None:
        self._acked = threading.Event()
        self._ack: bytes | StampedAck | None = None  # raw: decoded after the waiter woke
        self._ack_arrived = 0.0
        cfg = variant.config(endpoint)
        frame_key, ack_key = keys.rgbd(variant.robot), keys.bench(variant.robot, "ack")
        if variant.path == "raw":
            session = open_session(cfg)
            payload = bytes(frame.to_bytes())
            pub = session.declare_publisher(frame_key)
            wrap = variant.raw_wrap()

            def on_ack(sample: zenoh.Sample) -> None:
                self._ack_arrived = time.perf_counter()
                self._ack = sample.payload.to_bytes()
                self._acked.set()

            session.declare_subscriber(ack_key, on_ack)

            def send() -> tuple[float, float]:
                started = time.perf_counter()
                pub.put(wrap(payload))
                return started, time.perf_counter()

            self._send: Callable[[], tuple[float, float]] = send
            self._wait: Callable[[float], bool] = self._acked.wait
            self.close: Callable[[], None] = session.close
        else:
            # The measuring thread is the sender's event loop, as in ovamos.bench.transport.
            bus = StageBus.open(cfg, variant.robot, "bench-client", dispatch="caller")
            frame_pub = bus.publisher(frame_key, RgbdFrame)

            def on_bus_ack(ack: StampedAck) -> None:
                self._ack_arrived, self._ack = bus.arrived[ack_key], ack
                self._acked.set()

            bus.subscribe(ack_key, StampedAck, on_bus_ack)

            def send_bus() -> tuple[float, float]:
                frame_pub.put(frame)
                return bus.put_started, bus.put_ended

            self._send, self._wait, self.close = send_bus, loop_waiter(bus, self._acked), bus.close

    def round_trip(self, timeout: float) -> dict[str, float] | None:
        """Each stage's seconds and the whole round trip's ("round trip"); None when no ack came."""
        self._acked.clear()
        start = time.perf_counter()
        put_started, put_ended = self._send()
        if not self._wait(timeout):
            return None
        woke = time.perf_counter()
        ack = StampedAck.from_bytes(self._ack) if isinstance(self._ack, bytes) else self._ack
        assert ack is not None
        return {"encode": put_started - start, "put": put_ended - put_started,
                "to echo": ack.arrived - put_started, "to handler": ack.handled - ack.arrived,
                "ack": self._ack_arrived - ack.handled, "to waiter": woke - self._ack_arrived,
                "round trip": woke - start}


def run_stages(frames: int = 200, gap_ms: float = 5.0, ready_timeout_s: float = 30.0) -> dict[str, Any]:
    """Median microseconds of each stage per path, over ``frames`` round trips per path
    (:func:`~ovamos.bench.transport.interleave`: after its warm-up, the paths alternating, ``gap_ms``
    apart; over 10 % lost fails); and frames lost."""
    frame = pattern_frame(0, time.time())
    lost = {v.name: 0 for v in _PATHS}
    with echo_processes(_echo, _PATHS) as endpoint:
        senders: dict[str, _StageSender] = {}
        try:
            for v in _PATHS:  # one by one: those made before a failure are closed too
                senders[v.name] = _StageSender(v, endpoint, frame)
            for sender in senders.values():
                wait_ready(sender.round_trip, ready_timeout_s, 0.2, "the echo process never answered")
            samples = interleave({name: sender.round_trip for name, sender in senders.items()}, frames,
                                 gap_ms / 1e3, lost, (WARMUP + frames) // 10)
        finally:
            for sender in senders.values():
                sender.close()
    medians = {name: {stage: round(statistics.median(s[stage] for s in rows) * 1e6, 1)
                      for stage in (*STAGES, "round trip")}
               for name, rows in samples.items() if rows}
    return {"frame_bytes": len(frame.to_bytes()), "frames": frames, "gap_ms": gap_ms,
            "median_us": medians, "lost": lost}


def print_stages(console: Console, result: dict[str, Any]) -> None:
    medians = result["median_us"]
    paths = list(medians)
    pairs = [(ours, raw) for ours, raw in RATIOS.values() if ours in medians and raw in medians]
    table = Table("stage", *(f"{p} (us)" for p in paths), *(f"{ours} - {raw} (us)" for ours, raw in pairs),
                  title=f"Where a {result['frame_bytes']} B frame's round trip goes: medians of "
                        f"{result['frames']} round trips per path, {result['gap_ms']:g} ms apart "
                        f"(stages are medians each: they need not add up to the round trip)")
    for stage in (*STAGES, "round trip"):
        table.add_row(stage, *(f"{medians[p][stage]:.0f}" for p in paths),
                      *(f"{medians[ours][stage] - medians[raw][stage]:+.0f}" for ours, raw in pairs))
    console.print(table)
    if any(result["lost"].values()):
        console.print(f"frames lost (no ack within {LOST_AFTER_S:g} s): {result['lost']}")
