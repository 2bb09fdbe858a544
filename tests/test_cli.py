"""The ``ovamos`` command line: clear errors, the demo and the benchmark end to end."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from ovamos import __version__
from ovamos.bench.transport import run_benchmark
from ovamos.demo import DEMO_EPISODE, DEMO_SEED

pytestmark = pytest.mark.system  # processes, routers, browsers or real-time devices: make test-all


def ovamos(*args: str, timeout: float = 60) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "ovamos.cli", *args], capture_output=True,
                          text=True, timeout=timeout)


def test_version() -> None:
    out = ovamos("--version")
    assert out.returncode == 0 and __version__ in out.stdout


def test_unknown_services_are_clear_errors() -> None:
    unknown = ovamos("run", "teleporter")
    assert unknown.returncode == 2 and "unknown service 'teleporter'" in unknown.stderr


def test_bad_service_config_is_a_clear_error(tmp_path: Path) -> None:
    cfg = tmp_path / "tp.toml"
    cfg.write_text("rate_hz = -1\nfps = 3\n")
    out = ovamos("run", "testpattern", "--config", str(cfg), "--connect", "tcp/127.0.0.1:1")
    assert out.returncode == 2
    assert "rate_hz" in out.stderr and "fps" in out.stderr


def test_multicast_config_is_refused(tmp_path: Path) -> None:
    cfg = tmp_path / "z.json5"
    cfg.write_text('{mode: "router", scouting: {multicast: {enabled: true}}}')
    out = ovamos("router", "--config", str(cfg))
    assert out.returncode == 2 and "multicast" in out.stderr


def test_bad_robot_id_is_a_clear_error() -> None:
    out = ovamos("run", "monitor", "--robot-id", "a/b", "--connect", "tcp/127.0.0.1:1")
    assert out.returncode == 2 and "robot id" in out.stderr


def _ports(node: dict, kind: str) -> set[tuple[str, str | None]]:
    return {(p["key"], p["message"]) for p in node.get(kind, [])}


def test_graph_json_is_the_declared_topology() -> None:
    """``ovamos graph --json`` prints shared/topology.py's table: keys in and out with message types."""
    from ovamos.shared.topology import TOPOLOGY, graph
    out = ovamos("graph", "--json")
    assert out.returncode == 0, out.stderr
    data = json.loads(out.stdout)
    assert data == graph() and set(data["services"]) == set(TOPOLOGY)
    planner, mapping = data["services"]["planner"], data["services"]["mapping"]
    assert ("ovamos/{robot_id}/task/current", "TaskSpec") in _ports(planner, "inputs")
    assert ("ovamos/{robot_id}/plan/command", "PlanCommand") in _ports(planner, "outputs")
    assert ("ovamos/{robot_id}/map/snapshot", "MapSnapshot") in _ports(planner, "queries")
    assert _ports(mapping, "answers") == {("ovamos/{robot_id}/map/snapshot", "MapSnapshot")}
    # every key a service subscribes to or queries is published or answered by another service
    # (the e-stop by the gateway, for the operator's E-STOP button)
    produced = set().union(*(_ports(n, "outputs") | _ports(n, "answers") for n in data["services"].values()))
    consumed = set().union(*(_ports(n, "inputs") | _ports(n, "queries") for name, n in data["services"].items()
                             if name != "monitor"))
    assert consumed - produced == set()
    assert ("ovamos/{robot_id}/driver/estop", "EStop") in _ports(data["services"]["gateway"], "outputs")


def test_graph_table_has_a_row_per_service() -> None:
    from ovamos.shared.topology import TOPOLOGY
    out = ovamos("graph")
    assert out.returncode == 0, out.stderr
    assert all(name in out.stdout for name in TOPOLOGY)
    for text in ("task/current", "TaskSpec", "plan/command", "PlanCommand", "answers", "ovamos/{robot_id}/"):
        assert text in out.stdout, text


@pytest.mark.demo  # the fast tier's one end-to-end run
def test_demo_finds_every_target_through_the_http_api_and_cleans_up(tmp_path: Path) -> None:
    """Router, mapping, perception, planner, simulated robot and gateway as processes; the task
    goes in over HTTP and comes back done with every target found."""
    out = ovamos("demo", "--out", str(tmp_path), timeout=400)
    assert out.returncode == 0, out.stdout + out.stderr
    assert out.stdout.rindex("done: found") > out.stdout.rindex("recorded the run")  # the last line
    report = json.loads((tmp_path / "demo_report.json").read_text())
    task = report["task"]
    assert task["status"] == "done" and sorted(f["label"] for f in task["found"]) == sorted(task["targets"])
    assert 0 < task["steps"] <= task["max_steps"] and task["distance_m"] > 0
    png = (tmp_path / "demo_map.png").read_bytes()
    assert png.startswith(b"\x89PNG")
    assert all(n == 0 for n in report["restarts"].values())
    assert not (tmp_path / "endpoints.json").exists()  # it named the deployment while it was up
    planner_log = (tmp_path / "logs" / "planner.log").read_text()  # a normal end is no lost link
    assert "robot unreachable" not in planner_log and "driver shut down" in planner_log
    # lock-step with the kinematic robot: the distributed run is the in-process episode, step by step
    from ovamos.bench.episode import EpisodeConfig, run_episode
    from ovamos.world.episodes import make_episode
    local = run_episode(*make_episode(DEMO_SEED, DEMO_EPISODE), EpisodeConfig())
    assert task["steps"] == local.steps
    assert task["distance_m"] == pytest.approx(local.path_m, abs=1e-6)
    assert [(f["label"], f["step"]) for f in task["found"]] == [(s.label, s.step) for s in local.stops]


