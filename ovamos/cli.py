"""The ``ovamos`` command line."""

from __future__ import annotations

import json
import math
import os
import sys
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Literal, Optional

import numpy as np
import typer
import zenoh
from rich import box
from rich.console import Console
from rich.markup import escape
from rich.table import Column, Table

from ovamos import __version__
from ovamos.bench.policies import DEFAULT_POLICIES, POLICY_ORDER
from ovamos.shared.atomic import write_atomic
from ovamos.shared.bus.zconfig import DEFAULT_ENDPOINT, Mode, ZenohConfigError, build_config, open_session
from ovamos.shared.deploy import shipped_profiles
from ovamos.shared.log import setup_logging

if TYPE_CHECKING:
    from ovamos.shared.bus.status import LiveService
    from ovamos.world.scene import Scene

app = typer.Typer(add_completion=False, no_args_is_help=True,
                  help="OVAMOS multi-object search over Zenoh.")
bench_app = typer.Typer(no_args_is_help=True, help="Benchmarks (results print as tables).")
app.add_typer(bench_app, name="bench")
sim_app = typer.Typer(no_args_is_help=True, help="The simulated world: scenes, renders.")
app.add_typer(sim_app, name="sim")
certs_app = typer.Typer(no_args_is_help=True,
                        help="Certificates for the laptop-robot link (mTLS): a CA, then one per role.")
app.add_typer(certs_app, name="certs")
console = Console()
err = Console(stderr=True, soft_wrap=True)  # no line breaks inserted: a path in a message stays whole, to copy

ZenohFile = Annotated[Optional[Path], typer.Option("--zenoh", help="Zenoh config (json5).")]
Connect = Annotated[Optional[list[str]], typer.Option(help="Endpoint to connect to (repeatable).")]
Listen = Annotated[Optional[list[str]], typer.Option(help="Endpoint to listen on (repeatable).")]
RobotId = Annotated[str, typer.Option("--robot-id", help="Robot whose keys to use.")]
LogJson = Annotated[bool, typer.Option("--log-json", help="Log JSON lines.")]
LogLevel = Annotated[str, typer.Option("--log-level")]
AsJson = Annotated[bool, typer.Option("--json", help="Print one JSON object.")]
OnOff = Literal["on", "off"]
OpenTimeout = Annotated[float, typer.Option(
    "--open-timeout", help="Seconds to wait for a router when starting (then it reconnects for ever).")]
DEMO_OUT = Path("out/demo")
ENDPOINTS_FILE = "endpoints.json"
DEFAULT_ENDPOINTS = DEMO_OUT / ENDPOINTS_FILE
DEFAULT_GATEWAY = "http://127.0.0.1:8080"
Endpoints = Annotated[Optional[Path], typer.Option(
    "--endpoints", help=f"A running demo's endpoints (ovamos demo writes OUT/{ENDPOINTS_FILE}); default: "
                        f"{DEFAULT_ENDPOINTS} when it exists and no endpoint is given.")]


def _fail(message: str) -> typer.Exit:
    err.print(f"[red]error:[/red] {escape(message)}")
    return typer.Exit(2)


@dataclass(frozen=True)
class Deployment:
    """Where a running demo answers, as it writes it to ``OUT/endpoints.json`` while it is up.

    The demo runs on free ports; without this file ``status``, ``submit``, ``map`` ... would
    look at the default ports, where on a shared host someone else's deployment may answer
    and pass for the user's. ``pid`` is the demo's process: a file left by one killed
    outright (no chance to remove it) is recognised as pointing at nothing.
    """

    router: str
    gateway: str
    pid: int

    @classmethod
    def load(cls, path: Path) -> Deployment:
        try:
            data = json.loads(path.read_text())
            return cls(router=str(data["router"]), gateway=str(data["gateway"]), pid=int(data["pid"]))
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise _fail(f"cannot read the endpoints file {path}: {exc!r}") from None

    def running(self) -> bool:
        """Whether the process that wrote the file is still there."""
        try:
            os.kill(self.pid, 0)
        except ProcessLookupError:
            return False
        except PermissionError:  # someone else's process: there, if not ours
            pass
        return True

    def describe(self, path: Path) -> str:
        return f"{path} (router {self.router}, gateway {self.gateway})"

    @contextmanager
    def published(self, path: Path) -> Iterator[Path]:
        """The file at ``path`` for as long as the block runs (written whole, removed after)."""
        path.parent.mkdir(parents=True, exist_ok=True)
        write_atomic(path, json.dumps(asdict(self), indent=1).encode())
        try:
            yield path
        finally:
            path.unlink(missing_ok=True)


def _deployment_endpoint(endpoints: Path | None, given: bool, field: Literal["router", "gateway"],
                         default: str) -> str | None:
    """The ``router`` or ``gateway`` to use when none was given on the command line: that of
    ``--endpoints``, else of the demo's default file if its demo runs, else ``default``; says on
    stderr which, so that nobody takes another deployment's answers for their own. None: given."""
    if given:
        if endpoints is not None:
            raise _fail(f"--endpoints or the {field} itself (--connect / --zenoh / --gateway), not both")
        return None
    path = endpoints or DEFAULT_ENDPOINTS
    deployment = Deployment.load(path) if endpoints is not None or path.exists() else None
    if deployment is not None and not deployment.running():
        if endpoints is not None:
            raise _fail(f"{path} is stale: the demo that wrote it (pid {deployment.pid}) is gone")
        err.print(f"[yellow]ignoring {path}:[/yellow] the demo that wrote it (pid {deployment.pid}) is gone")
        deployment = None
    if deployment is None:
        err.print(f"deployment: the default {field} {default} (no running demo's {DEFAULT_ENDPOINTS})")
        return default
    err.print(f"deployment: {deployment.describe(path)}")
    return getattr(deployment, field)


def _tool_config(zenoh_file: Path | None, connect: list[str] | None, endpoints: Path | None,
                 open_timeout_s: float, mode: Mode | None = None) -> zenoh.Config:
    """The Zenoh config of an operator's tool (status, map, record, ...): the router given, else the
    deployment's (:func:`_deployment_endpoint`); opening the session gives up after
    ``open_timeout_s`` with the endpoint named, instead of waiting for ever for a router."""
    router = _deployment_endpoint(endpoints, zenoh_file is not None or bool(connect), "router", DEFAULT_ENDPOINT)
    try:
        return build_config(mode, file=zenoh_file, connect=[router] if router else connect or (),
                            open_timeout_s=open_timeout_s)
    except ZenohConfigError as exc:
        raise _fail(str(exc)) from None


def _version(value: bool) -> None:
    if value:
        console.print(f"ovamos {__version__}")
        raise typer.Exit()


@app.callback()
def _main(version: Annotated[bool, typer.Option("--version", callback=_version, is_eager=True,
                                                help="Print the version.")] = False) -> None:
    """OVAMOS multi-object search over Zenoh."""


Certs = Annotated[Optional[Path], typer.Option(
    "--certs", help="Folder made by `ovamos certs` (ca.pem, NAME.pem, NAME.key) for tls/ links.")]
CertName = Annotated[Optional[str], typer.Option(
    "--cert", help="This host's certificate in --certs (its CN: laptop, robot, ...).")]


def _tls(certs: Path | None, cert: str | None):
    from ovamos.shared.bus.zconfig import TlsFiles
    if (certs is None) != (cert is None):
        raise _fail("--certs and --cert go together: the folder and this host's certificate name")
    return None if certs is None or cert is None else TlsFiles.from_folder(certs, cert)


