"""``ovamos demo``: the whole system on this machine, driven through its HTTP API.

A router and every service (mapping, perception with the simulated backend,
planner, the simulated robot, the gateway) run as separate supervised
processes over real Zenoh on loopback, on free ports, with their configs and
logs under the output folder. The demo submits a search task over HTTP,
shows its progress live, then writes a report (JSON) and the map with the
robot's path (PNG) and stops everything. A recorder (``ovamos record``) runs
alongside and leaves the whole run in ``run.mcap`` (replay it, open it in Foxglove). The default episode is one the
method solves, so a first run shows a success; ``--seed``/``--episode``/
``--targets`` pick others. While the services are up, the caller can publish where they
answer (``publish``: the CLI writes ``OUT/endpoints.json``, which ``ovamos status``,
``submit`` and ``map`` then look at); with ``--keep-running`` the banner names them and
suggests next targets that the house contains.
"""

from __future__ import annotations

import json
import os
import signal
import threading
import time
from collections.abc import Callable, Sequence
from contextlib import AbstractContextManager, nullcontext
from pathlib import Path
from typing import Any, get_args

from rich.console import Console
from rich.live import Live
from rich.table import Table

from ovamos import fleet
from ovamos.profiles import Profile, load_profile, resolve_profile
from ovamos.services.gateway.client import GatewayClient, GatewayError
from ovamos.services.gateway.models import TaskView
from ovamos.services.mapping.config import MappingConfig
from ovamos.services.perception.config import PerceptionServiceConfig
from ovamos.services.sim.wheels import Motion
from ovamos.shared.dds import in_own_namespace
from ovamos.shared.procs import free_port, loopback
from ovamos.supervisor import Entry, Supervisor
from ovamos.world.episodes import make_episode
from ovamos.world.prior import ObjectPrior

DEMO_SEED, DEMO_EPISODE = 0, 4
#: a fleet's homes: episodes of seed 0 the method solves in 72-217 steps (in-process, default
#: config; 5, 7, 8 and 16 it does not), so a first fleet run shows a success for every robot
FLEET_EPISODES = (4, 1, 2, 3, 6, 9)
STARTUP_TIMEOUT_S = 90.0
SERVICES = ("mapping", "perception", "planner", "sim", "gateway")
#: with ``--base ros2`` the robot is a ROS 2 one (:mod:`ovamos.services.sim.ros2_robot`), driven and seen
#: through the ros2 base driver and camera
ROS2_SERVICES = ("mapping", "perception", "planner", "base_driver", "camera", "rosview", "gateway")
ROS2_BASE = "ros2"
LOCALIZATIONS = ("off", "on", "base")
"""``--localization``: none; the map matches each frame's scan against itself; the map follows the
ROS 2 robot's own localization (its stand-in for AMCL, :data:`ROS2_BASE` only)."""
BASES: tuple[str, ...] = (*get_args(Motion), ROS2_BASE)  # the simulated robot's ways to move


def demo_services(base: str) -> tuple[str, ...]:
    """The services a demo on ``base`` runs (every one shows a liveliness token but the gateway)."""
    return ROS2_SERVICES if base == ROS2_BASE else SERVICES
#: ``publish(router, gateway)``: a context that makes the endpoints known while it lasts and
#: yields where (the CLI's: ``OUT/endpoints.json``, removed when the demo stops)
Publish = Callable[[str, str], AbstractContextManager[Path | None]]


def default_timeout_s(base: str) -> float:
    """Time for a search to use its whole step budget (500 commands) on this base.

    A kinematic base completes a primitive at once (a step costs ~0.2 s of rendering,
    perception, mapping and planning); a wheeled base drives it in real time: 1.3-1.9 s per
    primitive on the simulated Kobuki and OpenCR (0.26 m/s, 1 m/s^2, closed loop to 2 mm and
    0.2 deg), so a 500-step search needs ~15 min.
    """
    return 600.0 if base == "kinematic" else 1500.0


FLEET_ID = "fleet"  # the robot id the fleet-wide services (perception, gateway) run under


