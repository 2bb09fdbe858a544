"""``ovamos demo``: the whole system on this machine, driven through its HTTP API.

A router and every service (mapping, perception with the simulated backend,
planner, the simulated robot, the gateway) run as separate supervised
processes over real Zenoh on loopback, on free ports, with their configs and
logs under the output folder. The demo submits a search task over HTTP,
shows its progress live, then writes a report (JSON) and the map with the
robot's path (PNG) and stops everything. A recorder (``ovamos record``) runs
alongside and leaves the whole run in ``run.mcap`` (replay it, open it in Foxglove). The default episode is one the
method solves, so a first run shows a success; ``--seed``/``--episode``/
``--targets`` pick others.
"""

from __future__ import annotations

import json
import signal
import threading
import time
from pathlib import Path
from typing import Any, get_args

from rich.console import Console
from rich.live import Live
from rich.table import Table

from bench.episode import scene_mapping
from services.gateway.client import GatewayClient, GatewayError
from services.gateway.models import TaskView
from services.sim.episodes import make_episode
from services.sim.service import Motion
from ovamos.supervisor import Entry, Supervisor, port_open
from shared.procs import free_port, loopback

DEMO_SEED, DEMO_EPISODE = 0, 4
STARTUP_TIMEOUT_S = 90.0
SERVICES = ("mapping", "perception", "planner", "sim", "gateway")


BASES: tuple[str, ...] = get_args(Motion)  # the simulated robot's ways to move


def default_timeout_s(base: str) -> float:
    """Time for a search to use its whole step budget (500 commands) on this base.

    A kinematic base completes a primitive at once (a step costs ~0.2 s of rendering,
    perception, mapping and planning); a wheeled base drives it in real time: 1.3-1.9 s per
    primitive on the simulated Kobuki and OpenCR (0.26 m/s, 1 m/s^2, closed loop to 2 mm and
    0.2 deg), so a 500-step search needs ~15 min.
    """
    return 600.0 if base == "kinematic" else 1500.0


def write_configs(folder: Path, *, seed: int, episode: int, robot_id: str, http_port: int,
                  width: int = 320, height: int = 240, base: str = "kinematic") -> dict[str, Path]:
    """One JSON config per service, all describing the same episode (scene, start pose); ``base``
    is how the simulated robot moves (see ``SimServiceConfig.motion``)."""
    _, scene, _ = make_episode(seed, episode)
    mapping = scene_mapping(scene)
    episode_keys = {"episode_seed": seed, "episode_index": episode}
    configs: dict[str, dict[str, Any]] = {
        "mapping": {"grid_cells": mapping.grid_cells, "center": list(mapping.center), "publish_hz": 5.0,
                    "checkpoint_path": str(folder / "map.ckpt")},
        "perception": {"backend": "sim", "sim": episode_keys},
        "planner": {},
        "sim": {**episode_keys, "motion": base, "lock_step": True, "width": width, "height": height},
        "gateway": {"port": http_port, "robots": [robot_id], "state_dir": str(folder / "gateway")},
    }
    folder.mkdir(parents=True, exist_ok=True)
    paths = {}
    for name, config in configs.items():
        paths[name] = folder / f"{name}.json"
        paths[name].write_text(json.dumps(config, indent=1))
    return paths


def demo_entries(configs: dict[str, Path], *, robot_id: str, zenoh_port: int,
                 record: Path | None = None) -> list[Entry]:
    """The router, a recorder writing ``record`` (if given; it starts before the services and stops
    after them, so it holds the whole run) and the services."""
    router = Entry("router", ("router", "--listen", loopback(zenoh_port), "--log-level", "WARNING"),
                   ready=("127.0.0.1", zenoh_port))
    recorder = [] if record is None else [Entry("record", ("record", "--robot-id", robot_id, "--out", str(record),
                                                           "--overwrite", "--connect", loopback(zenoh_port)))]
    return [router, *recorder] + [Entry(name, ("run", name, "--robot-id", robot_id, "--config", str(configs[name]),
                                               "--connect", loopback(zenoh_port)))
                                  for name in SERVICES]


def _progress(view: TaskView | None, elapsed: float) -> Table:
    table = Table(title=f"search task ({elapsed:.0f} s)", show_header=False)
    if view is None:
        table.add_row("status", "starting the services ...")
        return table
    table.add_row("status", view.status.value + (f" ({view.message})" if view.message else ""))
    table.add_row("targets", ", ".join(view.targets))
    table.add_row("found", ", ".join(f"{f.label} at ({f.x:.1f}, {f.y:.1f}) step {f.step}"
                                     for f in view.found) or "-")
    table.add_row("steps", f"{view.steps} / {view.max_steps}")
    table.add_row("distance", f"{view.distance_m:.2f} m")
    return table