@app.command()
def router(config: Annotated[Optional[Path], typer.Option(help="Zenoh router config (json5).")] = None,
           listen: Listen = None, connect: Connect = None, certs: Certs = None, cert: CertName = None,
           robot_id: Annotated[str, typer.Option(
               "--robot-id", help="With access control: the robot whose keys carry the router's stats.")]
           = "robot1",
           robots: Annotated[Optional[list[str]], typer.Option(
               "--robot", help="A laptop router's robots (repeatable): each robot's certificate "
               "(CN robot-<id>) is bound to its own keys; default: --robot-id alone.")] = None,
           log_json: LogJson = False, log_level: LogLevel = "INFO") -> None:
    """Run a Zenoh router (a Python session in router mode).

    With ``access_control`` enabled in its config, what the rules refuse is logged and counted:
    the router then shows in ``ovamos status`` as service ``router`` (instance: --cert, else
    ``0``) with a ``denied`` count per key.
    """
    from ovamos.router import run_router
    from ovamos.shared.service import install_signal_handlers
    setup_logging(json_lines=log_json, level=log_level)
    try:
        cfg = build_config("router", file=config, listen=listen or (), connect=connect or (),
                           tls=_tls(certs, cert))
        stop = threading.Event()
        run_router(cfg, robot_id=robot_id, name=cert or "0", stop=stop, robots=robots or (),
                   on_open=lambda: install_signal_handlers(stop))
    except ZenohConfigError as exc:
        raise _fail(str(exc)) from None


@certs_app.command("init")
def certs_init(folder: Annotated[Path, typer.Argument(help="Folder for ca.pem and ca.key (made if missing).")],
               days: Annotated[int, typer.Option(help="Validity of the CA.")] = 3650) -> None:
    """Create the certificate authority that signs the laptop's, the robot's and the tools' certificates."""
    from ovamos.shared.certs import CertError, init_ca
    try:
        path = init_ca(folder, days=days)
    except CertError as exc:
        raise _fail(str(exc)) from None
    console.print(f"CA created: {path} (and {folder / 'ca.key'}, mode 0600: keep it off the robot); "
                  f"{folder} is mode 0700")


@certs_app.command("issue")
def certs_issue(folder: Annotated[Path, typer.Argument(help="The CA's folder (from `ovamos certs init`).")],
                name: Annotated[str, typer.Argument(help="The role, written as the certificate's CN: laptop, "
                                                         "robot (a fleet's: robot-<id>, e.g. robot-r2), "
                                                         "operator, ...")],
                host: Annotated[Optional[list[str]], typer.Option(
                    "--host", help="An address (IP or DNS name) the holder is reached at (repeatable); "
                                   "needed on the router that listens on the link.")] = None,
                days: Annotated[int, typer.Option(help="Validity (at most the CA's).")] = 825,
                force: Annotated[bool, typer.Option(help="Replace an existing NAME.pem / NAME.key.")] = False
                ) -> None:
    """Make NAME.key (mode 0600) and NAME.pem, signed by the CA, with CN = NAME."""
    from ovamos.shared.certs import CertError, check_certificate, issue
    try:
        cert, key = issue(folder, name, hosts=host or (), days=days, force=force)
        info = check_certificate(cert)
    except CertError as exc:
        raise _fail(str(exc)) from None
    console.print(f"issued {info.describe()}; key {key} (mode 0600)")


@certs_app.command("show")
def certs_show(folder: Annotated[Path, typer.Argument(help="A certificate folder.")]) -> None:
    """Each certificate in the folder: its CN, hosts and expiry (exit 1 when one is not valid now)."""
    from ovamos.shared.certs import CertError, list_certificates
    found = list_certificates(folder)
    if not found:
        raise _fail(f"no certificates (*.pem) in {folder}")
    for item in found:
        console.print(f"[red]invalid:[/red] {item}" if isinstance(item, CertError) else item.describe())
    raise typer.Exit(1 if any(isinstance(i, CertError) for i in found) else 0)


@app.command()
def run(service: Annotated[str, typer.Argument(help="Service to run.")],
        robot_id: RobotId = "robot1",
        instance: Annotated[str, typer.Option(help="Instance name (unique per service).")] = "0",
        config: Annotated[Optional[Path], typer.Option(help="Service config (TOML or JSON).")] = None,
        zenoh_file: ZenohFile = None, connect: Connect = None, listen: Listen = None,
        set_: Annotated[Optional[list[str]], typer.Option(
            "--set", help="KEY=JSON: set a top-level setting of the config, a JSON object changing only "
                          "the keys it names in its section (repeatable; a fleet profile tells each "
                          "process its robots and scene this way, the demo its episode).")] = None,
        log_json: LogJson = False, log_level: LogLevel = "INFO") -> None:
    """Run one service until SIGINT / SIGTERM."""
    from ovamos.registry import UnknownServiceError, service_class
    from ovamos.shared.config import parse_overrides
    from ovamos.shared.keys import KeyExprError
    from ovamos.shared.service import ServiceConfigError, load_config, run_service
    setup_logging(json_lines=log_json, level=log_level)
    try:
        cls = service_class(service)
        cfg = load_config(cls, config, parse_overrides(set_ or []))
        zcfg = build_config(file=zenoh_file, connect=connect or (), listen=listen or ())
        run_service(cls, zcfg, cfg, robot_id=robot_id, instance=instance, stop=threading.Event())
    except (UnknownServiceError, ServiceConfigError, ZenohConfigError, KeyExprError) as exc:
        raise _fail(str(exc)) from None


ProfileName = Annotated[str, typer.Argument(help=f"{' | '.join(shipped_profiles())}, or a profile .toml file.")]


@app.command()
def up(profile: ProfileName,
       log_dir: Annotated[Path, typer.Option(help="Each process's output goes to LOG_DIR/NAME.log.")]
       = Path("state/logs"),
       connect_laptop: Annotated[Optional[str], typer.Option(
           "--connect-laptop", help="HOST:PORT of the laptop's router (the robot profile links to it; "
                                    "over TLS for a secure profile).")]
       = None,
       certs: Annotated[Path, typer.Option(
           help="Secure profiles: the folder with ca.pem and this host's NAME.pem / NAME.key.")]
       = Path("state/certs"),
       listen_link: Annotated[Optional[str], typer.Option(
           "--listen-link", help="HOST:PORT where the router also listens for the other host: the laptop's "
                                 "address on the robot network (TLS for a secure profile).")] = None,
       motion: Annotated[Optional[str], typer.Option(
           help="stepwise or continuous: how the robot drives (the planner's [agent] motion; the camera and "
                "the simulated robot lock-step or free-running). Give it on every host of a deployment. "
                "Default: as the services' configs say.")] = None,
       log_json: LogJson = False, log_level: LogLevel = "INFO") -> None:
    """Run a deployment profile: its router, then its services; restart crashed ones; Ctrl-C stops all."""
    from ovamos.profiles import ProfileError, supervisor_for
    from ovamos.shared.motion import MOTIONS
    from ovamos.supervisor import SupervisorError, status_table
    setup_logging(json_lines=log_json, level=log_level)
    if motion is not None and motion not in MOTIONS:
        raise _fail(f"--motion {motion!r}: one of {', '.join(MOTIONS)}")
    try:
        sup = supervisor_for(profile, log_dir=log_dir, connect_laptop=connect_laptop, certs=certs,
                             listen_link=listen_link, motion=motion)  # type: ignore[arg-type]  # checked above
        code = sup.run_forever(on_started=lambda s: console.print(status_table(s.status(), title=profile)))
    except (ProfileError, SupervisorError) as exc:
        raise _fail(str(exc)) from None
    raise typer.Exit(code)


