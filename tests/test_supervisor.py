"""The supervisor behind ``ovamos up``: real ``ovamos`` children, crashes, restarts, clean stops,
and deployment profiles that are checked before anything starts.

Children are real processes (a router, the test-pattern camera, and a command
that fails), since what can go wrong here (ordering, signals, process groups,
leftover processes) only shows with real ones.
"""

from __future__ import annotations

import io
import json
import os
import signal
import subprocess
import sys
import textwrap
from collections.abc import Iterator
from pathlib import Path

import pytest
from rich.console import Console
from rich.table import Table

from ovamos.profiles import (
    PROFILE_DIR,
    ProfileError,
    check_service_configs,
    laptop_endpoint,
    load_profile,
    resolve_profile,
    supervisor_for,
    tcp_address,
)
from ovamos.shared.motion import DriveMode
from ovamos.shared.procs import free_port, kill, loopback
from ovamos.shared.service import load_config
from ovamos.supervisor import Backoff, Entry, State, Supervisor, SupervisorError, exit_reason, port_open, status_table
from tests.polling import status_cli, wait_for

pytestmark = pytest.mark.system  # processes, routers, browsers or real-time devices: make test-all

REPO = Path(__file__).resolve().parents[1]
SHIPPED = sorted(PROFILE_DIR.glob("*.toml"))
# Restart quickly in tests; the shipped default starts at 0.5 s.
FAST = Backoff(initial_s=0.2, factor=2.0, max_s=0.8, reset_after_s=120.0)
TIMEOUT = 60.0  # generous: other test suites load this 2-core machine


def router_entry(port: int) -> Entry:
    return Entry("router", ("router", "--listen", loopback(port), "--log-level", "WARNING"),
                 ready=("127.0.0.1", port))


def camera_entry(port: int, robot_id: str = "suptest") -> Entry:
    return Entry("camera", ("run", "testpattern", "--connect", loopback(port), "--robot-id", robot_id))


def render(table: Table) -> str:
    console = Console(file=io.StringIO(), width=200)
    console.print(table)
    return console.file.getvalue()  # type: ignore[attr-defined]


def status_of(sup: Supervisor, name: str):
    return next(s for s in sup.status() if s.name == name)


def group_alive(pid: int) -> bool:
    """Whether any process of the group ``pid`` leads still exists."""
    try:
        os.killpg(pid, 0)
        return True
    except ProcessLookupError:
        return False


@pytest.fixture
def supervisors() -> Iterator[list[Supervisor]]:
    """Supervisors a test made; each is stopped even when the test fails."""
    made: list[Supervisor] = []
    yield made
    for sup in made:
        sup.stop()


# -- pure rules -----------------------------------------------------------------------------
def test_backoff_doubles_up_to_the_cap_and_resets_after_a_long_run() -> None:
    b = Backoff(initial_s=0.5, factor=2.0, max_s=30.0, reset_after_s=60.0)
    assert [b.delay(n) for n in range(1, 9)] == [0.5, 1, 2, 4, 8, 16, 30, 30]
    assert b.failures_after(3, uptime_s=5.0) == 4      # crashed again soon: wait longer
    assert b.failures_after(3, uptime_s=60.0) == 1     # had been healthy: restart quickly


def test_exit_reasons_name_the_code_or_the_signal() -> None:
    assert exit_reason(2) == "exit code 2"
    assert exit_reason(-signal.SIGKILL) == "killed by SIGKILL"
    assert exit_reason(-signal.SIGSEGV) == "killed by SIGSEGV"


def test_endpoints_to_probe() -> None:
    assert tcp_address("tcp/127.0.0.1:7447") == ("127.0.0.1", 7447)
    assert tcp_address("tcp/0.0.0.0:7447") == ("127.0.0.1", 7447)
    assert tcp_address("tcp/[::1]:7448#iface=lo") == ("::1", 7448)
    assert tcp_address("udp/127.0.0.1:7447") is None
    assert laptop_endpoint("192.168.1.10:7447") == "tcp/192.168.1.10:7447"
    for bad in ("192.168.1.10", ":7447", "host:0", "host:99999", "host:port"):
        with pytest.raises(ProfileError, match="HOST:PORT"):
            laptop_endpoint(bad)