def fleet_robots(count: int) -> list[str]:
    """The demo's robot ids: ``sim`` alone, ``sim1`` ... ``simN`` in a fleet."""
    return ["sim"] if count == 1 else [f"sim{i + 1}" for i in range(count)]


def suggested_targets(seed: int, episode: int, searched: Sequence[str], count: int = 3) -> list[str]:
    """Targets for a next task in episode (``seed``, ``episode``)'s house, best first.

    Only classes the house contains and a STOP can succeed for from the start (the robot stays
    in that part of the house: ``GroundTruth.stoppable_classes``), not ``searched`` already;
    furniture before small things, the bulkiest first: seen from across a room, they give a
    quick success (episode 0-4: sofa, then dining_table).
    """
    spec, scene, truth = make_episode(seed, episode)
    prior = ObjectPrior.load()
    bulk = {c: max(o.sx * o.sy * o.sz for o in scene.instances(c)) for c in scene.classes()}
    candidates = [c for c in truth.stoppable_classes(spec.start.x, spec.start.y) if c not in searched]
    return sorted(candidates, key=lambda c: (prior[c].small, -bulk[c]))[:count]


def _robot_configs(folder: Path, seed: int, episode: int, *, width: int, height: int, base: str,
                   motion: str = "stepwise", checkpoint: str = "map.ckpt", odometry: str = "ideal",
                   localization: str = "off") -> dict[str, dict[str, Any]]:
    """The per-robot services' configs for a robot in episode (``seed``, ``episode``): lock-step frames
    stepwise, free-running ones (``frame_hz``) when the robot drives continuously; the simulated
    robot's odometry erring as the preset ``odometry`` says, the map localizing or not."""
    _, scene, _ = make_episode(seed, episode)
    mapping = MappingConfig().covering(scene.width, scene.depth)
    episode_keys = {"episode_seed": seed, "episode_index": episode}
    lock_step = motion == "stepwise"
    robot = {"mapping": {"grid_cells": mapping.grid_cells, "center": list(mapping.center), "publish_hz": 5.0,
                         "checkpoint_path": str(folder / checkpoint),
                         "localization": {"enabled": localization != "off",
                                          "source": "base" if localization == "base" else "scan"}}}
    body = {"odometry": odometry, "odometry_seed": seed * 1000 + episode}
    if base != ROS2_BASE:
        return {**robot, "sim": {**episode_keys, "motion": base, "lock_step": lock_step, "width": width,
                                 "height": height, "robot": body}}
    from ovamos.services.sim.ros2_robot import BUMP_TOPIC, INSTANCE_IDS_TOPIC, MAP_POSE_TOPIC
    # the base's topics and geometry are the defaults, as the simulated robot's, which also
    # reports contact on BUMP_TOPIC and, localizing, its pose on MAP_POSE_TOPIC
    topics = {"bump": BUMP_TOPIC, **({"localization": MAP_POSE_TOPIC} if localization == "base" else {})}
    loopback_only = {"network": "loopback"}  # the rehearsal's DDS: the demo's namespace, nothing else
    return {**robot, "ros2_robot": {**episode_keys, "width": width, "height": height, "robot": body, "base": topics},
            "base_driver": {"driver": {"ros2": {**topics, **loopback_only}}},
            "rosview": loopback_only,  # the search on /ovamos/*, for RViz (deploy/ros2/ovamos.rviz)
            "camera": {"lock_step": lock_step, "ros2": {"instance_ids": INSTANCE_IDS_TOPIC, **loopback_only}}}


def _write(folder: Path, configs: dict[str, dict[str, Any]]) -> dict[str, Path]:
    """Each entry's changes to its profile's config, one JSON file each (what the demo changed, to
    read; :func:`demo_entries` passes them on as ``ovamos run --set``)."""
    folder.mkdir(parents=True, exist_ok=True)
    paths = {}
    for name, config in configs.items():
        paths[name] = folder / f"{name}.json"
        paths[name].write_text(json.dumps(config, indent=1))
    return paths