@app.command()
def doctor(profile: ProfileName = "all",
           other_host: Annotated[Optional[str], typer.Option(
               "--other-host", help="HOST:PORT of the other host's router over plain TCP (from the robot: the "
                                    "laptop's 7447, as --connect-laptop): is it reachable, and do the clocks "
                                    "agree? (Not a secure profile's TLS port.)")] = None,
           certs: Certs = None,
           load_models: Annotated[bool, typer.Option(
               help="Load the perception weights and time a frame on this device (seconds to a minute).")] = True,
           max_clock_offset: Annotated[float, typer.Option(
               help="Seconds the two hosts' clocks may disagree.")] = 0.1,
           as_json: AsJson = False) -> None:
    """Check this host as PROFILE will use it: extras, GPU and weights, camera, base, ports, the other
    host and its clock, certificates, disk; each check with the command that fixes it (exit 1 on a fail)."""
    from ovamos.doctor import DoctorOptions, diagnose
    from ovamos.doctor import as_json as doctor_json
    checks = diagnose(profile, DoctorOptions(other_host=other_host, certs=certs, load_models=load_models,
                                             max_clock_offset_s=max_clock_offset))
    if as_json:
        print(json.dumps(doctor_json(checks)))
    else:
        colour = {"pass": "green", "warn": "yellow", "fail": "red", "skip": "dim"}
        table = Table("check", "", Column("found, and the fix", overflow="fold"), title=f"ovamos doctor {profile}",
                      box=box.SIMPLE_HEAD, pad_edge=False)
        for c in checks:
            table.add_row(c.name, f"[{colour[c.status]}]{c.status}[/]",
                          escape(c.detail) + (f"\n[cyan]fix:[/] {escape(c.fix)}" if c.fix else ""))
        console.print(table)
    raise typer.Exit(1 if any(c.status == "fail" for c in checks) else 0)


@app.command("drive")
def drive_once(action: Annotated[str, typer.Argument(help="forward | left | right: one primitive (0.25 m or "
                                                         "30 deg as shipped).")],
               robot_id: RobotId = "robot1", zenoh_file: ZenohFile = None, connect: Connect = None,
               endpoints: Endpoints = None,
               timeout: Annotated[float, typer.Option(help="Seconds to wait for the base, and for the move.")]
               = 30.0) -> None:
    """Drive one primitive on a robot with no planner running, and say how far its odometry has it go
    (the first run: hold it against a tape measure)."""
    from ovamos.drive import DriveError, drive
    from ovamos.shared.bus import Bus
    from ovamos.shared.motion import Action
    actions = {"forward": Action.MOVE_FORWARD, "left": Action.TURN_LEFT, "right": Action.TURN_RIGHT}
    if action not in actions:
        raise _fail(f"ACTION {action!r}: one of {', '.join(actions)}")
    cfg = _tool_config(zenoh_file, connect, endpoints, timeout, "client")
    try:
        bus = Bus.open(cfg, robot_id, "drive")
    except ZenohConfigError as exc:
        raise _fail(str(exc)) from None
    try:
        driven = drive(bus, actions[action], timeout)
    except DriveError as exc:
        raise _fail(str(exc)) from None
    finally:
        bus.close()
    console.print(f"{driven.action.value}: {driven.outcome} in {driven.seconds:.1f} s; odometry: "
                  f"{driven.distance_m:.3f} m, {driven.turned_deg:+.1f} deg")


@app.command()
def submit(targets: Annotated[list[str], typer.Argument(help="Object names.")],
           gateway: Annotated[Optional[str], typer.Option(
               help=f"Gateway URL (default: the running demo's, else {DEFAULT_GATEWAY}).")] = None,
           endpoints: Endpoints = None,
           robot_id: Annotated[Optional[str], typer.Option("--robot-id")] = None,
           max_steps: Annotated[Optional[int], typer.Option()] = None,
           token: Annotated[Optional[str], typer.Option(envvar="OVAMOS_GATEWAY_TOKEN")] = None,
           wait: Annotated[bool, typer.Option(help="Follow until the task ends.")] = False,
           timeout: Annotated[float, typer.Option(help="Seconds to wait with --wait.")] = 600.0) -> None:
    """Submit a search task to the gateway (exit 1 when a followed task does not succeed)."""
    from ovamos.services.gateway.client import GatewayError, wait_task
    from ovamos.services.gateway.client import submit as submit_task
    gateway = _deployment_endpoint(endpoints, gateway is not None, "gateway", DEFAULT_GATEWAY) or gateway
    try:
        task = submit_task(targets, gateway, token, robot_id, max_steps)
        console.print(f"task {task.id}: {task.status.value} on {task.robot_id} ({gateway}{task.location})")
        if wait:
            final = wait_task(task.id, gateway, token, timeout, on_update=lambda v: console.print(
                f"{v.status.value} step {v.steps} found {', '.join(f.label for f in v.found) or '-'}"))
            raise typer.Exit(0 if final.status.value == "done" else 1)
    except (GatewayError, TimeoutError) as exc:
        raise _fail(str(exc)) from None


@app.command()
def status(robot_id: RobotId = "*", zenoh_file: ZenohFile = None, connect: Connect = None,
           endpoints: Endpoints = None,
           timeout: Annotated[float, typer.Option(
               help="Seconds to wait for a router, then as long for the services' answers.")] = 2.0,
           as_json: Annotated[bool, typer.Option("--json", help="Print JSON.")] = False) -> None:
    """List live services (from Zenoh liveliness) with their message counters."""
    from ovamos.shared.bus.status import live_services
    cfg = _tool_config(zenoh_file, connect, endpoints, timeout, "client")
    try:
        session = open_session(cfg)
    except ZenohConfigError as exc:
        raise _fail(str(exc)) from None
    try:
        services = live_services(session, robot_id, timeout)
    finally:
        session.close()
    if as_json:
        print(json.dumps([{"robot_id": s.robot_id, "service": s.service, "instance": s.instance,
                           "stats": s.stats.model_dump() if s.stats else None} for s in services]))
        return
    console.print(live_table(services))


def live_table(services: list[LiveService]) -> Table:
    """``ovamos status`` for people, readable on an 80-column terminal: one row per instance (the
    instance after ``#`` where it is not the usual ``0``), its counters summed over its keys."""
    table = Table("robot", Column("service", no_wrap=True, min_width=11), "pid",
                  *(Column(name, justify="right") for name in ("in", "out", "dropped", "bad", "errors", "denied")),
                  title=f"{len(services)} live service instance(s)", box=box.SIMPLE_HEAD, collapse_padding=True,
                  pad_edge=False, caption="in / out: messages received / published; bad: malformed (refused "
                                          "undecoded); denied: refused by the ACL")
    for s in services:
        totals = [0] * 6
        if s.stats:
            for c in s.stats.counters.values():
                totals = [a + b for a, b in zip(totals, (c.received, c.published, c.dropped, c.malformed,
                                                          c.errors, c.denied))]
        table.add_row(s.robot_id, s.service if s.instance == "0" else f"{s.service}#{s.instance}",
                      str(s.stats.pid) if s.stats else "?", *map(str, totals))
    return table


def _port_lines(ports: list[dict], note: str = "") -> list[str]:
    """``task/current  TaskSpec`` per port, the common ``ovamos/{robot_id}/`` prefix left out."""
    lines = []
    for port in ports:
        notes = [note] if note else []
        if port.get("keep_latest"):
            notes.append("latest" if port["keep_latest"] == 1 else f"latest {port['keep_latest']}")
        lines.append(f"{port['key'].removeprefix(GRAPH_PREFIX)}  [cyan]{port['message'] or 'any'}[/cyan]"
                     + (f" ({', '.join(notes)})" if notes else ""))
    return lines


GRAPH_PREFIX = "ovamos/{robot_id}/"


def graph_table(data: dict) -> Table:
    """``ovamos graph`` for people: one row per service, its keys in and out with their message types."""
    table = Table("service", "inputs", "outputs", show_lines=True,
                  title=f"the services' dataflow (keys under {GRAPH_PREFIX})",
                  caption="latest: only the newest sample is kept while the service is busy; "
                          "get: queries the key; answers: replies to gets on it")
    for name, node in data["services"].items():
        inputs = _port_lines(node["inputs"]) + _port_lines(node.get("queries", []), "get")
        outputs = _port_lines(node["outputs"]) + _port_lines(node.get("answers", []), "answers")
        table.add_row(name, "\n".join(inputs) or "-", "\n".join(outputs) or "-")
    return table


