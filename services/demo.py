"""``ovamos demo``: the most complete system that runs end to end today.

At this stage that is a Zenoh router, a test-pattern camera, the mapping
service and a monitor, each its own process on loopback, exchanging real RGB-D
frames; the demo watches them through the same liveliness and stats queries
``ovamos status`` uses, draws the resulting map to a PNG, then shuts
everything down. It ends by saying what is still missing.
"""

from __future__ import annotations

import subprocess
import time
from pathlib import Path
from typing import Any

from rich.console import Console
from rich.live import Live
from rich.table import Table

from services.mapping.render import render_map, write_png
from services.registry import PLANNED
from shared import keys
from shared.procs import free_port, loopback, start_cli, stop
from shared.messages import MapSnapshot
from shared.status import LiveService, live_services
from shared.zconfig import build_config, open_session

DEMO_SERVICES = ("testpattern", "mapping", "monitor")
STARTUP_TIMEOUT_S = 30.0


def _table(services: list[LiveService], elapsed: float) -> Table:
    table = Table(title=f"ovamos demo: {elapsed:4.1f} s", show_lines=False)
    for column in ("service", "pid", "published", "received", "dropped", "malformed", "detail"):
        table.add_column(column)
    for s in services:
        c = s.stats.counters if s.stats else {}
        total = {f: sum(getattr(v, f) for v in c.values())
                 for f in ("published", "received", "dropped", "malformed")}
        table.add_row(f"{s.service}/{s.instance}", str(s.stats.pid) if s.stats else "?",
                      *(str(total[f]) for f in ("published", "received", "dropped", "malformed")),
                      _detail(s.stats.info if s.stats else {}))
    return table


def _detail(info: dict[str, Any]) -> str:
    lines = [f"{row['key']}: {row['rate_hz']:.1f} Hz, {row['mbytes_per_s']:.1f} MB/s, "
             f"latency {row['median_latency_ms'] or 0:.1f} ms" for row in info.get("streams", [])]
    if "frames_sent" in info:
        lines.append(f"{info['frames_sent']} frames sent")
    return "\n".join(lines)


def run_demo(console: Console, *, seconds: float, robot_id: str, out_dir: Path) -> int:
    """Run the demo; 0 when frames flowed intact from camera to monitor and into the map."""
    endpoint = loopback(free_port())
    common = ["--connect", endpoint, "--robot-id", robot_id, "--log-level", "WARNING"]
    console.print(f"[bold]Starting[/bold] a Zenoh router on {endpoint} and services "
                  f"{', '.join(DEMO_SERVICES)}, each in its own process.")
    procs: list[subprocess.Popen] = [start_cli(["router", "--listen", endpoint,
                                                "--log-level", "WARNING"])]
    procs += [start_cli(["run", name, *common]) for name in DEMO_SERVICES]
    session = open_session(build_config(connect=[endpoint]))
    services: list[LiveService] = []
    try:
        with console.status("waiting for the services to come up"):
            _wait_until_up(session, robot_id)
        start = time.monotonic()  # the clock starts once everything runs: slow start-ups don't count
        with Live(console=console, refresh_per_second=4) as live:
            while (elapsed := time.monotonic() - start) < seconds:
                services = live_services(session, robot_id, timeout_s=1.0)
                live.update(_table(services, elapsed))
                time.sleep(0.5)
        map_png = _draw_map(session, robot_id, out_dir)
    finally:
        session.close()
        for proc in reversed(procs):
            stop(proc)
    console.print()
    ok = _verdict(console, services, robot_id)
    if map_png is not None:
        console.print(f"The map the mapping service built from those frames: {map_png}")
    console.print("\n[bold]Not in this demo yet[/bold] (each service arrives with its issue): " +
                  ", ".join(f"{name} (#{issue})" for name, issue in PLANNED.items()) +
                  ". The full demo (simulated robot searching a home for targets submitted over "
                  "HTTP) replaces this one with the gateway issue.")
    return 0 if ok else 1


def _draw_map(session: Any, robot_id: str, out_dir: Path) -> Path | None:
    for reply in session.get(keys.map_snapshot(robot_id), timeout=5.0):
        if reply.ok is not None:
            snapshot = MapSnapshot.from_bytes(reply.ok.payload.to_bytes())
            out_dir.mkdir(parents=True, exist_ok=True)
            return write_png(out_dir / "demo_map.png", render_map(snapshot))
    return None


def _wait_until_up(session: Any, robot_id: str, timeout_s: float = STARTUP_TIMEOUT_S) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        up = {s.service for s in live_services(session, robot_id, timeout_s=1.0)}
        if up >= set(DEMO_SERVICES):
            return
        time.sleep(0.2)


def _verdict(console: Console, services: list[LiveService], robot_id: str) -> bool:
    by_name = {s.service: s for s in services if s.stats}
    missing = [name for name in DEMO_SERVICES if name not in by_name]
    if missing:
        console.print(f"[red]FAILED[/red]: {', '.join(missing)} never reported.")
        return False
    frames = by_name["monitor"].stats.counters.get(keys.rgbd(robot_id))
    if frames is None or frames.received == 0 or frames.malformed:
        console.print(f"[red]FAILED[/red]: the monitor saw no valid frames ({frames}).")
        return False
    mapped = by_name["mapping"].stats.info.get("seq", -1)
    if mapped < 0:
        console.print("[red]FAILED[/red]: the mapping service fused no frame.")
        return False
    console.print(f"[green]OK[/green]: {frames.received} RGB-D frames crossed the router from "
                  f"testpattern to monitor, {frames.malformed} malformed; the map fused frames up "
                  f"to seq {mapped}.")
    return True