def test_entry_names_must_be_unique(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="unique"):
        Supervisor([Entry("a", ("router",)), Entry("a", ("router",))], log_dir=tmp_path)


# -- real processes -------------------------------------------------------------------------
def test_router_first_then_services_and_stop_leaves_nothing(tmp_path: Path,
                                                            supervisors: list[Supervisor]) -> None:
    """The camera is listed first, yet starts only once the router's port accepts connections."""
    port = free_port()
    sup = Supervisor([camera_entry(port), router_entry(port)], log_dir=tmp_path / "logs", backoff=FAST)
    supervisors.append(sup)
    sup.start()
    router, camera = status_of(sup, "router"), status_of(sup, "camera")
    assert router.ready_at is not None and camera.first_started_at is not None
    assert router.first_started_at is not None and router.first_started_at <= router.ready_at
    assert camera.first_started_at >= router.ready_at
    wait_for(lambda: any(s["service"] == "testpattern" for s in status_cli(port, "suptest")),
             timeout=TIMEOUT, what="the supervised camera on the router")
    assert [s.state for s in sup.status()] == [State.RUNNING, State.RUNNING]
    procs = [sup.process("router"), sup.process("camera")]
    assert all(p is not None for p in procs)
    assert "camera" in render(status_table(sup.status()))

    sup.stop()
    assert all(p.returncode is not None and not group_alive(p.pid) for p in procs if p)
    assert [s.state for s in sup.status()] == [State.STOPPED, State.STOPPED]
    assert not port_open("127.0.0.1", port)
    assert sup.restart_events == []  # a requested stop is not a crash
    header = (tmp_path / "logs" / "camera.log").read_text().splitlines()[0]
    assert header.endswith(f"start: ovamos run testpattern --connect {loopback(port)} --robot-id suptest")


def test_a_killed_child_is_restarted_and_counted(tmp_path: Path, supervisors: list[Supervisor]) -> None:
    port = free_port()
    sup = Supervisor([router_entry(port), camera_entry(port)], log_dir=tmp_path, backoff=FAST)
    supervisors.append(sup)
    sup.start()
    for crash in (1, 2):
        proc = wait_for(lambda: sup.process("camera"), timeout=TIMEOUT, what="the camera running")
        kill(proc)  # SIGKILL, as a crash or the OOM killer would
        wait_for(lambda n=crash: status_of(sup, "camera").restarts == n
                 and status_of(sup, "camera").state is State.RUNNING,
                 timeout=TIMEOUT, what=f"restart #{crash}")
        new = sup.process("camera")
        assert new is not None and new.pid != proc.pid
    events = [e for e in sup.restart_events if e.name == "camera"]
    assert [e.reason for e in events] == ["killed by SIGKILL"] * 2
    assert [e.delay_s for e in events] == [0.2, 0.4]  # crashed again soon after: backs off
    assert status_of(sup, "router").restarts == 0
    assert status_of(sup, "camera").last_exit == "killed by SIGKILL"
    wait_for(lambda: any(s["service"] == "testpattern" for s in status_cli(port, "suptest")),
             timeout=TIMEOUT, what="the restarted camera back on the router")