@pytest.mark.serial  # frames 1 ms apart: a loaded machine loses them (the benchmark refuses over 10 %)
def test_transport_benchmark_reports_both_paths_with_and_without_shared_memory() -> None:
    result = run_benchmark(frames=5, runs=1, gap_ms=1.0)
    assert result["frame_bytes"] > 640 * 480 * 7
    for path in ("raw", "ovamos", "raw_shm", "ovamos_shm", "raw_zpool"):
        assert result[f"{path}_median_us"] > 0
    assert result["overhead_ratio"] == round(result["ovamos_median_us"] / result["raw_median_us"], 3)
    assert result["shm_overhead_ratio"] == round(result["ovamos_shm_median_us"] / result["raw_shm_median_us"], 3)
    assert set(result["lost"]) == {"raw", "ovamos", "raw+shm", "ovamos+shm", "raw+zpool"}  # counted, each


@pytest.mark.serial  # frames 1 ms apart: a loaded machine loses them (the benchmark refuses over 10 %)
def test_transport_stages_split_each_round_trip_across_the_processes() -> None:
    from ovamos.bench.transport_stages import STAGES, run_stages
    result = run_stages(frames=5, gap_ms=1.0)
    paths = {"raw", "ovamos", "raw+shm", "ovamos+shm"}
    assert set(result["median_us"]) == paths and set(result["lost"]) == paths
    for path in result["median_us"].values():
        assert set(path) == {*STAGES, "round trip"}
        # the echo's clock is the sender's (CLOCK_MONOTONIC): its stamps fall inside the round trip
        assert 0 < path["to echo"] < path["round trip"] and 0 <= path["to handler"] < path["round trip"]
    for ours, raw in (("ovamos", "raw"), ("ovamos+shm", "raw+shm")):
        # raw puts bytes encoded once, before the first round trip
        assert result["median_us"][ours]["encode"] > result["median_us"][raw]["encode"]


@pytest.mark.serial  # frames 1 ms apart: a loaded machine loses them (the benchmark refuses over 10 %)
def test_tls_transport_benchmark_compares_the_links() -> None:
    from ovamos.bench.transport_tls import run_tls_benchmark
    result = run_tls_benchmark(frames=5, runs=1, gap_ms=1.0)
    assert result["tcp_median_us"] > 0 and result["tls_median_us"] > 0 and result["tls_acl_median_us"] > 0
    assert result["tls_overhead_ratio"] == round(result["tls_median_us"] / result["tcp_median_us"], 3)


def test_sim_benchmark_reports_both_resolutions() -> None:
    from ovamos.bench.sim import run_benchmark as run_sim_benchmark
    result = run_sim_benchmark(frames=3, runs=1)
    assert result["fps_640x480"] > 0 and result["fps_320x240"] > 0
    assert result["objects"] > 0


def test_sim_commands_write_pictures(tmp_path: Path) -> None:
    scene = ovamos("sim", "scene", "--seed", "2", "--out", str(tmp_path / "map.png"),
                   "--save", str(tmp_path / "scene.json"))
    assert scene.returncode == 0, scene.stderr
    render = ovamos("sim", "render", "--scene", str(tmp_path / "scene.json"), "--width", "160",
                    "--height", "120", "--out", str(tmp_path / "frame.png"))
    assert render.returncode == 0, render.stderr
    assert "sees" in render.stdout
    import cv2
    assert cv2.imread(str(tmp_path / "map.png")).shape[2] == 3
    assert cv2.imread(str(tmp_path / "frame.png")).shape[:2] == (120, 480)
    blocked = ovamos("sim", "render", "--seed", "2", "--x", "-5", "--y", "-5", "--out",
                     str(tmp_path / "x.png"))
    assert blocked.returncode == 2 and "not free space" in blocked.stderr


def test_planner_benchmark_reports_latency_and_sims() -> None:
    from ovamos.bench.planner import run_benchmark as run_planner_benchmark
    result = run_planner_benchmark(runs=1, sims=50)
    assert set(result["decision_ms"]) == set(result["plus_decision_ms"]) == {"5", "10", "20"}
    assert result["sims_per_s"] > 0


def test_submit_through_a_gateway_process(cli, router_port: int, tmp_path: Path) -> None:
    from ovamos.shared.procs import free_port, loopback
    from tests.polling import port_open, wait_for
    port = free_port()
    cfg = tmp_path / "gateway.toml"
    cfg.write_text(f'port = {port}\nstate_dir = "{tmp_path / "state"}"\nrobots = ["sim"]\n')
    cli("run", "gateway", "--robot-id", "sim", "--config", str(cfg), "--connect", loopback(router_port))
    wait_for(lambda: port_open(port), what="the gateway listens")
    url = f"http://127.0.0.1:{port}"
    out = ovamos("submit", "chair", "fridge", "--gateway", url)
    assert out.returncode == 0 and "searching on sim" in out.stdout, out.stderr
    bad = ovamos("submit", "chair", "CHAIR", "--gateway", url)
    assert bad.returncode == 2 and "duplicate" in bad.stderr.lower()
    # a deployment's endpoints file (ovamos demo writes one) stands for --gateway, and is named
    from ovamos.cli import Deployment
    with Deployment(loopback(router_port), url, os.getpid()).published(tmp_path / "endpoints.json") as endpoints:
        via_file = ovamos("submit", "sofa", "--endpoints", str(endpoints))
    assert via_file.returncode == 0 and "queued on sim" in via_file.stdout, via_file.stderr  # after chair, fridge
    assert f"deployment: {endpoints} (router {loopback(router_port)}, gateway {url})" in " ".join(
        via_file.stderr.split())
