"""The ``ovamos`` command line."""

from __future__ import annotations

import json
import logging
import threading
from pathlib import Path
from typing import Annotated, Optional

import typer
from rich.console import Console
from rich.table import Table

from shared import __version__
from shared.log import setup_logging
from shared.zconfig import ZenohConfigError, build_config, open_session

app = typer.Typer(add_completion=False, no_args_is_help=True,
                  help="OVAMOS multi-object search over Zenoh.")
bench_app = typer.Typer(no_args_is_help=True, help="Benchmarks (results print as tables).")
app.add_typer(bench_app, name="bench")
console = Console()
err = Console(stderr=True)

ZenohFile = Annotated[Optional[Path], typer.Option("--zenoh", help="Zenoh config (json5).")]
Connect = Annotated[Optional[list[str]], typer.Option(help="Endpoint to connect to (repeatable).")]
Listen = Annotated[Optional[list[str]], typer.Option(help="Endpoint to listen on (repeatable).")]
RobotId = Annotated[str, typer.Option("--robot-id", help="Robot whose keys to use.")]
LogJson = Annotated[bool, typer.Option("--log-json", help="Log JSON lines.")]
LogLevel = Annotated[str, typer.Option("--log-level")]


def _fail(message: str) -> typer.Exit:
    err.print(f"[red]error:[/red] {message}")
    return typer.Exit(2)


def _version(value: bool) -> None:
    if value:
        console.print(f"ovamos {__version__}")
        raise typer.Exit()


@app.callback()
def _main(version: Annotated[bool, typer.Option("--version", callback=_version, is_eager=True,
                                                help="Print the version.")] = False) -> None:
    """OVAMOS multi-object search over Zenoh."""


@app.command()
def router(config: Annotated[Optional[Path], typer.Option(help="Zenoh router config (json5).")] = None,
           listen: Listen = None, connect: Connect = None,
           log_json: LogJson = False, log_level: LogLevel = "INFO") -> None:
    """Run a Zenoh router (a Python session in router mode)."""
    from shared.service import install_signal_handlers
    setup_logging(json_lines=log_json, level=log_level)
    try:
        cfg = build_config("router", file=config, listen=listen or (), connect=connect or ())
        session = open_session(cfg)
    except ZenohConfigError as exc:
        raise _fail(str(exc))
    stop = threading.Event()
    install_signal_handlers(stop)
    logging.getLogger("ovamos.router").info("router %s listening on %s", session.zid(),
                                            cfg.get_json("listen/endpoints"))
    stop.wait()
    session.close()


@app.command()
def run(service: Annotated[str, typer.Argument(help="Service to run.")],
        robot_id: RobotId = "robot1",
        instance: Annotated[str, typer.Option(help="Instance name (unique per service).")] = "0",
        config: Annotated[Optional[Path], typer.Option(help="Service config (TOML or JSON).")] = None,
        zenoh_file: ZenohFile = None, connect: Connect = None, listen: Listen = None,
        log_json: LogJson = False, log_level: LogLevel = "INFO") -> None:
    """Run one service until SIGINT / SIGTERM."""
    from services.registry import UnknownServiceError, service_class
    from shared.keys import KeyExprError
    from shared.service import ServiceConfigError, load_config, run_service
    setup_logging(json_lines=log_json, level=log_level)
    try:
        cls = service_class(service)
        cfg = load_config(cls, config)
        zcfg = build_config(file=zenoh_file, connect=connect or (), listen=listen or ())
        run_service(cls, zcfg, cfg, robot_id=robot_id, instance=instance, stop=threading.Event())
    except (UnknownServiceError, ServiceConfigError, ZenohConfigError, KeyExprError) as exc:
        raise _fail(str(exc))


@app.command()
def status(robot_id: RobotId = "*", zenoh_file: ZenohFile = None, connect: Connect = None,
           timeout: Annotated[float, typer.Option(help="Seconds to wait for answers.")] = 2.0,
           as_json: Annotated[bool, typer.Option("--json", help="Print JSON.")] = False) -> None:
    """List live services (from Zenoh liveliness) with their message counters."""
    from shared.status import live_services
    try:
        session = open_session(build_config("client", file=zenoh_file, connect=connect or ()))
    except ZenohConfigError as exc:
        raise _fail(str(exc))
    try:
        services = live_services(session, robot_id, timeout)
    finally:
        session.close()
    if as_json:
        print(json.dumps([{"robot_id": s.robot_id, "service": s.service, "instance": s.instance,
                           "stats": s.stats.model_dump() if s.stats else None} for s in services]))
        return
    table = Table("robot", "service", "instance", "pid", "received", "dropped", "malformed",
                  "errors", "published", title=f"{len(services)} live service instance(s)")
    for s in services:
        totals = [0] * 5
        if s.stats:
            for c in s.stats.counters.values():
                totals = [a + b for a, b in zip(totals, (c.received, c.dropped, c.malformed,
                                                          c.errors, c.published))]
        table.add_row(s.robot_id, s.service, s.instance, str(s.stats.pid) if s.stats else "?",
                      *map(str, totals))
    console.print(table)


@app.command()
def demo(seconds: Annotated[float, typer.Option(help="How long to run.")] = 6.0,
         robot_id: RobotId = "demo") -> None:
    """Run a router and services on this machine over real Zenoh, and show what flows."""
    from services.demo import run_demo
    raise typer.Exit(run_demo(console, seconds=seconds, robot_id=robot_id))


@bench_app.command("transport")
def bench_transport(
        frames: Annotated[int, typer.Option(help="Round trips per run.")] = 200,
        runs: Annotated[int, typer.Option(help="Runs (the median of run medians is reported).")] = 5,
        gap_ms: Annotated[float, typer.Option(help="Pause before each round trip.")] = 5.0,
        as_json: Annotated[bool, typer.Option("--json", help="Print one JSON object.")] = False
) -> None:
    """Latency of a 640x480 RGB-D frame through a router: raw Zenoh vs. the ovamos bus."""
    from bench.transport import print_table, run_benchmark
    result = run_benchmark(frames=frames, runs=runs, gap_ms=gap_ms, progress=None if as_json else err)
    if as_json:
        print(json.dumps(result))
    else:
        print_table(console, result)


def main() -> None:
    app()


if __name__ == "__main__":
    main()
