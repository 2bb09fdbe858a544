"""Transport benchmark over the inter-host link (``ovamos bench transport --tls``): what mTLS costs.

The laptop + robot deployment: a router per host, linked; a frame goes from a client of the
robot's router, over the link, to a client of the laptop's router, which acknowledges it back the
same way. Three links, up at once on this machine and measured in the same run, round trips
interleaved so drift hits all alike:

* ``tcp``: the routers linked over plain TCP (the ``laptop`` / ``robot`` profiles);
* ``tls``: the same link over TLS with mutual authentication (certificates from ``ovamos certs``);
* ``tls+acl``: the secure profiles' routers as shipped (``*-router-secure.json5``): mTLS and
  access control, whose refusals the router reads from Zenoh's trace (:mod:`ovamos.shared.bus.acl`).

Shared memory is off in the clients: between two hosts there is none, so the frame's bytes
cross the link. The frame is the 640x480 RGB-D test pattern on ``sensors/rgbd`` (the robot's
key, allowed over the secure link), the acknowledgement a small put on ``task/events``.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import statistics
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

from rich.console import Console
from rich.table import Table

from ovamos.bench.transport import AckedSender, measure, print_lost
from ovamos.services.diag.testpattern import pattern_frame
from ovamos.shared import keys
from ovamos.shared.bus.zconfig import build_config, open_session
from ovamos.shared.certs import init_ca, issue
from ovamos.shared.deploy import DEPLOY_DIR
from ovamos.shared.procs import (
    deferred_signals,
    free_port,
    run_dying_with_parent,
    signals_unwind,
    start_cli,
    stop,
    stop_spawned,
)

ROBOT = "bench"
FRAME, ACK = keys.rgbd(ROBOT), keys.task_events(ROBOT)
VARIANTS = ("tcp", "tls", "tls+acl")


def _client_config(endpoint: str) -> Any:
    cfg = build_config("client", connect=[endpoint])
    cfg.insert_json5("transport/shared_memory/enabled", "false")  # two hosts share no memory
    return cfg


def _echo(endpoint: str, ready: Any, stop_event: Any) -> None:
    """On the laptop: acknowledge every frame."""
    session = open_session(_client_config(endpoint))
    ack = session.declare_publisher(ACK)
    sub = session.declare_subscriber(FRAME, lambda s: ack.put(len(s.payload.to_bytes()).to_bytes(8, "little")))
    ready.set()
    stop_event.wait()
    sub.undeclare()
    session.close()


class _Link(AckedSender):
    """Two routers linked one way (``variant``), an echo on the laptop's, a pinger on the robot's.

    What it started is stopped by :meth:`close`, or at once when it fails to come up."""

    def __init__(self, variant: str, certs: Path, frame: bytes, ctx: Any, stop_event: Any) -> None:
        self.variant = variant
        self.routers: list[Any] = []
        self.echo: Any = None
        self.session: Any = None
        self._stop_event = stop_event
        try:
            self._start(certs, frame, ctx)
        except BaseException:
            self.close()
            raise

    def _start(self, certs: Path, frame: bytes, ctx: Any) -> None:
        variant, stop_event = self.variant, self._stop_event
        laptop, link, robot = free_port(), free_port(), free_port()
        proto = "tcp" if variant == "tcp" else "tls"
        lap_args = ["router", "--listen", f"tcp/127.0.0.1:{laptop}", "--listen", f"{proto}/127.0.0.1:{link}",
                    "--log-level", "WARNING"]
        rob_args = ["router", "--listen", f"tcp/127.0.0.1:{robot}", "--connect", f"{proto}/127.0.0.1:{link}",
                    "--log-level", "WARNING"]
        if variant != "tcp":
            lap_args += ["--certs", str(certs), "--cert", "laptop", "--robot-id", ROBOT]
            rob_args += ["--certs", str(certs), "--cert", "robot", "--robot-id", ROBOT]
        if variant == "tls+acl":
            lap_args += ["--config", str(DEPLOY_DIR / "zenoh" / "laptop-router-secure.json5")]
            rob_args += ["--config", str(DEPLOY_DIR / "zenoh" / "robot-router-secure.json5")]
        for args in (lap_args, rob_args):
            with deferred_signals():  # a signal waits until the router's handle is kept
                self.routers.append(start_cli(args))
        ready = ctx.Event()
        with deferred_signals():
            self.echo = ctx.Process(target=run_dying_with_parent,
                                    args=(os.getpid(), _echo, f"tcp/127.0.0.1:{laptop}", ready, stop_event))
            self.echo.start()
        if not ready.wait(60):
            raise TimeoutError(f"{variant}: the echo process did not start")
        self.acked = threading.Event()
        self.session = open_session(_client_config(f"tcp/127.0.0.1:{robot}"))
        self.pub = self.session.declare_publisher(FRAME)
        self.sub = self.session.declare_subscriber(ACK, lambda _s: self.acked.set())
        self.frame = frame

    def send(self) -> None:
        self.pub.put(self.frame)

    def close(self) -> None:
        """Close the pinger's session, then stop the echo (set ``stop_event`` first) and the routers."""
        with deferred_signals():
            if self.session is not None:
                self.session.close()
                self.session = None
            if self.echo is not None:
                self._stop_event.set()  # one event for every link's echo: they all end
                stop_spawned(self.echo)
            for router in self.routers:
                stop(router)