@app.command()
def graph(as_json: AsJson = False) -> None:
    """The services' dataflow (shared/topology.py): each service's keys in and out, with message types."""
    from ovamos.shared.topology import graph as dataflow
    data = dataflow()
    if as_json:
        print(json.dumps(data))
    else:
        console.print(graph_table(data))


@app.command()
def demo(seed: Annotated[Optional[int], typer.Option(help="Episode set seed (default: the demo episode's).")] = None,
         episode: Annotated[Optional[int], typer.Option(
             help="Episode index: scene, start, targets (default: the demo episode).")] = None,
         targets: Annotated[Optional[list[str]], typer.Option("--target", help="Override the episode's "
                                                                              "targets (repeatable).")] = None,
         keep_running: Annotated[bool, typer.Option(help="Stay up afterwards; print the gateway URL.")] = False,
         timeout: Annotated[Optional[float], typer.Option(
             help="Give the search this many seconds (default: 600 on the kinematic base, 1500 on a "
                  "wheeled one, whose primitives take real time).")] = None,
         base: Annotated[Optional[str], typer.Option(
             help="How the simulated robot moves: kinematic (ideal; the default stepwise), odrive, kobuki "
                  "(the default continuous) or opencr (the real base driver and its client on a simulated "
                  "device), or ros2.")] = None,
         motion: Annotated[str, typer.Option(
             help="stepwise: a primitive, then the frame after it (the paper's); continuous: paths driven "
                  "while frames free-run (a wheeled base).")] = "stepwise",
         out: Annotated[Path, typer.Option(help="Folder for the report, map, configs and logs; while the "
                                                f"services are up, {ENDPOINTS_FILE} (their router and "
                                                "gateway, for status, submit, map ...).")]
         = DEMO_OUT,
         record: Annotated[bool, typer.Option(help="Record the run to OUT/run.mcap (a fleet: "
                                                   "OUT/run-ROBOT.mcap per robot).")] = True,
         robots: Annotated[int, typer.Option(
             min=1, max=16, help="Robots searching at once, each in its own home, through one perception "
                                 "service and one gateway (from the default episode: the episodes in "
                                 "ovamos.demo.FLEET_EPISODES, which the method solves; else EPISODE, "
                                 "EPISODE+1, ...).")] = 1,
         max_steps: Annotated[Optional[int], typer.Option(
             min=1, help="Each task's step limit (default: the paper's 500).")] = None,
         odometry: Annotated[str, typer.Option(help="How the simulated robot's odometry errs: ideal (exact), "
                                                    "realistic or hard (services/sim/odometry.py).")] = "ideal",
         localization: Annotated[str, typer.Option(help="off; on: the map matches each frame against itself, "
                                                        "in a frame odometry drift does not move; base: the map "
                                                        "follows the robot's own localization (--base ros2: its "
                                                        "stand-in for AMCL on amcl_pose).")] = "off"
         ) -> None:
    """Every service and the simulated robot as processes over Zenoh; a task submitted over HTTP."""
    from ovamos.demo import BASES, DEMO_EPISODE, DEMO_SEED, LOCALIZATIONS, ROS2_BASE, run_demo
    from ovamos.services.sim.odometry import ODOMETRY_PRESET_NAMES
    from ovamos.services.sim.wheels import CONTINUOUS_BASE
    from ovamos.shared.motion import MOTIONS
    seed = DEMO_SEED if seed is None else seed
    episode = DEMO_EPISODE if episode is None else episode
    if motion not in MOTIONS:
        raise _fail(f"--motion {motion!r}: one of {', '.join(MOTIONS)}")
    base = base or ("kinematic" if motion == "stepwise" else CONTINUOUS_BASE)
    if motion == "continuous" and base == "kinematic":
        raise _fail("--motion continuous drives paths on wheels: the kinematic base only executes primitives; "
                    f"choose --base {CONTINUOUS_BASE}, opencr, odrive or ros2")
    if base not in BASES:
        raise _fail(f"--base {base!r}: one of {', '.join(BASES)}")
    if odometry not in ODOMETRY_PRESET_NAMES:
        raise _fail(f"--odometry {odometry!r}: one of {', '.join(ODOMETRY_PRESET_NAMES)}")
    if localization not in LOCALIZATIONS:
        raise _fail(f"--localization {localization!r}: one of {', '.join(LOCALIZATIONS)}")
    if localization == "base" and base != ROS2_BASE:
        raise _fail(f"--localization base follows a ROS 2 robot's own localization: only with --base {ROS2_BASE} "
                    "(the other simulated bases have none; --localization on matches scans instead)")
    if base == ROS2_BASE:
        _into_loopback_namespace(robots)
    try:
        code = run_demo(console, out_dir=out, seed=seed, episode=episode, targets=targets,
                        keep_running=keep_running, timeout_s=timeout, base=base,
                        record=out / "run.mcap" if record else None, robots=robots, max_steps=max_steps,
                        motion=motion, odometry=odometry, localization=localization,
                        publish=lambda router, gateway: Deployment(router, gateway, os.getpid()).published(
                            out / ENDPOINTS_FILE))
    except (TimeoutError, OSError) as exc:
        raise _fail(str(exc)) from None
    raise typer.Exit(code)


def _into_loopback_namespace(robots: int) -> None:
    """``demo --base ros2`` runs DDS, which only starts in a loopback-only network namespace: run the
    demo again in one unless it is in one already."""
    from ovamos.shared.dds import DdsNetworkError, check_loopback_only, in_own_namespace, rerun_in_loopback_namespace
    if robots > 1:
        raise _fail("--base ros2 runs one robot (--robots 1)")
    try:
        check_loopback_only()
    except DdsNetworkError as exc:
        if in_own_namespace():
            raise _fail(str(exc)) from None
        console.print("--base ros2: DDS starts only in a network namespace with nothing but loopback; running "
                      "the demo in one (python -m ovamos.shared.dds -- ...); its router and gateway answer only "
                      "inside it.")
        rerun_in_loopback_namespace([sys.executable, "-m", "ovamos.cli", *sys.argv[1:]])


KeyNames = Annotated[Optional[list[str]], typer.Option(
    "--keys", help="Key names to take (repeatable; default: every key a service publishes, see ovamos graph).")]


@app.command()
def record(out: Annotated[Path, typer.Option("--out", help="MCAP file to write.")],
           robot_id: RobotId = "robot1", keys_: KeyNames = None,
           split_mb: Annotated[Optional[float], typer.Option(
               "--split-mb", help="Start a new file (run.1.mcap, ...) past this many MB.")] = None,
           budget_mb: Annotated[float, typer.Option(
               "--budget-mb", help="Queue at most this many MB; beyond, messages are dropped and counted.")]
           = 256.0,
           compression: Annotated[str, typer.Option(help="Chunk compression: zstd, lz4 or none.")] = "zstd",
           views: Annotated[bool, typer.Option(help="Also write the Foxglove view channels.")] = True,
           overwrite: Annotated[bool, typer.Option(help="Replace OUT if it exists.")] = False,
           zenoh_file: ZenohFile = None, connect: Connect = None, endpoints: Endpoints = None,
           open_timeout: OpenTimeout = 10.0,
           log_json: LogJson = False, log_level: LogLevel = "INFO") -> None:
    """Record a robot's keys to MCAP (raw channels for replay, Foxglove views) until SIGINT / SIGTERM."""
    from ovamos.record.channels import UnknownKeyError, select
    from ovamos.record.live import record as run_record
    from ovamos.record.recorder import RecorderConfig, RecordingExistsError
    from ovamos.shared.keys import KeyExprError
    setup_logging(json_lines=log_json, level=log_level)
    if compression not in ("zstd", "lz4", "none"):
        raise _fail(f"--compression {compression!r}: one of zstd, lz4, none")
    zcfg = _tool_config(zenoh_file, connect, endpoints, open_timeout)
    try:
        ports = select(keys_)
        config = RecorderConfig(budget_bytes=int(budget_mb * 2 ** 20),
                                compression=compression,  # type: ignore[arg-type]  # checked above
                                split_bytes=None if split_mb is None else int(split_mb * 2 ** 20),
                                views=views, overwrite=overwrite)
        stats = run_record(zcfg, robot_id, ports, out, config, threading.Event())
    except (UnknownKeyError, RecordingExistsError, ZenohConfigError, KeyExprError, OSError) as exc:
        raise _fail(str(exc)) from None
    written = sum(stats["written"].values())
    dropped = sum(stats["dropped"].values())
    err.print(f"recorded {written} messages ({stats['bytes'] / 2 ** 20:.1f} MB raw, {dropped} dropped) "
              f"-> {', '.join(stats['files'])}")
    if stats["failed"]:
        raise _fail(f"the recording stopped early: {stats['failed']}")