def test_a_failing_child_backs_off_and_its_log_says_why(tmp_path: Path,
                                                        supervisors: list[Supervisor]) -> None:
    """A child that keeps exiting non-zero is retried ever more slowly."""
    sup = Supervisor([Entry("broken", ("run", "no-such-service"))], log_dir=tmp_path, backoff=FAST)
    supervisors.append(sup)
    sup.start()
    wait_for(lambda: len(sup.restart_events) >= 3, timeout=TIMEOUT, what="three crashes")
    sup.stop()
    events = sup.restart_events
    assert [e.delay_s for e in events[:3]] == [0.2, 0.4, 0.8]  # the cap is covered above
    assert all(e.reason == "exit code 2" for e in events)
    assert all(b.at - a.at >= a.delay_s for a, b in zip(events, events[1:]))
    assert status_of(sup, "broken").restarts >= 2
    text = (tmp_path / "broken.log").read_text()
    assert text.count("start: ovamos run no-such-service") >= 3
    assert "unknown service 'no-such-service'" in text


def test_a_child_that_ends_cleanly_is_not_restarted(tmp_path: Path, supervisors: list[Supervisor]) -> None:
    sup = Supervisor([Entry("version", ("--version",))], log_dir=tmp_path, backoff=FAST)
    supervisors.append(sup)
    sup.start()
    wait_for(lambda: status_of(sup, "version").state is State.EXITED, timeout=TIMEOUT, what="the exit")
    assert status_of(sup, "version").last_exit == "exit code 0"
    assert status_of(sup, "version").restarts == 0 and sup.restart_events == []
    assert "ovamos" in (tmp_path / "version.log").read_text()


def test_a_large_log_is_rotated_when_its_child_starts(tmp_path: Path, supervisors: list[Supervisor]) -> None:
    log = tmp_path / "version.log"
    for generation in (3, 2, 1):
        log.with_name(f"version.log.{generation}").write_text(f"generation {generation}\n")
    log.write_text("old output\n" * 100)
    sup = Supervisor([Entry("version", ("--version",))], log_dir=tmp_path, backoff=FAST, max_log_bytes=500)
    supervisors.append(sup)
    sup.start()
    wait_for(lambda: status_of(sup, "version").state is State.EXITED, timeout=TIMEOUT, what="the exit")
    assert log.read_text().startswith("=== ") and "old output" not in log.read_text()
    assert (tmp_path / "version.log.1").read_text() == "old output\n" * 100
    assert (tmp_path / "version.log.2").read_text() == "generation 1\n"
    assert (tmp_path / "version.log.3").read_text() == "generation 2\n"  # generation 3 dropped
    assert not (tmp_path / "version.log.4").exists()


def test_a_router_that_cannot_start_is_an_error_naming_its_log(tmp_path: Path) -> None:
    """Two routers on one port: the second exits, and start() says so instead of waiting forever."""
    port = free_port()
    first = Supervisor([router_entry(port)], log_dir=tmp_path / "a")
    with first:
        clash = Entry("router2", router_entry(port).argv, ready=("127.0.0.1", free_port()))
        second = Supervisor([clash], log_dir=tmp_path / "b")
        with pytest.raises(SupervisorError, match=r"router2 ended \(exit code 2\).*router2\.log"):
            second.start()
        assert status_of(second, "router2").state is State.STOPPED


def test_sigterm_to_the_supervisor_stops_its_children(tmp_path: Path) -> None:
    """``run_forever`` (what ``ovamos up`` runs) turns SIGTERM into a clean stop of everything."""
    port = free_port()
    script = textwrap.dedent(f"""
        import logging, sys
        from ovamos.supervisor import Supervisor, Entry
        logging.basicConfig(level=logging.INFO, stream=sys.stdout, format="%(message)s", force=True)
        entries = [Entry("router", ("router", "--listen", "{loopback(port)}"), ready=("127.0.0.1", {port})),
                   Entry("camera", ("run", "testpattern", "--connect", "{loopback(port)}"))]
        sys.exit(Supervisor(entries, log_dir=sys.argv[1]).run_forever(
            on_started=lambda sup: print("PIDS", *[s.pid for s in sup.status()], flush=True)))
    """)
    proc = subprocess.Popen([sys.executable, "-c", script, str(tmp_path)], cwd=REPO, text=True,
                            stdout=subprocess.PIPE, start_new_session=True)
    try:
        pids: list[int] = []
        for line in proc.stdout or ():
            if line.startswith("PIDS"):
                pids = [int(p) for p in line.split()[1:]]
                break
        assert len(pids) == 2, "the supervisor did not report its children"
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(TIMEOUT) == 0
        output = (proc.stdout.read() if proc.stdout else "")
        assert "stopped camera" in output and "stopped router" in output
        assert output.index("stopped camera") < output.index("stopped router")  # reverse order
        assert not any(group_alive(pid) for pid in pids)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
        if proc.stdout:
            proc.stdout.close()