def run_tls_benchmark(frames: int = 200, runs: int = 5, gap_ms: float = 5.0,
                      progress: Console | None = None) -> dict[str, Any]:
    frame = bytes(pattern_frame(0, time.time()).to_bytes())
    ctx = mp.get_context("spawn")
    stop_echo = ctx.Event()
    links: dict[str, _Link] = {}
    with signals_unwind(), tempfile.TemporaryDirectory(prefix="ovamos-bench-tls-") as tmp:
        certs = Path(tmp)
        init_ca(certs)
        issue(certs, "laptop", hosts=["127.0.0.1"])
        issue(certs, "robot", hosts=["127.0.0.1"])
        try:
            for variant in VARIANTS:
                links[variant] = _Link(variant, certs, frame, ctx, stop_echo)
            for link in links.values():
                link.wait_ready(60.0, 0.3, f"{link.variant}: no frame crossed the link within 60 s")
            medians, lost = measure(links, frames, runs, gap_ms / 1e3, progress, lambda s: f"{s * 1e3:.2f} ms")
        finally:
            with deferred_signals():
                stop_echo.set()
                for link in links.values():
                    link.close()
    us = {v: round(statistics.median(m) * 1e6, 1) for v, m in medians.items()}
    return {
        "frame_bytes": len(frame), "frames_per_run": frames, "runs": runs, "gap_ms": gap_ms,
        **{f"{v.replace('+', '_')}_median_us": us[v] for v in VARIANTS},
        # from the printed medians, so dividing the table's cells gives the same ratios
        "tls_overhead_ratio": round(us["tls"] / us["tcp"], 3),
        "tls_acl_overhead_ratio": round(us["tls+acl"] / us["tcp"], 3),
        "run_medians_us": {v: [round(m * 1e6, 1) for m in ms] for v, ms in medians.items()},
        "lost": lost,
    }


def print_table(console: Console, result: dict[str, Any]) -> None:
    table = Table("link between the routers", "median round trip (ms)", "vs plain TCP",
                  title=f"RGB-D frame {result['frame_bytes']} B robot -> laptop and an ack back, over the "
                        f"link between two routers, median of {result['runs']} runs x "
                        f"{result['frames_per_run']} frames, {result['gap_ms']:g} ms apart")
    tcp = result["tcp_median_us"]
    for v in VARIANTS:
        value = result[f"{v.replace('+', '_')}_median_us"]
        table.add_row(v, f"{value / 1e3:.2f}", f"{value / tcp:.3f}")
    console.print(table)
    print_lost(console, result["lost"])
    console.print(f"TLS overhead ratio (tls / tcp): {result['tls_overhead_ratio']:.3f}; with access control: "
                  f"{result['tls_acl_overhead_ratio']:.3f}")