@app.command()
def replay(recording: Annotated[Path, typer.Argument(help="MCAP file written by ovamos record.")],
           rate: Annotated[float, typer.Option(help="Speed: 1.0 is the recorded pace.")] = 1.0,
           as_fast: Annotated[bool, typer.Option("--max", help="Publish as fast as possible (no pacing).")]
           = False,
           keys_: KeyNames = None,
           robot_id: Annotated[Optional[str], typer.Option(
               "--robot-id", help="Publish on this robot's keys (default: the recorded robot's).")] = None,
           force: Annotated[bool, typer.Option(
               "--force", help="Replay even onto a robot whose driver is alive (its odometry and "
               "map would mix with the recording's).")] = False,
           zenoh_file: ZenohFile = None, connect: Connect = None, endpoints: Endpoints = None,
           open_timeout: OpenTimeout = 10.0,
           log_json: LogJson = False, log_level: LogLevel = "INFO") -> None:
    """Publish a recording's raw channels back on Zenoh, with their recorded timing."""
    from ovamos.record.channels import UnknownKeyError
    from ovamos.record.live import LiveRobotError
    from ovamos.record.live import replay as run_replay
    from ovamos.record.replay import RecordingError
    from ovamos.shared.keys import KeyExprError
    setup_logging(json_lines=log_json, level=log_level)
    if rate <= 0:
        raise _fail(f"--rate {rate}: must be > 0")
    zcfg = _tool_config(zenoh_file, connect, endpoints, open_timeout)
    try:
        report = run_replay(zcfg, recording, rate=None if as_fast else rate, names=keys_, robot_id=robot_id,
                            stop=threading.Event(), force=force)
    except (RecordingError, UnknownKeyError, ZenohConfigError, KeyExprError, LiveRobotError) as exc:
        raise _fail(str(exc)) from None
    counts = ", ".join(f"{k} {n}" for k, n in sorted(report.read.items())) or "nothing"
    err.print(f"replayed {counts}")
    for skipped in report.skipped_channels:
        err.print(f"[yellow]skipped[/yellow] {skipped}")
    if report.truncated:
        err.print(f"[yellow]the file ends early:[/yellow] {report.truncated}")


@app.command()
def view(robot_id: RobotId = "robot1", keys_: KeyNames = None,
         host: Annotated[str, typer.Option(help="Address to listen on (loopback by default).")] = "127.0.0.1",
         port: Annotated[int, typer.Option(help="WebSocket port (0: a free one).")] = 8765,
         zenoh_file: ZenohFile = None, connect: Connect = None, endpoints: Endpoints = None,
         open_timeout: OpenTimeout = 10.0,
         log_json: LogJson = False, log_level: LogLevel = "INFO") -> None:
    """A Foxglove WebSocket server showing a robot's live traffic (camera, map layers, planner, task)."""
    from ovamos.record.channels import UnknownKeyError, select
    from ovamos.record.live import view as run_view
    from ovamos.shared.keys import KeyExprError
    setup_logging(json_lines=log_json, level=log_level)

    def started(bound: int) -> None:
        err.print(f"Foxglove live view of {robot_id} on ws://{host}:{bound} (open it in Foxglove: "
                  f"Open connection > Foxglove WebSocket; layout deploy/foxglove/ovamos.json)")

    zcfg = _tool_config(zenoh_file, connect, endpoints, open_timeout)
    try:
        run_view(zcfg, robot_id, select(keys_), host=host,
                 port=port, stop=threading.Event(), on_started=started)
    except (UnknownKeyError, ZenohConfigError, KeyExprError, RuntimeError) as exc:
        raise _fail(str(exc)) from None


@app.command("map")
def map_png(out: Annotated[Path, typer.Option(help="PNG to write.")],
            robot_id: Annotated[Optional[str], typer.Option(
                "--robot-id", help="The robot (default: the gateway's one robot; over Zenoh: robot1).")] = None,
            gateway: Annotated[Optional[str], typer.Option(
                help=f"Gateway URL (default: the running demo's, else {DEFAULT_GATEWAY}).")] = None,
            token: Annotated[Optional[str], typer.Option(envvar="OVAMOS_GATEWAY_TOKEN")] = None,
            zenoh_file: ZenohFile = None, connect: Connect = None, endpoints: Endpoints = None,
            layer: Annotated[Optional[str], typer.Option(help="One target's layer (default: all).")] = None,
            timeout: Annotated[float, typer.Option(
                help="Seconds to wait for the gateway (or a router, then as long for the map).")] = 5.0) -> None:
    """Draw the robot's current map as the operator's page does: obstacles, values, frontiers, objects,
    and the latest task's path, targets and found objects with the robot (from the gateway). With
    --connect / --zenoh: the mapping service's snapshot alone, without the task and the robot."""
    if zenoh_file is not None or connect:
        if gateway is not None:
            raise _fail("--gateway or --connect / --zenoh, not both")
        _map_from_zenoh(out, robot_id or "robot1", _tool_config(zenoh_file, connect, None, timeout, "client"),
                        layer, timeout)
        return
    from ovamos.services.gateway.client import GatewayClient, GatewayError
    url = _deployment_endpoint(endpoints, gateway is not None, "gateway", DEFAULT_GATEWAY) or gateway
    try:
        with GatewayClient(url, token, timeout_s=timeout) as client:
            if robot_id is None:
                robots = list(client.health()["robots"])
                if len(robots) != 1:
                    raise _fail(f"the gateway at {url} serves robots {', '.join(robots)}: pick one with --robot-id")
                robot_id = robots[0]
            png = client.map_png(robot_id, layer)
    except GatewayError as exc:
        raise _fail(str(exc)) from None
    try:
        out.write_bytes(png)
    except OSError as exc:
        raise _fail(f"cannot write {out}: {exc}") from None
    console.print(f"map of {robot_id} from {url} -> {out}")


def _map_from_zenoh(out: Path, robot_id: str, cfg: zenoh.Config, layer: str | None, timeout: float) -> None:
    """``ovamos map`` without a gateway: the mapping service's snapshot, drawn alone."""
    from ovamos.services.mapping.render import render_map, write_png
    from ovamos.shared import keys
    from ovamos.shared.messages import DecodeError, MapSnapshot
    try:
        session = open_session(cfg)
    except ZenohConfigError as exc:
        raise _fail(str(exc)) from None
    try:
        replies = [r.ok for r in session.get(keys.map_snapshot(robot_id), timeout=timeout) if r.ok]
        if not replies:
            raise _fail(f"no mapping service answered for robot {robot_id!r} within {timeout} s")
        snapshot = MapSnapshot.from_bytes(replies[0].payload.to_bytes())
        write_png(out, render_map(snapshot, layer=layer))
    except (DecodeError, ValueError) as exc:
        raise _fail(str(exc)) from None
    finally:
        session.close()
    console.print(f"map of {robot_id} (last frame {snapshot.seq}, layers {', '.join(snapshot.layers) or '-'}, "
                  f"{len(snapshot.frontiers)} frontiers, {len(snapshot.objects)} objects; no task, no robot: "
                  f"the gateway draws those) -> {out}")