def write_configs(folder: Path, *, seed: int, episode: int, robot_id: str, http_port: int,
                  width: int = 320, height: int = 240, base: str = "kinematic", motion: str = "stepwise",
                  odometry: str = "ideal", localization: str = "off") -> dict[str, Path]:
    """Each service's changes to the demo profile's config (:func:`demo_profile`), all describing the
    same episode (scene, start pose); ``base`` is how the simulated robot moves (see ``SimServiceConfig.motion``), ``motion`` how the planner
    drives it (``[agent] motion``), ``odometry`` how its odometry errs, ``localization`` whether the
    map localizes (:data:`LOCALIZATIONS`)."""
    episode_keys = {"episode_seed": seed, "episode_index": episode}
    return _write(folder, {**_robot_configs(folder, seed, episode, width=width, height=height, base=base,
                                            motion=motion, odometry=odometry, localization=localization),
                           "perception": {"backend": "sim", "sim": episode_keys},
                           "planner": _planner_config(motion),
                           "gateway": {"port": http_port, "robots": [robot_id],
                                       "state_dir": str(folder / "gateway")}})


def _planner_config(motion: str) -> dict[str, Any]:
    return {} if motion == "stepwise" else {"agent": {"motion": motion}}


def fleet_episodes(seed: int, episode: int, robots: int) -> dict[str, int]:
    """Each robot of the demo's fleet and its episode: from the default episode, the episodes of
    :data:`FLEET_EPISODES`; from another, that one and those after it."""
    ids = fleet_robots(robots)
    if (seed, episode) == (DEMO_SEED, DEMO_EPISODE) and robots <= len(FLEET_EPISODES):
        return dict(zip(ids, FLEET_EPISODES))
    return {robot: episode + i for i, robot in enumerate(ids)}


def write_fleet_configs(folder: Path, *, seed: int, episodes: dict[str, int], http_port: int,
                        width: int = 320, height: int = 240, base: str = "kinematic", motion: str = "stepwise",
                        odometry: str = "ideal", localization: str = "off") -> dict[str, Path]:
    """A fleet's configs (:mod:`ovamos.fleet`): ``mapping-R`` and ``sim-R`` per robot R, each
    robot in its own home (``episodes[R]``); one ``perception`` that batches across the robots,
    reading each robot's frames in its scene; one ``planner`` config and one ``gateway`` for all."""
    robots = list(episodes)
    homes = {robot: fleet.scene(seed, index) for robot, index in episodes.items()}
    configs: dict[str, dict[str, Any]] = {}
    for robot, home in homes.items():
        for name, config in _robot_configs(folder, seed, home["episode_index"], width=width, height=height,
                                           base=base, motion=motion, checkpoint=f"map-{robot}.ckpt",
                                           odometry=odometry, localization=localization).items():
            configs[f"{name}-{robot}"] = config
    perception = PerceptionServiceConfig(backend="sim", batch_size=len(robots), batch_wait_ms=10.0)
    configs["perception"] = {**perception.model_dump(mode="json", include={"backend", "batch_size", "batch_wait_ms"}),
                             **fleet.fleet_wide_settings("perception", perception, robots, homes)}
    configs["planner"] = _planner_config(motion)
    configs["gateway"] = {"port": http_port, "robots": robots, "state_dir": str(folder / "gateway")}
    return _write(folder, configs)


def demo_profile(base: str = "kinematic", *, fleet_of: Sequence[str] = ()) -> Profile:
    """The shipped profile the demo runs (``ovamos up`` runs the same): ``all``, ``all-ros2`` on the
    ros2 base, ``fleet`` with the robots ``fleet_of``."""
    if fleet_of:
        return load_profile(resolve_profile("fleet")).model_copy(update={"robots": list(fleet_of),
                                                                          "robot_id": FLEET_ID})
    return load_profile(resolve_profile("all-ros2" if base == ROS2_BASE else "all"))