def test_a_profile_runs_end_to_end(tmp_path: Path, supervisors: list[Supervisor]) -> None:
    """A profile file becomes working argv: its router and service meet on Zenoh (moved to a free port)."""
    port = free_port()
    profile = write_profile(tmp_path, f"""
        robot_id = "profiled"
        [router]
        config = "{REPO}/deploy/zenoh/router.json5"
        [[services]]
        service = "testpattern"
        zenoh = "{REPO}/deploy/zenoh/service.json5"
        [restart]
        initial_s = 0.1
    """)
    sup = supervisor_for(profile, log_dir=tmp_path / "logs", endpoint=loopback(port))
    supervisors.append(sup)
    assert sup.backoff.initial_s == 0.1
    sup.start()
    live = wait_for(lambda: status_cli(port, "profiled"), timeout=TIMEOUT, what="the profiled service")
    assert [(s["service"], s["instance"]) for s in live] == [("testpattern", "0")]
    assert (tmp_path / "logs" / "testpattern.log").exists()


# -- profiles -------------------------------------------------------------------------------
def write_profile(tmp_path: Path, text: str, name: str = "p.toml") -> Path:
    path = tmp_path / name
    path.write_text(textwrap.dedent(text))
    return path


def test_profile_paths_are_relative_to_the_file_and_flags_are_built(tmp_path: Path) -> None:
    (tmp_path / "m.toml").write_text("publish_hz = 1.0\n")
    path = write_profile(tmp_path, f"""
        robot_id = "r7"
        [router]
        config = "{REPO}/deploy/zenoh/robot-router.json5"
        [[services]]
        service = "mapping"
        config = "m.toml"
        instance = "2"
        delay_s = 1.5
    """)
    profile = load_profile(path)
    router, mapping = profile.entries(router_connect=[laptop_endpoint("10.0.0.5:7447")])
    assert router.ready == ("127.0.0.1", 7448)
    assert router.argv == ("router", "--config", str(REPO / "deploy/zenoh/robot-router.json5"),
                           "--connect", "tcp/10.0.0.5:7447")
    assert mapping.name == "mapping-2" and mapping.delay_s == 1.5
    assert mapping.argv == ("run", "mapping", "--robot-id", "r7", "--instance", "2",
                            "--config", str(tmp_path / "m.toml"))
    assert profile.entries()[0].argv[-1] == str(REPO / "deploy/zenoh/robot-router.json5")
    moved = profile.entries(endpoint="tcp/127.0.0.1:9999")
    assert moved[0].ready == ("127.0.0.1", 9999) and moved[0].argv[-2:] == ("--listen", "tcp/127.0.0.1:9999")
    assert moved[1].argv[-2:] == ("--connect", "tcp/127.0.0.1:9999")


def _configs(entries: list[Entry]) -> dict[str, object]:
    """Each service entry's config as ``ovamos run`` would load it (its file and its --set overrides)."""
    from ovamos.registry import service_class
    from ovamos.shared.config import parse_overrides
    loaded = {}
    for e in entries:
        if e.argv[0] != "run":
            continue
        argv = list(e.argv)
        config = argv[argv.index("--config") + 1] if "--config" in argv else None
        sets = [argv[i + 1] for i, a in enumerate(argv) if a == "--set"]
        loaded[e.name] = load_config(service_class(argv[1]), config, parse_overrides(sets))
    return loaded


