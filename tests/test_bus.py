"""The bus between real Zenoh sessions (router and clients in this process)."""

from __future__ import annotations

import queue
import threading
import time

import numpy as np
import pytest
import zenoh

from ovamos.services.diag.testpattern import pattern_frame
from ovamos.shared import keys
from ovamos.shared.bus import Bus
from ovamos.shared.bus.status import live_services
from ovamos.shared.bus.zconfig import build_config
from ovamos.shared.messages import JsonMessage, RgbdFrame
from tests.polling import wait_for


class Note(JsonMessage):
    text: str


@pytest.fixture
def open_bus(inproc_router: str):
    buses: list[Bus] = []

    def open_(service: str, instance: str = "0", robot_id: str = "r1") -> Bus:
        bus = Bus.open(build_config(connect=[inproc_router]), robot_id, service, instance)
        buses.append(bus)
        return bus

    yield open_
    for bus in buses:
        bus.close()


def _send_until(pub, msg, received: threading.Event, timeout: float = 10.0) -> None:
    """Publish until a subscriber has it: declarations propagate asynchronously."""
    wait_for(lambda: pub.put(msg) or received.wait(0.1), timeout, "delivery")


def test_typed_messages_arrive_intact(open_bus) -> None:
    a, b = open_bus("a"), open_bus("b")
    got: queue.Queue[RgbdFrame] = queue.Queue()
    arrived = threading.Event()
    b.subscribe(keys.rgbd("r1"), RgbdFrame, lambda f: (got.put(f), arrived.set()), keep=1)
    frame = pattern_frame(7, 123.25, width=64, height=48, seed=3)
    _send_until(a.publisher(keys.rgbd("r1"), RgbdFrame), frame, arrived)
    out = got.get(timeout=5)
    assert out.seq == 7 and out.stamp == 123.25
    assert out.intrinsics == frame.intrinsics and out.camera_pose == frame.camera_pose
    assert np.array_equal(out.rgb, frame.rgb) and np.array_equal(out.depth, frame.depth)
    assert b.counters.snapshot()[keys.rgbd("r1")].received >= 1
    assert a.counters.snapshot()[keys.rgbd("r1")].published >= 1


def test_publisher_refuses_the_wrong_type(open_bus) -> None:
    pub = open_bus("a").publisher(keys.task_events("r1"), Note)
    with pytest.raises(TypeError, match="carries Note"):
        pub.put(pattern_frame(0, 0.0, width=8, height=8))


def test_malformed_and_failing_messages_are_counted_and_service_keeps_serving(
        open_bus, client: zenoh.Session) -> None:
    bus = open_bus("svc")
    key = keys.task_events("r1")
    seen: list[str] = []
    ok = threading.Event()

    def handler(note: Note) -> None:
        if note.text == "boom":
            raise RuntimeError("handler bug")
        seen.append(note.text)
        ok.set()

    bus.subscribe(key, Note, handler)
    wait_for(lambda: client.put(key, Note(text="hello").to_bytes()) or ok.wait(0.1),
             what="first delivery")
    for garbage in (b"", b"\x00\xff", b'{"v": 1}', b'{"v": 2, "text": "x"}', b"[1, 2]"):
        client.put(key, garbage)
    client.put(key, Note(text="boom").to_bytes())
    ok.clear()
    client.put(key, Note(text="after").to_bytes())
    assert ok.wait(5)
    counters = wait_for(lambda: (c := bus.counters.snapshot()[key]).malformed == 5 and c.errors == 1
                        and c, what="counters")
    assert seen[-1] == "after"
    assert counters.received >= 8
    # and it still answers health queries
    (svc,) = [s for s in live_services(client, "r1") if s.service == "svc"]
    assert svc.stats is not None and svc.stats.counters[key].malformed == 5


