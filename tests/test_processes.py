"""Services as separate OS processes through a router: what a deployment relies on."""

from __future__ import annotations

import hashlib
import multiprocessing as mp
import signal
import threading
import time

import pytest

from ovamos.services.diag.testpattern import pattern_frame
from ovamos.shared import keys
from ovamos.shared.bus import Bus
from ovamos.shared.bus.status import live_services
from ovamos.shared.bus.zconfig import build_config, open_session
from ovamos.shared.messages import RgbdFrame
from ovamos.shared.procs import free_port, kill, loopback, stop
from tests.polling import port_open, status_cli, wait_for

pytestmark = pytest.mark.system  # processes, routers, browsers or real-time devices: make test-all

SEED = 11


def _digest(frame: RgbdFrame) -> tuple:
    return (frame.seq, frame.camera_pose, frame.intrinsics.model_dump(),
            hashlib.sha256(frame.rgb.tobytes()).hexdigest(),
            hashlib.sha256(frame.depth.tobytes()).hexdigest(), frame.rgb.shape, str(frame.depth.dtype))


def _publisher(endpoint: str, stop) -> None:
    with Bus.open(build_config(connect=[endpoint]), "r1", "sender") as bus:
        pub = bus.publisher(keys.rgbd("r1"), RgbdFrame)
        seq = 0
        while not stop.wait(0.05):
            pub.put(pattern_frame(seq, 0.0, seed=SEED))
            seq += 1


def _receiver(endpoint: str, results) -> None:
    got = threading.Event()

    def on_frame(frame: RgbdFrame) -> None:
        if not got.is_set():
            got.set()
            results.put(_digest(frame))

    with Bus.open(build_config(connect=[endpoint]), "r1", "receiver") as bus:
        bus.subscribe(keys.rgbd("r1"), RgbdFrame, on_frame, keep=1)
        got.wait(60)


def test_two_spawned_processes_exchange_a_full_frame_intact(router_port: int) -> None:
    endpoint = loopback(router_port)
    ctx = mp.get_context("spawn")
    stop, results = ctx.Event(), ctx.Queue()
    procs = [ctx.Process(target=_receiver, args=(endpoint, results)),
             ctx.Process(target=_publisher, args=(endpoint, stop))]
    try:
        for p in procs:
            p.start()
        received = results.get(timeout=60)
    finally:
        stop.set()
        for p in procs:
            p.join(20)
            if p.is_alive():
                p.kill()
                p.join()
    expected = pattern_frame(received[0], 0.0, seed=SEED)
    assert expected.rgb.shape == (480, 640, 3)
    assert received == _digest(expected)
    assert all(p.exitcode == 0 for p in procs)


def _instances(port: int, service: str) -> list[str]:
    return [s["instance"] for s in status_cli(port) if s["service"] == service]


def test_killed_service_disappears_from_status_and_reappears_when_restarted(cli, router_port) -> None:
    args = ["run", "monitor", "--connect", loopback(router_port), "--robot-id", "r1",
            "--instance", "k1", "--log-level", "WARNING"]
    proc = cli(*args)
    wait_for(lambda: _instances(router_port, "monitor") == ["k1"], what="monitor in status")
    kill(proc)
    wait_for(lambda: _instances(router_port, "monitor") == [], what="monitor gone from status")
    cli(*args)
    wait_for(lambda: _instances(router_port, "monitor") == ["k1"], what="monitor back in status")


def test_sigterm_stops_a_service_cleanly(cli, router_port) -> None:
    proc = cli("run", "monitor", "--connect", loopback(router_port), "--robot-id", "r1",
               "--instance", "t1", "--log-level", "WARNING")
    wait_for(lambda: _instances(router_port, "monitor") == ["t1"], what="monitor up")
    assert stop(proc, timeout=10) == 0
    assert _instances(router_port, "monitor") == []


def test_a_service_waiting_for_its_router_dies_on_sigterm(cli) -> None:
    proc = cli("run", "monitor", "--connect", loopback(free_port()), "--log-level", "WARNING")
    time.sleep(1.0)
    assert proc.poll() is None  # still waiting for a router that never comes
    assert stop(proc, timeout=10) == -signal.SIGTERM


def test_clients_survive_a_router_restart(cli) -> None:
    port = free_port()
    router_args = ["router", "--listen", loopback(port), "--log-level", "WARNING"]
    router = cli(*router_args)
    wait_for(lambda: port_open(port), what="router")
    common = ["--connect", loopback(port), "--robot-id", "r1", "--log-level", "WARNING"]
    cli("run", "testpattern", *common, "--config", "tests/data/small_testpattern.toml")
    cli("run", "monitor", *common)

    def frames_seen() -> int:
        session = open_session(build_config(connect=[loopback(port)]))
        try:
            for s in live_services(session, "r1", timeout_s=1.0):
                if s.service == "monitor" and s.stats:
                    c = s.stats.counters.get(keys.rgbd("r1"))
                    return c.received if c else 0
            return 0
        finally:
            session.close()

    before = wait_for(frames_seen, what="frames before the restart")
    kill(router)
    cli(*router_args)
    wait_for(lambda: port_open(port), what="router restarted")
    # same service processes, never restarted: their frames flow again
    wait_for(lambda: frames_seen() > before + 5, what="frames after the restart")
    names = sorted(s["service"] for s in status_cli(port, "r1"))
    assert names == ["monitor", "testpattern"]


def test_malformed_frames_are_counted_by_a_running_service(cli, router_port) -> None:
    cli("run", "monitor", "--connect", loopback(router_port), "--robot-id", "r1",
        "--log-level", "ERROR")
    wait_for(lambda: _instances(router_port, "monitor"), what="monitor up")
    session = open_session(build_config(connect=[loopback(router_port)]))
    try:
        good = bytes(pattern_frame(0, 0.0, width=16, height=12).to_bytes())
        bad = bytearray(good)
        bad[0:4] = b"JUNK"

        def rgbd_counters():
            (monitor,) = [s for s in status_cli(router_port, "r1") if s["service"] == "monitor"]
            return monitor["stats"]["counters"].get(keys.rgbd("r1"))

        # a new session learns of subscribers asynchronously: warm the route with good frames
        warm = wait_for(lambda: session.put(keys.rgbd("r1"), good) or rgbd_counters(),
                        what="a good frame reaching the monitor")["received"]
        for payload in (bytes(bad), b"not a frame", good[:100]):
            session.put(keys.rgbd("r1"), payload)
        wait_for(lambda: rgbd_counters()["malformed"] == 3, what="3 malformed counted")
        session.put(keys.rgbd("r1"), good)
        wait_for(lambda: rgbd_counters()["received"] >= warm + 4, what="a good frame after the bad ones")
        assert rgbd_counters()["malformed"] == 3
    finally:
        session.close()