def _entries(profile: str, motion: DriveMode | None = None) -> list[Entry]:
    return load_profile(resolve_profile(profile)).entries(motion=motion)


def test_up_motion_sets_the_planner_camera_and_simulated_robot_and_keeps_the_rest() -> None:
    """``ovamos up PROFILE --motion continuous``: the planner drives paths (the rest of its agent
    section as configured), the camera and the simulated robot free-run, a kinematic simulated
    robot gets wheels; ``--motion stepwise`` lock-steps them; without it, the configs rule."""
    plain = _configs(_entries("all"))
    moving = _configs(_entries("all", "continuous"))
    assert moving["planner"].agent.motion == "continuous"  # type: ignore[attr-defined]
    assert moving["planner"].agent.model_dump(exclude={"motion"}) == plain["planner"].agent.model_dump(exclude={"motion"})  # type: ignore[attr-defined]
    assert (moving["sim"].lock_step, moving["sim"].motion) == (False, "kobuki")  # type: ignore[attr-defined]
    assert (plain["sim"].lock_step, plain["sim"].motion, plain["planner"].agent.motion) == (True, "kinematic", "stepwise")  # type: ignore[attr-defined]
    assert moving["mapping"] == plain["mapping"] and moving["gateway"] == plain["gateway"]
    robot = _configs(_entries("robot", "continuous"))
    assert robot["camera"].lock_step is False  # type: ignore[attr-defined]
    assert _configs(_entries("robot", "stepwise"))["camera"].lock_step is True  # type: ignore[attr-defined]
    assert _configs(_entries("laptop", "continuous"))["planner"].agent.motion == "continuous"  # type: ignore[attr-defined]


def test_up_refuses_an_unknown_motion() -> None:
    done = subprocess.run([sys.executable, "-m", "ovamos.cli", "up", "all", "--motion", "smooth"],
                          capture_output=True, text=True, timeout=60)
    assert done.returncode != 0 and "--motion 'smooth': one of stepwise, continuous" in done.stdout + done.stderr


@pytest.mark.parametrize(("text", "expected"), [
    ("[[services]]\nservice = 'mapping'\nbogus = 1\n",
     r"services\[0\] \(mapping\): bogus: Extra inputs are not permitted"),
    ("robot_idd = 'x'\n[[services]]\nservice = 'mapping'\n", r"robot_idd: Extra inputs"),
    ("[[services]]\nservice = 'mapper'\n", r"services\[0\] \(mapper\): unknown service 'mapper'; known: "),
    ("[[services]]\nservice = 'mapping'\nconfig = 'nope.toml'\n",
     r"services\[0\] \(mapping\): config file .*nope\.toml does not exist"),
    ("[router]\nconfig = 'nope.json5'\n", r"router: config file .*nope\.json5 does not exist"),
    ("[[services]]\nservice = 'mapping'\n[[services]]\nservice = 'mapping'\n",
     r"services\[1\] \(mapping\): name 'mapping' is used twice"),
    ("[[services]]\nservice = 'planner'\ndelay_s = -1\n", r"services\[0\] \(planner\): delay_s: "),
    ("[restart]\ninitial_s = 0\n", r"restart.initial_s: "),
    ("description = 'nothing'\n", "nothing to run"),
    ("[[services]\n", "cannot read profile"),
])
def test_profile_errors_name_the_file_and_the_entry(tmp_path: Path, text: str, expected: str) -> None:
    path = write_profile(tmp_path, text, name="bad.toml")
    with pytest.raises(ProfileError, match=expected) as info:
        load_profile(path)
    assert "bad.toml" in str(info.value)


def test_a_service_config_that_does_not_fit_its_service_is_refused(tmp_path: Path) -> None:
    (tmp_path / "m.toml").write_text("publish_hz = -1\n")
    path = write_profile(tmp_path, "[[services]]\nservice = 'mapping'\nconfig = 'm.toml'\n")
    with pytest.raises(ProfileError, match=r"p\.toml: services\[0\] \(mapping\): .*publish_hz"):
        check_service_configs(load_profile(path))