def demo_entries(configs: dict[str, Path], *, robot_id: str, zenoh_port: int,
                 record: Path | None = None, base: str = "kinematic") -> list[Entry]:
    """The demo profile's router (on ``zenoh_port``) and services with the demo's ``configs`` on top
    (:func:`write_configs`); a recorder writing ``record`` (if given; it starts before the services
    and stops after them, so it holds the whole run), and on the ros2 base the ROS 2 robot."""
    profile = demo_profile(base).model_copy(update={"robot_id": robot_id})
    router, *services = profile.entries(endpoint=loopback(zenoh_port), changes=_changes(configs))
    robot = [Entry("ros2_robot", ("sim", "ros2", "--config", str(configs["ros2_robot"])))] \
        if base == ROS2_BASE else []
    return [router, *_recorders([robot_id], zenoh_port, record), *robot, *services]


def fleet_entries(configs: dict[str, Path], *, robots: list[str], zenoh_port: int,
                  record: Path | None = None) -> list[Entry]:
    """:func:`demo_entries` for a fleet (configs from :func:`write_fleet_configs`), the ``fleet``
    profile's: per-robot services as ``NAME-ROBOT``, perception and the gateway once, under
    :data:`FLEET_ID`; with ``record``, one recording per robot (``run-R.mcap`` beside it)."""
    router, *services = demo_profile(fleet_of=robots).entries(endpoint=loopback(zenoh_port),
                                                              changes=_changes(configs))
    return [router, *_recorders(robots, zenoh_port, record), *services]


def _changes(configs: dict[str, Path]) -> dict[str, dict[str, Any]]:
    return {name: json.loads(path.read_text()) for name, path in configs.items() if name != "ros2_robot"}


def _recorders(robots: list[str], zenoh_port: int, record: Path | None) -> list[Entry]:
    if record is None:
        return []
    return [Entry("record" if len(robots) == 1 else f"record-{robot}",
                  ("record", "--robot-id", robot, "--out", str(_recording(record, robot, len(robots))),
                   "--overwrite", "--connect", loopback(zenoh_port))) for robot in robots]


def _recording(record: Path, robot: str, robots: int) -> Path:
    return record if robots == 1 else record.with_name(f"{record.stem}-{robot}{record.suffix}")


def _progress(views: dict[str, TaskView | None], elapsed: float) -> Table:
    table = Table("robot", "status", "targets", "found", "steps", "distance",
                  title=f"search tasks ({elapsed:.0f} s)")
    for robot, view in views.items():
        if view is None:
            table.add_row(robot, "starting the services ...", "", "", "", "")
            continue
        table.add_row(robot, view.status.value + (f" ({view.message})" if view.message else ""),
                      ", ".join(view.targets),
                      ", ".join(f"{f.label} at ({f.x:.1f}, {f.y:.1f}) step {f.step}" for f in view.found) or "-",
                      f"{view.steps} / {view.max_steps}", f"{view.distance_m:.2f} m")
    return table


def wait_for_services(client: GatewayClient, robots: list[str], deadline: float,
                      services: Sequence[str] = SERVICES) -> None:
    """Until every service of each robot shows its liveliness token (the gateway asks Zenoh; its
    answering is the gateway's own sign of life, so a gateway not listening yet is waited for
    too, and a fleet's runs under the fleet's id)."""
    wanted = set(services) - {"gateway"}
    while time.monotonic() < deadline:
        try:
            health = client.health()["robots"]
            if all({s["service"] for s in health[robot]["services"]} >= wanted for robot in robots):
                return
        except GatewayError:
            pass
        time.sleep(0.5)
    raise TimeoutError(f"the services did not all come up within {STARTUP_TIMEOUT_S:.0f} s "
                       f"(see the logs)")


