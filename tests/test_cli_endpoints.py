"""Which deployment the operator's commands talk to, and that they give up when none answers.

Issue 32: ``ovamos status`` with no router waited for ever; the demo's free ports were
unknown to ``status`` / ``submit`` / ``map``, which looked at the default ports (on a shared
host, maybe someone else's deployment); the keep-running banner suggested a target the
house does not contain.
"""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
from pathlib import Path

import foxglove
import pytest

from ovamos.cli import DEFAULT_ENDPOINTS, Deployment
from ovamos.demo import DEMO_EPISODE, DEMO_SEED, suggested_targets
from ovamos.record.channels import RawChannel
from ovamos.shared.bus.zconfig import RouterUnreachableError, build_config, open_session
from ovamos.shared.messages import Odometry
from ovamos.shared.procs import free_port, loopback, start_cli, stop
from ovamos.world.episodes import make_episode
from tests.polling import wait_for

pytestmark = pytest.mark.system  # processes, routers, browsers or real-time devices: make test-all

OPEN_TIMEOUT_S = 2.0


def ovamos(*args: str, cwd: Path | None = None, timeout: float = 60) -> subprocess.CompletedProcess:
    """``ovamos ARGS`` with this interpreter (in ``cwd``: where the default endpoints file is looked for)."""
    return subprocess.run([sys.executable, "-m", "ovamos.cli", *args], capture_output=True, text=True,
                          timeout=timeout, cwd=cwd)


def said(out: subprocess.CompletedProcess) -> str:
    """stderr as one line: rich wraps it at the console's width."""
    return " ".join(out.stderr.split())


# -- no router: give up, naming the endpoint ---------------------------------------------------
@pytest.mark.parametrize("command", [
    ("status", "--timeout", str(OPEN_TIMEOUT_S)),
    ("map", "--out", "{tmp}/map.png", "--timeout", str(OPEN_TIMEOUT_S)),
    ("record", "--out", "{tmp}/run.mcap", "--open-timeout", str(OPEN_TIMEOUT_S)),
    ("view", "--port", "0", "--open-timeout", str(OPEN_TIMEOUT_S)),
    ("replay", "{tmp}/one.mcap", "--open-timeout", str(OPEN_TIMEOUT_S)),
], ids=lambda c: c[0])
def test_a_tool_with_no_router_answering_exits_with_the_endpoint_named(command: tuple[str, ...],
                                                                       tmp_path: Path) -> None:
    _one_message_recording(tmp_path / "one.mcap")  # replay reads the file before it opens Zenoh
    endpoint = loopback(free_port())  # nothing listens there
    args = [a.format(tmp=tmp_path) for a in command]
    out = ovamos(*args, "--connect", endpoint, timeout=OPEN_TIMEOUT_S + 30)
    assert out.returncode == 2, out.stdout + out.stderr
    assert f"no Zenoh router answered at {endpoint} within {OPEN_TIMEOUT_S:g} s" in said(out)
    assert "ovamos up" in said(out)


def _one_message_recording(path: Path) -> None:
    context = foxglove.Context()
    writer = foxglove.open_mcap(path, context=context)
    RawChannel("odom", Odometry, "r1").open(context).log(Odometry(seq=0, stamp=0.0, x=0.0, y=0.0, yaw=0.0).to_bytes())
    writer.close()


def test_an_open_timeout_still_reconnects_after_a_router_restart() -> None:
    """The timeout is for opening only: a recorder or viewer, once up, survives its router's restart."""
    endpoint = loopback(free_port())
    with pytest.raises(RouterUnreachableError, match=re.escape(endpoint)):
        open_session(build_config("client", connect=[endpoint], open_timeout_s=0.5))
    router = open_session(build_config("router", listen=[endpoint]))
    client = open_session(build_config("client", connect=[endpoint], open_timeout_s=OPEN_TIMEOUT_S))
    got: list[bytes] = []
    client.declare_subscriber("test/restart", lambda s: got.append(s.payload.to_bytes()))
    router.close()
    router = open_session(build_config("router", listen=[endpoint]))
    sender = open_session(build_config("client", connect=[endpoint]))
    try:
        wait_for(lambda: sender.put("test/restart", b"after") or got, what="a sample through the new router")
    finally:
        for session in (sender, client, router):
            session.close()


# -- the endpoints file ------------------------------------------------------------------------
def _exited_pid() -> int:
    """The pid of a process that has exited (and been reaped): a demo killed outright."""
    proc = subprocess.Popen([sys.executable, "-c", ""])
    proc.wait()
    return proc.pid