def test_unknown_profile_names_list_the_shipped_ones() -> None:
    assert resolve_profile("all") == PROFILE_DIR / "all.toml"
    with pytest.raises(ProfileError, match="all, all-ros2, fleet, laptop, laptop-secure, robot, robot-ros2, robot-secure"):
        resolve_profile("everything")


def test_shipped_profiles_are_complete_and_valid() -> None:
    """all / laptop / robot (and the secure two) parse, reference existing files, and say what the
    design asks."""
    assert [p.stem for p in SHIPPED] == ["all-ros2", "all", "fleet", "laptop-secure", "laptop", "robot-ros2",
                                         "robot-secure", "robot"]
    wanted = {"all": {"gateway", "perception", "mapping", "planner", "sim"},
              "laptop": {"gateway", "perception", "mapping", "planner"},
              "robot": {"base_driver", "camera"}}
    wanted |= {"laptop-secure": wanted["laptop"], "robot-secure": wanted["robot"], "fleet": wanted["all"],
               "robot-ros2": wanted["robot"] | {"rosview"},
               "all-ros2": wanted["laptop"] | wanted["robot"] | {"rosview"}}
    for path in SHIPPED:
        profile = load_profile(path)  # also checks that every referenced file exists
        check_service_configs(profile)  # registered services: configs fit their models
        assert {s.service for s in profile.services} == wanted[path.stem], path.name
        assert profile.router is not None and profile.router.config is not None
        entries = profile.entries()
        assert entries[0].ready is not None and all(e.ready is None for e in entries[1:])
        for spec in profile.services:
            # Zenoh files live in deploy/zenoh, which test_zconfig checks for loopback + no multicast.
            assert spec.zenoh is not None and spec.zenoh.parent == REPO / "deploy" / "zenoh"
            assert spec.config is not None and spec.config.parent == REPO / "deploy" / "services"
            assert not spec.connect
        assert not profile.router.listen and not profile.router.connect


def test_shipped_service_configs_fit_their_services() -> None:
    """Each deploy/services file validates against its service's config class."""
    from ovamos.registry import service_class
    checked = []
    for path in sorted((REPO / "deploy" / "services").glob("*.toml")):
        load_config(service_class(path.stem.split("-")[0]), path)
        checked.append(path.stem)
    assert checked == ["base_driver-kobuki", "base_driver-opencr", "base_driver-ros2-tb3", "base_driver-ros2-tb4",
                       "base_driver-ros2", "base_driver", "camera-ros2-oakd", "camera-ros2-realsense", "camera-ros2",
                       "camera", "gateway-laptop",
                       "gateway", "mapping", "perception-fleet", "perception-hf", "perception-sim", "planner", "rosview", "sim"]


def test_a_fleet_profile_runs_per_robot_services_per_robot_and_tells_the_others_the_robots() -> None:
    """The shipped fleet: mapping, planner and a simulated robot per robot, each robot in its own
    home (the episode after the previous robot's), one perception told each robot's scene, one
    gateway; each process's settings parse as its service's config."""
    from ovamos.registry import service_class
    from ovamos.shared.config import parse_overrides
    entries = {e.name: e for e in load_profile(resolve_profile("fleet")).entries()}
    assert sorted(entries) == sorted(["router", "gateway", "perception",
                                      *(f"{s}-{r}" for s in ("mapping", "planner", "sim") for r in ("r1", "r2", "r3"))])

    def settings(entry: Entry) -> dict:
        argv = list(entry.argv)
        service, config = argv[1], Path(argv[argv.index("--config") + 1])
        sets = parse_overrides([argv[i + 1] for i, a in enumerate(argv) if a == "--set"])
        load_config(service_class(service), config, sets)  # the process would accept them
        return {"robot": argv[argv.index("--robot-id") + 1], **sets}

    assert settings(entries["sim-r3"]) == {"robot": "r3", "episode_seed": 0, "episode_index": 2}
    assert settings(entries["mapping-r2"]) == {"robot": "r2"}
    assert settings(entries["gateway"]) == {"robot": "fleet", "robots": ["r1", "r2", "r3"]}
    perception = settings(entries["perception"])
    assert perception["robots"] == ["r1", "r2", "r3"]
    assert {r: s["episode_index"] for r, s in perception["sim"]["robots"].items()} == {"r1": 0, "r2": 1, "r3": 2}