def _report(result: dict, as_json: bool, print_table: Callable[[Console, dict], None]) -> None:
    """Benchmarks print one JSON object for scripts, or their table for people."""
    if as_json:
        print(json.dumps(result))
    else:
        print_table(console, result)


@bench_app.command("transport")
def bench_transport(
        frames: Annotated[int, typer.Option(help="Round trips per run.")] = 200,
        runs: Annotated[int, typer.Option(help="Runs (the median of run medians is reported).")] = 5,
        gap_ms: Annotated[float, typer.Option(help="Pause before each round trip.")] = 5.0,
        tls: Annotated[bool, typer.Option(
            "--tls", help="Instead: the frame over the link between two routers, plain TCP vs mTLS "
                          "(and mTLS with the secure profiles' access control).")] = False,
        stages: Annotated[bool, typer.Option(
            "--stages", help="Instead: where the round trip's time goes (encode, put, link, hand-off "
                             "and decode, ack, wake-up), raw Zenoh beside the bus, shared memory off and on.")] = False,
        as_json: AsJson = False
) -> None:
    """Latency of a 640x480 RGB-D frame through a router: raw Zenoh vs. the ovamos bus (--tls: over
    the laptop-robot link, plain TCP vs mTLS; --stages: the round trip split into stages)."""
    if stages:
        from ovamos.bench.transport_stages import print_stages, run_stages
        _report(run_stages(frames=frames, gap_ms=gap_ms), as_json, print_stages)
        return
    if tls:
        from ovamos.bench.transport_tls import print_table as print_tls
        from ovamos.bench.transport_tls import run_tls_benchmark
        result = run_tls_benchmark(frames=frames, runs=runs, gap_ms=gap_ms, progress=None if as_json else err)
        _report(result, as_json, print_tls)
        return
    from ovamos.bench.transport import print_table, run_benchmark
    result = run_benchmark(frames=frames, runs=runs, gap_ms=gap_ms, progress=None if as_json else err)
    _report(result, as_json, print_table)


@bench_app.command("sim")
def bench_sim(frames: Annotated[int, typer.Option(help="Frames per run.")] = 50,
              runs: Annotated[int, typer.Option(help="Runs (the median is reported).")] = 3,
              as_json: AsJson = False
              ) -> None:
    """Rendered frames per second of the simulator at 640x480 and 320x240."""
    from ovamos.bench.sim import print_table, run_benchmark
    result = run_benchmark(frames=frames, runs=runs)
    _report(result, as_json, print_table)


@bench_app.command("mapping")
def bench_mapping(frames: Annotated[int, typer.Option(help="Frames per run.")] = 40,
                  runs: Annotated[int, typer.Option(help="Runs (the median is reported).")] = 3,
                  as_json: AsJson = False
                  ) -> None:
    """Milliseconds per 640x480 frame for a full map update with 1, 3 and 10 target layers."""
    from ovamos.bench.mapping import print_table, run_benchmark
    result = run_benchmark(frames=frames, runs=runs, progress=None if as_json else err)
    _report(result, as_json, print_table)


@bench_app.command("localization")
def bench_localization(frames: Annotated[int, typer.Option(help="Frames per run.")] = 60,
                       runs: Annotated[int, typer.Option(help="Runs (the median is reported).")] = 3,
                       as_json: AsJson = False
                       ) -> None:
    """Milliseconds per 640x480 frame for matching it against the map (median, p95)."""
    from ovamos.bench.localization import print_table, run_benchmark
    result = run_benchmark(frames=frames, runs=runs, progress=None if as_json else err)
    _report(result, as_json, print_table)


@bench_app.command("planner")
def bench_planner(runs: Annotated[int, typer.Option(help="Instances per size (median).")] = 5,
                  as_json: AsJson = False
                  ) -> None:
    """POUCT simulations per second and decision latency for 5, 10 and 20 candidates."""
    from ovamos.bench.planner import print_table, run_benchmark
    result = run_benchmark(runs=runs, progress=None if as_json else err)
    _report(result, as_json, print_table)


@bench_app.command("camera")
def bench_camera(frames: Annotated[int, typer.Option(help="Frames per run.")] = 150,
                 runs: Annotated[int, typer.Option(help="Runs (the median is reported).")] = 5,
                 as_json: AsJson = False
                 ) -> None:
    """Frames per second of the RealSense backend at 640x480 (SDK software device), published over Zenoh."""
    from ovamos.bench.camera import print_table, run_benchmark
    result = run_benchmark(frames=frames, runs=runs, progress=None if as_json else err)
    _report(result, as_json, print_table)


@bench_app.command("ros2")
def bench_ros2(seconds: Annotated[float, typer.Option(help="Seconds of frames per run.")] = 10.0,
               runs: Annotated[int, typer.Option(help="Runs (the median is reported).")] = 3,
               commands: Annotated[int, typer.Option(help="Velocity commands timed per run.")] = 50,
               as_json: AsJson = False) -> None:
    """ROS 2 frame path (640x480 at 30 Hz into the camera service, one core) and cmd_vel latency,
    against mock ROS 2 peers in a loopback-only network namespace (entered by itself: root)."""
    import subprocess
    import sys

    from ovamos.shared.dds import DdsNetworkError, check_loopback_only
    try:
        check_loopback_only()
    except DdsNetworkError:  # not yet inside one: run again in a loopback-only namespace
        raise typer.Exit(subprocess.run([sys.executable, "-m", "ovamos.shared.dds", "--", sys.executable, "-m",
                                         "ovamos.cli", *sys.argv[1:]]).returncode) from None
    from ovamos.bench.ros2 import print_table, run_benchmark
    result = run_benchmark(runs=runs, seconds=seconds, commands=commands, progress=None if as_json else err)
    _report(result, as_json, print_table)


@bench_app.command("record")
def bench_record(seconds: Annotated[float, typer.Option(help="How long to record.")] = 20.0,
                 noise: Annotated[bool, typer.Option(help="Give the simulator's frames a camera's noise "
                                                          "(flat renders compress ~170x).")] = True,
                 as_json: AsJson = False) -> None:
    """Recording 640x480 RGB-D at 30 Hz plus map snapshots at 2 Hz over Zenoh: MB/s, frames/s, drops."""
    from ovamos.bench.record import print_table, run_benchmark
    _report(run_benchmark(seconds=seconds, noise=noise), as_json, print_table)


SceneSeed = Annotated[int, typer.Option("--seed", help="Scene seed.")]
SceneFile = Annotated[Optional[Path], typer.Option("--scene", help="Scene JSON (instead of --seed).")]


@bench_app.command("perception")
def bench_perception(frames: Annotated[int, typer.Option(help="hf frames per run (~90 s each on 2 CPU cores).")] = 1,
                     runs: Annotated[int, typer.Option(help="Runs (the median is reported).")] = 3,
                     sim_frames: Annotated[int, typer.Option(help="sim frames per run.")] = 40,
                     hf: Annotated[bool, typer.Option("--hf/--no-hf", help="Also time the real models.")] = True,
                     as_json: AsJson = False) -> None:
    """Frames per second of the sim and hf perception backends (CPU; GPU fp16 when CUDA is present)."""
    from ovamos.bench.perception import print_table, run_benchmark
    result = run_benchmark(frames=frames, runs=runs, sim_frames=sim_frames, hf=hf,
                           progress=None if as_json else err)
    _report(result, as_json, print_table)