def test_status_and_submit_read_the_demos_endpoints_file(cli, router_port: int, tmp_path: Path) -> None:
    """From the folder a demo ran in, status sees that deployment's services (not the default
    port's) and says which deployment it looks at; submit goes to its gateway."""
    cli("run", "monitor", "--robot-id", "r1", "--connect", loopback(router_port))
    gateway = f"http://127.0.0.1:{free_port()}"  # nothing listens: submit's error names it
    with Deployment(loopback(router_port), gateway, os.getpid()).published(tmp_path / DEFAULT_ENDPOINTS) as path:
        assert json.loads(path.read_text())["router"] == loopback(router_port)

        def monitor_listed() -> bool:
            out = ovamos("status", "--json", "--timeout", "1", cwd=tmp_path)
            assert out.returncode == 0, out.stderr
            return any(s["service"] == "monitor" and s["robot_id"] == "r1" for s in json.loads(out.stdout))

        wait_for(monitor_listed, what="status to list the deployment's monitor")
        out = ovamos("status", "--timeout", "1", cwd=tmp_path)
        assert (f"deployment: {DEFAULT_ENDPOINTS} (router {loopback(router_port)}, gateway {gateway})"
                in said(out))
        submit = ovamos("submit", "chair", cwd=tmp_path)
        assert submit.returncode == 2 and f"cannot reach the gateway at {gateway}" in said(submit)
        explicit = ovamos("status", "--endpoints", str(path), "--connect", loopback(router_port))
        assert explicit.returncode == 2 and "not both" in said(explicit)
    assert not path.exists()


def test_a_stale_endpoints_file_is_ignored_by_default_and_refused_when_named(tmp_path: Path) -> None:
    router = loopback(free_port())
    with Deployment(router, "http://127.0.0.1:1", _exited_pid()).published(tmp_path / DEFAULT_ENDPOINTS) as path:
        default = ovamos("status", "--timeout", "1", cwd=tmp_path, timeout=31)
        assert f"ignoring {DEFAULT_ENDPOINTS}" in said(default) and "is gone" in said(default)
        assert "deployment: the default router" in said(default)
        named = ovamos("status", "--endpoints", str(path), "--timeout", "1", timeout=31)
        assert named.returncode == 2 and "is stale" in said(named)


# -- what the house contains -------------------------------------------------------------------
def test_sim_scene_lists_the_episodes_house(tmp_path: Path) -> None:
    spec, scene, truth = make_episode(DEMO_SEED, DEMO_EPISODE)
    episode = f"{DEMO_SEED}-{DEMO_EPISODE}"
    out = ovamos("sim", "scene", "--episode", episode, "--json")
    assert out.returncode == 0, out.stderr
    listing = {entry["class"]: entry for entry in json.loads(out.stdout)["objects"]}
    assert sorted(listing) == scene.classes()
    stoppable = set(truth.stoppable_classes(spec.start.x, spec.start.y))
    rooms = {r.id: r.type for r in scene.rooms}
    for cls, entry in listing.items():
        assert entry["count"] == len(scene.instances(cls))
        assert {room.split(" ")[0] for room in entry["rooms"]} == {rooms[o.room] for o in scene.instances(cls)}
        assert entry["stoppable"] == (cls in stoppable)
    table = ovamos("sim", "scene", "--episode", episode, "--objects", "--out", str(tmp_path / "house.png"))
    assert table.returncode == 0, table.stderr
    assert all(cls in table.stdout for cls in scene.classes())
    assert (tmp_path / "house.png").read_bytes().startswith(b"\x89PNG")
    both = ovamos("sim", "scene", "--episode", episode, "--seed", "3", "--objects")
    assert both.returncode == 2 and "not both" in said(both)


def test_suggested_targets_are_in_the_house_and_not_searched_yet() -> None:
    spec, scene, truth = make_episode(DEMO_SEED, DEMO_EPISODE)
    suggested = suggested_targets(DEMO_SEED, DEMO_EPISODE, spec.targets)
    assert suggested and len(set(suggested)) == len(suggested)
    assert set(suggested) <= set(truth.stoppable_classes(spec.start.x, spec.start.y)) - set(spec.targets)


# -- the demo publishes its endpoints while it runs --------------------------------------------
def test_the_keep_running_demo_publishes_its_endpoints_and_suggests_targets_of_its_house(tmp_path: Path) -> None:
    """The demo (its search cut short: this is about the endpoints) writes OUT/endpoints.json once
    its services are up, its banner names the router, the gateway and a target the house holds,
    ``ovamos status`` there lists its services, and the file goes when the demo stops."""
    out_dir = tmp_path / "demo"
    log = (tmp_path / "demo.out").open("w")
    demo = start_cli(["demo", "--keep-running", "--no-record", "--timeout", "3", "--out", str(out_dir)],
                     stdout=log, stderr=subprocess.STDOUT)
    try:
        endpoints = out_dir / "endpoints.json"
        wait_for(endpoints.exists, timeout=150, what="the demo's endpoints.json")
        deployment = Deployment.load(endpoints)
        assert deployment.pid == demo.pid
        status = ovamos("status", "--json", "--endpoints", str(endpoints), "--robot-id", "sim")
        assert status.returncode == 0, status.stderr
        assert {s["service"] for s in json.loads(status.stdout)} >= {"mapping", "planner", "sim"}
        printed = tmp_path / "demo.out"
        wait_for(lambda: "Ctrl-C stops everything" in printed.read_text(), timeout=120,
                 what="the keep-running banner")
        banner = " ".join(printed.read_text().split())
        assert f"router {deployment.router}, gateway {deployment.gateway}" in banner
        first = re.search(r'"targets": \["(\w+)"\]', banner)
        assert first is not None
        _, scene, _ = make_episode(DEMO_SEED, DEMO_EPISODE)
        assert first.group(1) in scene.classes()
        demo.send_signal(signal.SIGTERM)
        assert demo.wait(timeout=60) in (0, 1)  # its own exit (1: the cut search), not the signal's
        assert not endpoints.exists()
    finally:
        stop(demo, timeout=60)
        log.close()