def run_demo(console: Console, *, out_dir: Path, seed: int = DEMO_SEED, episode: int = DEMO_EPISODE,
             targets: list[str] | None = None, robot_id: str = "sim", keep_running: bool = False,
             timeout_s: float | None = None, base: str = "kinematic", record: Path | None = None,
             robots: int = 1, publish: Publish | None = None, max_steps: int | None = None,
             motion: str = "stepwise", odometry: str = "ideal", localization: str = "off") -> int:
    """Run the demo; ``record``: the MCAP file to record the run to (None: no recording);
    ``max_steps``: each task's step limit (None: the gateway's default, the paper's 500); ``motion``:
    stepwise or continuous (a wheeled ``base`` only); ``odometry``: how the simulated robot's
    odometry errs (a preset); ``localization``: whether the map localizes, and how
    (:data:`LOCALIZATIONS`).

    ``robots`` > 1: a fleet (:func:`write_fleet_configs`), robot i searching episode
    ``episode + i`` (its own home) for that episode's targets (or ``targets``), all at once.
    ``publish``: see :data:`Publish`; entered once every service is up, left when they stop."""
    episodes = {robot_id: episode} if robots == 1 else fleet_episodes(seed, episode, robots)
    fleet_ids = list(episodes)
    tasks = {robot: targets or list(make_episode(seed, e)[0].targets) for robot, e in episodes.items()}
    http_port, zenoh_port = free_port(), free_port()
    url, router = f"http://127.0.0.1:{http_port}", loopback(zenoh_port)
    if robots == 1:
        configs = write_configs(out_dir / "config", seed=seed, episode=episode, robot_id=robot_id,
                                http_port=http_port, base=base, motion=motion, odometry=odometry,
                                localization=localization)
        entries = demo_entries(configs, robot_id=robot_id, zenoh_port=zenoh_port, record=record, base=base)
    else:
        configs = write_fleet_configs(out_dir / "config", seed=seed, episodes=episodes,
                                      http_port=http_port, base=base, motion=motion, odometry=odometry,
                                      localization=localization)
        entries = fleet_entries(configs, robots=fleet_ids, zenoh_port=zenoh_port, record=record)
    for robot, e in episodes.items():
        console.print(f"{robot}: episode {seed}-{e}: {', '.join(tasks[robot])}")
    console.print(f"router {router}, gateway {url}; logs in {out_dir / 'logs'}")
    started = time.monotonic()
    with Supervisor(entries, log_dir=out_dir / "logs") as supervisor, GatewayClient(url) as client:
        deadline = started + STARTUP_TIMEOUT_S
        wait_for_services(client, fleet_ids, deadline, demo_services(base))
        with publish(router, url) if publish is not None else nullcontext() as endpoints_file:
            views = _search(console, client, tasks, started,
                            default_timeout_s(base) * robots if timeout_s is None else timeout_s, max_steps)
            outcome = _write_results(console, client, views, out_dir, seed, episodes,
                                     time.monotonic() - started, supervisor)
            if keep_running:
                _print(console, outcome)
                first = fleet_ids[0]
                _serve_until_interrupted(console, router, url, first, f"{seed}-{episodes[first]}",
                                         suggested_targets(seed, episodes[first], tasks[first]), endpoints_file)
    if record is not None:  # complete once the supervisor stopped the recorder, after the services
        for robot in fleet_ids:
            path = _recording(record, robot, robots)
            console.print(f"recorded the run to {path} (ovamos replay {path}; or open it in Foxglove)")
    if not keep_running:
        _print(console, outcome)  # last: one line per robot
    return 0 if all(v.status.value == "done" for v in views.values()) else 1


def _print(console: Console, lines: list[str]) -> None:
    for line in lines:
        console.print(line)


def _search(console: Console, client: GatewayClient, tasks: dict[str, list[str]], started: float,
            timeout_s: float, max_steps: int | None = None) -> dict[str, TaskView]:
    """Submit each robot's task at once and follow them until all are over (or the time is up:
    those still running are cancelled)."""
    ids = {robot: client.submit(targets, robot_id=robot, max_steps=max_steps).id for robot, targets in tasks.items()}
    views = {robot: client.get(task_id) for robot, task_id in ids.items()}
    with Live(_progress(dict(views), 0.0), console=console, refresh_per_second=4) as live:
        deadline = time.monotonic() + timeout_s
        while not all(v.final for v in views.values()) and time.monotonic() < deadline:
            time.sleep(0.5)
            views = {robot: client.get(task_id) for robot, task_id in ids.items()}
            live.update(_progress(dict(views), time.monotonic() - started))
    if not console.is_terminal:  # Live's last frame ends without a newline when piped: done lines start one
        console.line()
    return {robot: view if view.final else client.cancel(ids[robot]) for robot, view in views.items()}