@bench_app.command("fleet")
def bench_fleet(robots: Annotated[str, typer.Option(help="Robot counts, comma-separated (each robot in its "
                                                         "own home).")] = "1,2,4",
                window: Annotated[float, typer.Option(help="Seconds the running fleet is measured.")] = 15.0,
                warmup: Annotated[float, typer.Option(help="Seconds of search before the window.")] = 5.0,
                sim_rounds: Annotated[int, typer.Option(help="Rounds of sim perception frames (one per "
                                                             "robot each).")] = 10,
                hf: Annotated[bool, typer.Option("--hf/--no-hf", help="Also time the real models (CPU, "
                                                                     "full size, random weights).")] = True,
                hf_detect: Annotated[bool, typer.Option(help="hf with boxes and masks too (~80 s a frame "
                                                             "on 2 CPU cores), not scores only.")] = False,
                as_json: AsJson = False) -> None:
    """Perception frames/s (batch 1 vs batched), planner decisions/s and step latency per robot count."""
    from ovamos.bench.fleet import print_table, run_benchmark
    try:
        counts = [int(n) for n in robots.split(",") if n.strip()]
        result = run_benchmark(counts, window_s=window, warmup_s=warmup, sim_rounds=sim_rounds, hf=hf,
                               hf_detect=hf_detect, progress=None if as_json else err)
    except ValueError as exc:
        raise _fail(str(exc)) from None
    _report(result, as_json, print_table)


@bench_app.command("soak")
def bench_soak(tasks: Annotated[int, typer.Option(help="Tasks in sequence on one stack (see bench/soak.py).")] = 20,
               fresh: Annotated[bool, typer.Option("--fresh/--no-fresh", help="Also run each task that can "
                                                   "succeed from a fresh start (in process) for its steps.")] = True,
               as_json: AsJson = False) -> None:
    """One demo stack left up for task after task: per task result, steps, seconds, why it failed,
    and each service's RSS."""
    from ovamos.bench.soak import print_table, run_benchmark
    try:
        result = run_benchmark(tasks, fresh=fresh, progress=None if as_json else err)
    except ValueError as exc:
        raise _fail(str(exc)) from None
    _report(result, as_json, print_table)


@bench_app.command("homes")
def bench_homes(count: Annotated[int, typer.Option(help="Homes to generate (seeds 0..count-1).")] = 200,
                homes: Annotated[str, typer.Option(help="Home tier: default or large.")] = "default",
                as_json: AsJson = False) -> None:
    """Statistics of the generated homes (rooms, areas, furniture, small objects) beside ProcTHOR-10K's."""
    from ovamos.bench.homes import print_table, run
    try:
        result = run(count, homes)
    except ValueError as exc:
        raise _fail(str(exc)) from None
    _report(result, as_json, print_table)


@bench_app.command("compare")
def bench_compare(a: Annotated[Path, typer.Argument(help="Run A: an ovamos bench search --out folder.")],
                  b: Annotated[Path, typer.Argument(help="Run B, compared with A on the episodes both hold.")],
                  allow_code_change: Annotated[bool, typer.Option(
                      help="Pair runs of different code on a report seed (a change that chose nothing on it).")]
                  = False,
                  as_json: AsJson = False) -> None:
    """Two search runs on their shared episodes: SR, MSPL, steps, B minus A with 95% intervals
    (e.g. --base kinematic against --base kobuki on one seed). Runs of different code on a report
    seed are refused (bench/seeds.py)."""
    from ovamos.bench.compare import compare_runs, print_comparison
    from ovamos.bench.search import SearchError
    try:
        result = compare_runs(a, b, allow_code_change)
    except SearchError as exc:
        raise _fail(str(exc)) from None
    _report(result, as_json, print_comparison)


@bench_app.command("search")
def bench_search(
        episodes: Annotated[int, typer.Option(help="Episodes per policy (the paper: 120).")] = 120,
        seed: Annotated[int, typer.Option(help="Seed of the episode set (ids are SEED-INDEX).")] = 0,
        policies: Annotated[str, typer.Option(help="Comma-separated, of: " + ", ".join(POLICY_ORDER) + ".")] =
        ",".join(DEFAULT_POLICIES),
        workers: Annotated[int, typer.Option(help="Worker processes.")] = 2,
        out: Annotated[Optional[Path], typer.Option(help="Folder for episodes.jsonl, timings.jsonl, "
                                                         "summary.json, chart.png (or the replay PNG).")] = None,
        replay: Annotated[Optional[str], typer.Option(help="Draw one episode (SEED-INDEX, e.g. 0-3) "
                                                           "instead of running the benchmark.")] = None,
        policy: Annotated[str, typer.Option(help="Policy of the replayed episode.")] = "ovamos",
        source: Annotated[Optional[Path], typer.Option("--from", help="episodes.jsonl to read the replayed "
                                                                      "episode from (default: re-run it).")] = None,
        max_steps: Annotated[Optional[int], typer.Option(help="Step limit override, for quick runs and "
                                                              "tests only (the paper's: 500).")] = None,
        perception: Annotated[str, typer.Option(help="Simulated perception preset: ideal, realistic or hard "
                                                     "(world/perception_presets.py).")] = "ideal",
        homes: Annotated[str, typer.Option(help="Home tier: default (40-150 m2, 3-7 rooms) or large "
                                                "(150-300 m2, 8-12 rooms).")] = "default",
        resume: Annotated[bool, typer.Option(help="Keep the episodes --out already holds (a run cut short, "
                                                  "or one to add policies or episodes to) and run the rest.")
                          ] = False,
        base: Annotated[str, typer.Option(help="The robot: kinematic (each primitive lands exactly) or "
                                               "odrive, kobuki, opencr (the base controller on that simulated "
                                               "base, in simulated time).")] = "kinematic",
        motion: Annotated[str, typer.Option(help="stepwise (a primitive, then the frame after it) or continuous "
                                                 "(paths driven while the camera free-runs; a wheeled --base).")
                          ] = "stepwise",
        cluster: Annotated[Optional[str], typer.Option(help="Run the episodes on Dask instead of --workers "
                                                            "processes: local[:N] (N workers on 127.0.0.1), "
                                                            "tcp://HOST:PORT (a running dask scheduler) or "
                                                            "slurm (with --cluster-config). Needs "
                                                            "ovamos[cluster].")] = None,
        cluster_config: Annotated[Optional[Path], typer.Option(help="TOML file with a [slurm] table for "
                                                                    "--cluster slurm (queue, cores, memory, "
                                                                    "walltime, jobs).")] = None,
        odometry: Annotated[str, typer.Option(help="How the robot's odometry errs: ideal (exact, as before), "
                                                   "realistic or hard (services/sim/odometry.py).")] = "ideal",
        localization: Annotated[OnOff, typer.Option(help="Match each frame against the map, which then lives "
                                                         "in a frame that odometry drift does not move.")] = "off",
        step_latency: Annotated[Optional[float], typer.Option(
            help="Seconds a step costs besides its motion (frame, perception, fusion, decision), in a wheeled "
                 "base's search time (default: 0.183, assumed for a GPU laptop; give your own measured one).")]
        = None,
        as_json: AsJson = False) -> None:
    """Search benchmark: SR and MSPL per policy (the paper's Tables I and II), or one episode's picture."""
    from ovamos.bench.search import SearchError
    from ovamos.bench.search import main as search_main
    try:
        code = search_main(episodes=episodes, seed=seed, policies=policies, workers=workers, as_json=as_json,
                           out=out, max_steps=max_steps, replay_id=replay, policy=policy, source=source,
                           perception=perception, homes=homes, resume=resume, base=base, motion=motion,
                           cluster=cluster, cluster_config=cluster_config, odometry=odometry,
                           localization=localization == "on", step_latency=step_latency, console=console, err=err)
    except SearchError as exc:
        raise _fail(str(exc)) from None
    raise typer.Exit(code)