def test_latest_only_drops_stale_frames_and_counts_them(open_bus, client: zenoh.Session) -> None:
    bus = open_bus("slow")
    key = keys.rgbd("r1")
    release, first = threading.Event(), threading.Event()
    handled: list[int] = []

    def slow(frame: RgbdFrame) -> None:
        first.set()
        release.wait(10)
        handled.append(frame.seq)

    bus.subscribe(key, RgbdFrame, slow, keep=1)
    wait_for(lambda: client.put(key, pattern_frame(0, 0.0, width=8, height=8).to_bytes())
             or first.wait(0.1), what="first frame")
    # BLOCK: this test is about the mailbox dropping frames, so Zenoh itself must drop none
    # (a put's default congestion control drops when a busy machine lets the queue fill)
    for seq in range(1, 21):
        client.put(key, pattern_frame(seq, 0.0, width=8, height=8).to_bytes(),
                   congestion_control=zenoh.CongestionControl.BLOCK)
    wait_for(lambda: bus.counters.snapshot()[key].received >= 21, what="all frames received")
    release.set()
    wait_for(lambda: handled and handled[-1] == 20, what="the newest frame handled")
    counters = bus.counters.snapshot()[key]
    # one frame is in the handler, one waits in the mailbox: everything else was dropped
    assert len(handled) <= 3
    assert counters.dropped == counters.received - len(handled)


def test_liveliness_follows_open_and_close(open_bus, client: zenoh.Session) -> None:
    bus = open_bus("mapping", "7")
    wait_for(lambda: [s for s in live_services(client, "r1") if s.instance == "7"],
             what="token visible")
    bus.close()
    wait_for(lambda: not [s for s in live_services(client, "r1") if s.instance == "7"],
             what="token gone")


def test_ids_that_would_break_keys_are_refused(client: zenoh.Session) -> None:
    with pytest.raises(keys.KeyExprError):
        Bus(client, "robot/1", "svc", "0")
    with pytest.raises(keys.KeyExprError):
        Bus(client, "r1", "svc", "*")


def test_close_waits_for_the_handler_being_run(open_bus) -> None:
    """Handlers run on the bus's dispatcher thread: closing the bus lets the one in progress
    finish (a handler that signals before its last step must not be cut off by the close)."""
    a, b = open_bus("a"), open_bus("b")
    started, finished = threading.Event(), threading.Event()

    def slow(_note: Note) -> None:
        started.set()
        time.sleep(0.3)
        finished.set()

    b.subscribe(keys.task_events("r1"), Note, slow)
    _send_until(a.publisher(keys.task_events("r1"), Note), Note(text="x"), started)
    b.close()
    assert finished.is_set()


def test_large_payloads_go_through_shared_memory_and_small_ones_do_not(open_bus, client) -> None:
    """A 640x480 frame is put as a buffer of the bus's own pool, which a subscriber on this host
    receives by reference (Zenoh hands it a shared buffer); a small message is put as bytes."""
    bus = open_bus("camera")
    assert bus.shm is not None  # shared memory is on in Zenoh's default config
    shared: dict[str, bool] = {}
    sub = client.declare_subscriber("ovamos/r1/**", lambda s: shared.setdefault(
        str(s.key_expr), s.payload.as_shm() is not None))
    frames, notes = bus.publisher(keys.rgbd("r1"), RgbdFrame), bus.publisher(keys.bench("r1", "note"), Note)
    wait_for(lambda: frames.put(pattern_frame(1, 0.0)) or keys.rgbd("r1") in shared, 10, "a frame arrives")
    wait_for(lambda: notes.put(Note(text="small")) or keys.bench("r1", "note") in shared, 10, "a note arrives")
    sub.undeclare()
    assert shared == {keys.rgbd("r1"): True, keys.bench("r1", "note"): False}
    assert bus.stats().info["shm_shared"] >= 1 and bus.stats().info["shm_fallbacks"] == 0


def test_a_config_with_shared_memory_off_puts_bytes(inproc_router: str) -> None:
    cfg = build_config(connect=[inproc_router])
    cfg.insert_json5("transport/shared_memory/enabled", "false")
    with Bus.open(cfg, "r1", "camera") as bus:
        assert bus.shm is None and "shm_shared" not in bus.stats().info