def test_override_settings_are_json_and_a_bad_one_is_refused() -> None:
    from ovamos.shared.config import ServiceConfigError, format_override, parse_overrides
    assert parse_overrides([format_override("robots", ["a", "b"]), "batch_wait_ms=2.5"]) == \
        {"robots": ["a", "b"], "batch_wait_ms": 2.5}
    with pytest.raises(ServiceConfigError, match="not JSON"):
        parse_overrides(["robots=[a"])
    with pytest.raises(ServiceConfigError, match="KEY=JSON"):
        parse_overrides(["robots"])


def test_a_profile_built_in_code_with_an_unknown_service_is_refused() -> None:
    """check_service_configs reports what load_profile would have (a Profile made without a file)."""
    from ovamos.profiles import Profile
    with pytest.raises(ProfileError, match=r"services\[0\] \(mapper\): unknown service 'mapper'"):
        check_service_configs(Profile.model_validate({"services": [{"service": "mapper"}]}))


def _without_changes(argv: tuple[str, ...]) -> tuple[str, ...]:
    out: list[str] = []
    skip = False
    for arg in argv:
        if skip:
            skip = False
        elif arg == "--set":
            skip = True
        else:
            out.append(arg)
    return tuple(out)


@pytest.mark.parametrize("robots", [1, 2])
def test_the_demo_runs_a_shipped_profile_with_its_episode_on_top(tmp_path: Path, robots: int) -> None:
    """Issue 49: ``ovamos demo`` and ``ovamos up`` are one description. The demo's processes are the
    ``all`` profile's (``fleet`` for a fleet), in its order, with its configs and Zenoh files, the
    demo changing settings on top (``--set``, each what the demo wrote in its config folder), so a
    profile edited for ``ovamos up`` is what the demo runs."""
    from ovamos.demo import (
        FLEET_ID,
        demo_entries,
        fleet_entries,
        fleet_episodes,
        fleet_robots,
        write_configs,
        write_fleet_configs,
    )
    from ovamos.shared.config import parse_overrides
    from ovamos.shared.procs import loopback
    if robots == 1:
        configs = write_configs(tmp_path, seed=0, episode=4, robot_id="sim", http_port=9999)
        entries = demo_entries(configs, robot_id="sim", zenoh_port=7999)
        profile = load_profile(resolve_profile("all"))
    else:
        ids = fleet_robots(robots)
        configs = write_fleet_configs(tmp_path, seed=0, episodes=fleet_episodes(0, 4, robots), http_port=9999)
        entries = fleet_entries(configs, robots=ids, zenoh_port=7999)
        profile = load_profile(resolve_profile("fleet")).model_copy(update={"robots": ids, "robot_id": FLEET_ID})
    up = profile.entries(endpoint=loopback(7999))
    assert [(e.name, _without_changes(e.argv)) for e in entries] == [(e.name, _without_changes(e.argv)) for e in up]
    for entry in entries[1:]:
        changed = parse_overrides([a for i, a in enumerate(entry.argv) if i and entry.argv[i - 1] == "--set"])
        written = configs.get(entry.name, configs.get(entry.argv[1]))  # per robot, else per service
        wrote = {} if written is None else json.loads(written.read_text())
        assert set(wrote) <= set(changed), entry.name
        assert all(changed[k] == v for k, v in wrote.items() if not isinstance(v, dict)), entry.name