def _scene(seed: int, scene_file: Path | None):
    from ovamos.world.generate import generate_scene
    from ovamos.world.scene import Scene, SceneError
    if scene_file is None:
        return generate_scene(seed)
    try:
        return Scene.load(scene_file)
    except SceneError as exc:
        raise _fail(str(exc)) from None


@sim_app.command("scene")
def sim_scene(out: Annotated[Optional[Path], typer.Option(
                  help="Top-down map PNG to write (rooms, walls, objects labelled; an episode's start).")] = None,
              seed: Annotated[Optional[int], typer.Option("--seed", help="Scene seed (default 0).")] = None,
              scene_file: SceneFile = None,
              episode: Annotated[Optional[str], typer.Option(
                  help="Instead: the house of episode SEED-INDEX (e.g. 0-4, the demo's), with its start.")]
              = None,
              objects: Annotated[bool, typer.Option(
                  "--objects", help="List what the house contains: each class, its count and rooms (with "
                                    "--episode: whether a search for it can succeed).")] = False,
              as_json: Annotated[bool, typer.Option("--json", help="The list as one JSON object.")] = False,
              save: Annotated[Optional[Path], typer.Option(help="Also save the scene JSON.")] = None
              ) -> None:
    """Draw a scene from above: rooms, walls, objects with labels; or list the objects it holds."""
    import cv2

    from ovamos.world.draw import draw_scene
    if out is None and not objects and not as_json:
        raise _fail("nothing to do: give --out PNG (the picture) and/or --objects (the list)")
    start, stoppable = None, None
    if episode is not None:
        if seed is not None or scene_file is not None:
            raise _fail("--episode or --seed / --scene, not both")
        from ovamos.bench.search import SearchError, parse_episode_id
        from ovamos.world.episodes import make_episode
        try:
            spec, scene, truth = make_episode(*parse_episode_id(episode))
        except SearchError as exc:
            raise _fail(str(exc)) from None
        start, stoppable = spec.start, set(truth.stoppable_classes(spec.start.x, spec.start.y))
    else:
        scene = _scene(seed or 0, scene_file)
    if out is not None:
        cv2.imwrite(str(out), draw_scene(scene, robot=start))
    if save is not None:
        scene.save(save)
    listing = scene_objects(scene, stoppable)
    if as_json:
        print(json.dumps({"seed": scene.seed, "episode": episode, "objects": listing}))
        return
    if objects:
        console.print(objects_table(listing, stoppable is not None))
    types = sorted({r.type for r in scene.rooms})
    console.print(f"scene {scene.seed}: {scene.width:.1f} x {scene.depth:.1f} m ({scene.area:.0f} m2), "
                  f"{len(scene.rooms)} rooms ({', '.join(types)}), {len(scene.objects)} objects "
                  f"of {len(scene.classes())} classes" + (f" -> {out}" if out is not None else ""))


def scene_objects(scene: Scene, stoppable: set[str] | None = None) -> list[dict]:
    """``ovamos sim scene --objects``: per class of the scene, its count and the rooms it is in
    (named ``TYPE``, or ``TYPE ID`` where the house has several of a type); with ``stoppable``
    (an episode's), whether a STOP can succeed for it, so that a task asks for one that can."""
    types = [r.type for r in scene.rooms]
    names = {r.id: r.type if types.count(r.type) == 1 else f"{r.type} {r.id}" for r in scene.rooms}
    listing = []
    for cls in scene.classes():
        found = scene.instances(cls)
        entry = {"class": cls, "count": len(found), "rooms": sorted({names[o.room] for o in found})}
        if stoppable is not None:
            entry["stoppable"] = cls in stoppable
        listing.append(entry)
    return listing


def objects_table(listing: list[dict], with_stoppable: bool) -> Table:
    """:func:`scene_objects` for people."""
    table = Table("class", "count", "rooms", *(("a search can succeed",) if with_stoppable else ()),
                  title=f"{len(listing)} object classes")
    for entry in listing:
        table.add_row(entry["class"], str(entry["count"]), ", ".join(entry["rooms"]),
                      *(("yes" if entry["stoppable"] else "no",) if with_stoppable else ()))
    return table


@sim_app.command("render")
def sim_render(out: Annotated[Path, typer.Option(help="PNG to write: RGB | depth | ids.")],
               seed: SceneSeed = 0, scene_file: SceneFile = None,
               x: Annotated[Optional[float], typer.Option(help="Camera x (default: a free spot).")] = None,
               y: Annotated[Optional[float], typer.Option(help="Camera y.")] = None,
               yaw: Annotated[Optional[float], typer.Option(help="Heading, radians.")] = None,
               width: int = 640, height: int = 480) -> None:
    """Render what the robot's camera sees, side by side: RGB, depth, instance ids."""
    import cv2

    from ovamos.world.draw import side_by_side
    from ovamos.world.evaluator import GroundTruth
    from ovamos.world.render import SceneRenderer
    scene = _scene(seed, scene_file)
    truth = GroundTruth(scene)
    if x is None or y is None:  # default: about 2 m from the biggest object, looking at it
        biggest = max(scene.objects, key=lambda o: o.sx * o.sy)
        field = truth.object_field(biggest.id)
        x, y = truth.grid.to_world(*np.unravel_index(int(np.argmin(np.abs(field - 2.0))), field.shape))
        yaw = math.atan2(biggest.y - y, biggest.x - x) if yaw is None else yaw
    elif not truth.is_free(x, y):
        raise _fail(f"({x}, {y}) is not free space for the robot in this scene")
    yaw = 0.0 if yaw is None else yaw
    with SceneRenderer(scene, width, height) as renderer:
        frame = renderer.render(x, y, yaw)
    cv2.imwrite(str(out), side_by_side(frame))
    seen = sorted({scene.object(int(i)).cls for i in np.unique(frame.instance_ids) if i > 0})
    console.print(f"camera at ({x:.2f}, {y:.2f}) yaw {yaw:.2f}: sees {', '.join(seen) or 'no objects'}"
                  f" -> {out}")


@sim_app.command("ros2")
def sim_ros2(config: Annotated[Optional[Path], typer.Option(
                 help="Settings (TOML or JSON; services/sim/ros2_robot.py: Ros2SimRobotConfig).")] = None,
             episode: Annotated[Optional[str], typer.Option(
                 help="The robot of episode SEED-INDEX: its house and start (default: the config's, else 0-0).")] = None,
             set_: Annotated[Optional[list[str]], typer.Option(
                 "--set", help="KEY=JSON: replace a setting, e.g. base='{\"stamped\": false}' for a "
                               "Create 3's Twist (repeatable).")] = None,
             log_level: LogLevel = "INFO") -> None:
    """A simulated robot behind ROS 2 topics: cmd_vel in, odom and a RealSense's topics out, until
    Ctrl-C. DDS stays in a loopback-only namespace: run it as `python -m ovamos.shared.dds -- ovamos sim ros2`."""
    from ovamos.bench.search import SearchError, parse_episode_id
    from ovamos.services.sim.ros2_robot import Ros2SimRobotConfig
    from ovamos.services.sim.ros2_robot import main as run_robot
    from ovamos.shared.config import ServiceConfigError, parse_overrides, read_config
    from ovamos.shared.ros2 import Ros2Unavailable
    setup_logging(level=log_level)
    try:
        overrides = parse_overrides(set_ or [])
        if episode is not None:
            overrides["episode_seed"], overrides["episode_index"] = parse_episode_id(episode)
        run_robot(read_config(Ros2SimRobotConfig, config, overrides))
    except (SearchError, ServiceConfigError, Ros2Unavailable) as exc:
        raise _fail(str(exc)) from None


def main() -> None:
    app()


if __name__ == "__main__":
    main()