def _wait_for_services(client: GatewayClient, robot_id: str, deadline: float) -> None:
    """Until every service of the robot shows its liveliness token (the gateway asks Zenoh)."""
    while time.monotonic() < deadline:
        try:
            robot = client.health()["robots"][robot_id]
            if {s["service"] for s in robot["services"]} >= set(SERVICES):
                return
        except GatewayError:
            pass
        time.sleep(0.5)
    raise TimeoutError(f"the services did not all come up within {STARTUP_TIMEOUT_S:.0f} s "
                       f"(see the logs)")


def run_demo(console: Console, *, out_dir: Path, seed: int = DEMO_SEED, episode: int = DEMO_EPISODE,
             targets: list[str] | None = None, robot_id: str = "sim", keep_running: bool = False,
             timeout_s: float | None = None, base: str = "kinematic", record: Path | None = None) -> int:
    """Run the demo; ``record``: the MCAP file to record the run to (None: no recording)."""
    spec, _, _ = make_episode(seed, episode)
    targets = targets or list(spec.targets)
    http_port, zenoh_port = free_port(), free_port()
    configs = write_configs(out_dir / "config", seed=seed, episode=episode, robot_id=robot_id,
                            http_port=http_port, base=base)
    url = f"http://127.0.0.1:{http_port}"
    console.print(f"episode {spec.episode_id}: {', '.join(targets)}; gateway {url}; "
                  f"logs in {out_dir / 'logs'}")
    started = time.monotonic()
    entries = demo_entries(configs, robot_id=robot_id, zenoh_port=zenoh_port, record=record)
    with Supervisor(entries, log_dir=out_dir / "logs") as supervisor, GatewayClient(url) as client:
        deadline = started + STARTUP_TIMEOUT_S
        while not port_open("127.0.0.1", http_port) and time.monotonic() < deadline:
            time.sleep(0.2)
        _wait_for_services(client, robot_id, deadline)
        view = _search(console, client, targets, robot_id, started,
                       default_timeout_s(base) if timeout_s is None else timeout_s)
        report = _write_results(console, client, view, out_dir, robot_id, seed, episode,
                                time.monotonic() - started, supervisor)
        if keep_running:
            _serve_until_interrupted(console, url, robot_id)
    if record is not None:  # complete once the supervisor stopped the recorder, after the services
        console.print(f"recorded the run to {record} (ovamos replay {record}; or open it in Foxglove)")
    return 0 if report["task"]["status"] == "done" else 1


def _search(console: Console, client: GatewayClient, targets: list[str], robot_id: str, started: float,
            timeout_s: float) -> TaskView:
    accepted = client.submit(targets, robot_id=robot_id)
    view = client.get(accepted.id)
    with Live(_progress(view, 0.0), console=console, refresh_per_second=4) as live:
        deadline = time.monotonic() + timeout_s
        while not view.final and time.monotonic() < deadline:
            time.sleep(0.5)
            view = client.get(accepted.id)
            live.update(_progress(view, time.monotonic() - started))
    if not view.final:
        view = client.cancel(accepted.id)
    return view


def _write_results(console: Console, client: GatewayClient, view: TaskView, out_dir: Path, robot_id: str,
                   seed: int, episode: int, seconds: float, supervisor: Supervisor) -> dict[str, Any]:
    out_dir.mkdir(parents=True, exist_ok=True)
    map_path = out_dir / "demo_map.png"
    try:
        map_path.write_bytes(client.map_png(robot_id))
    except GatewayError as exc:
        console.print(f"[yellow]no map image:[/yellow] {exc}")
    report = {"episode": f"{seed}-{episode}", "seconds": round(seconds, 1),
              "task": json.loads(view.model_dump_json()),
              "restarts": {s.name: s.restarts for s in supervisor.status()}}
    (out_dir / "demo_report.json").write_text(json.dumps(report, indent=1))
    found = ", ".join(f.label for f in view.found) or "nothing"
    colour = "green" if view.status.value == "done" else "red"
    console.print(f"[{colour}]{view.status.value}[/{colour}]: found {found} in {view.steps} steps, "
                  f"{view.distance_m:.1f} m; report {out_dir / 'demo_report.json'}, map {map_path}")
    return report


def _serve_until_interrupted(console: Console, url: str, robot_id: str) -> None:
    console.print(f"Everything keeps running. Operator page: {url}/ (API docs: {url}/docs). Try:\n"
                  f"  curl -X POST {url}/v1/tasks -H 'Content-Type: application/json' "
                  f"-d '{{\"targets\": [\"bed\"], \"robot_id\": \"{robot_id}\"}}'\n"
                  f"Ctrl-C stops everything.")
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    stop.wait()