def _write_results(console: Console, client: GatewayClient, views: dict[str, TaskView], out_dir: Path,
                   seed: int, episodes: dict[str, int], seconds: float, supervisor: Supervisor) -> list[str]:
    """Write the report (one robot: its task at the top level, as before; a fleet: ``robots``, each
    robot's episode and task) and each robot's map; return one ``done: ...`` line per robot."""
    out_dir.mkdir(parents=True, exist_ok=True)
    single = len(views) == 1
    maps = {robot: out_dir / ("demo_map.png" if single else f"demo_map-{robot}.png") for robot in views}
    for robot, path in maps.items():
        try:
            path.write_bytes(client.map_png(robot))
        except GatewayError as exc:
            console.print(f"[yellow]no map image of {robot}:[/yellow] {exc}")
    per_robot = {robot: {"episode": f"{seed}-{episodes[robot]}", "task": json.loads(view.model_dump_json())}
                 for robot, view in views.items()}
    restarts = {s.name: s.restarts for s in supervisor.status()}
    report: dict[str, Any] = ({**next(iter(per_robot.values())), "seconds": round(seconds, 1), "restarts": restarts}
                              if single else {"seconds": round(seconds, 1), "robots": per_robot, "restarts": restarts})
    report_path = out_dir / "demo_report.json"
    report_path.write_text(json.dumps(report, indent=1))
    lines = []
    for robot, view in views.items():
        found = ", ".join(f.label for f in view.found) or "nothing"
        colour = "green" if view.status.value == "done" else "red"
        who = "" if single else f"{robot} "
        lines.append(f"[{colour}]{view.status.value}[/{colour}]: {who}found {found} in {view.steps} steps, "
                     f"{view.distance_m:.1f} m; report {report_path}, map {maps[robot]}")
    return lines


def banner(router: str, url: str, robot_id: str, episode_id: str, suggested: Sequence[str],
           endpoints_file: Path | None) -> str:
    """What the keep-running demo says: where it answers, and a next task for a target the house
    contains (``suggested``, from :func:`suggested_targets`), over HTTP and with ``ovamos submit``."""
    lines = [f"Everything keeps running: router {router}, gateway {url}"
             + (f" (in {endpoints_file}: ovamos status / submit / map take it as --endpoints)"
                if endpoints_file else "") + ".",
             f"Operator page: {url}/ (API docs: {url}/docs)."]
    if suggested:
        where = f"--endpoints {endpoints_file}" if endpoints_file else f"--gateway {url}"
        lines += [f"Try a next search in the house of episode {episode_id}:",
                  f"  curl -X POST {url}/v1/tasks -H 'Content-Type: application/json' "
                  f"-d '{{\"targets\": [\"{suggested[0]}\"], \"robot_id\": \"{robot_id}\"}}'",
                  f"  ovamos submit {suggested[0]} --robot-id {robot_id} {where}"]
    if suggested[1:]:
        lines.append(f"Other targets there: {', '.join(suggested[1:])}.")
    lines.append(f"Everything the house contains: ovamos sim scene --episode {episode_id} --objects")
    if in_own_namespace():
        lines.append("These addresses are in the demo's own network namespace (--base ros2): from another "
                     f"shell, nsenter --net=/proc/{os.getpid()}/ns/net COMMAND (as root); the search is on "
                     "the /ovamos/* ROS topics there (rviz2 -d deploy/ros2/ovamos.rviz, with the same "
                     "FASTRTPS_DEFAULT_PROFILES_FILE).")
    lines.append("Ctrl-C stops everything.")
    return "\n".join(lines)


def _serve_until_interrupted(console: Console, router: str, url: str, robot_id: str, episode_id: str,
                             suggested: Sequence[str], endpoints_file: Path | None) -> None:
    # no markup (the JSON's brackets) and no wrapping inserted: its commands are for copying
    console.print(banner(router, url, robot_id, episode_id, suggested, endpoints_file), markup=False,
                  soft_wrap=True)
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    stop.wait()
