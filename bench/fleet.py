"""Fleet benchmark: how one laptop's perception and planners scale with the number of robots.

Per robot count (``--robots 1,2,4``):

* **perception**, in process, the backend as the service calls it
  (:meth:`PerceptionBackend.process`): each robot's 640x480 frames (rendered in
  its own home, 3 targets each) one call per frame (``batch 1``) and one call per
  round of one frame per robot (``batched``), as the service's round-robin batches
  are. ``sim``: the simulator's perception; ``hf``: the real pipeline with
  full-size random-weight models (BLIP-base ITC scores; with ``--hf-detect`` also
  GroundingDINO Swin-T boxes and SAM ViT-B masks, ~80 s a frame on 2 CPU cores).
* **the system**: the demo's fleet processes (router; per robot mapping,
  planner and simulated robot in lock-step; one perception service batching
  across robots; one gateway) over Zenoh, each robot searching its home for 3
  objects that are not there (so none stops early), measured for ``window_s``
  after ``warmup_s``: planner decisions per second over all robots, and per robot
  the step latency, from a frame's capture (its stamp) to the planner's next
  command (the command's stamp), both on this host's clock.
"""

from __future__ import annotations

import statistics
import tempfile
import threading
import time
from collections import defaultdict
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from rich.console import Console
from rich.table import Table

from ovamos.bench.sim import camera_poses
from ovamos.demo import FLEET_EPISODES, FLEET_ID, fleet_entries, fleet_robots, wait_for_services, write_fleet_configs
from ovamos.services.gateway.client import GatewayClient
from ovamos.services.perception.backend import Job, PerceptionBackend
from ovamos.services.perception.sim_backend import SimBackend
from ovamos.shared import keys
from ovamos.shared.bus import Bus
from ovamos.shared.bus.zconfig import build_config
from ovamos.shared.messages import PlanCommand, RgbdFrame
from ovamos.shared.procs import free_port, loopback
from ovamos.supervisor import Supervisor
from ovamos.world.episodes import make_episode
from ovamos.world.evaluator import GroundTruth
from ovamos.world.prior import ObjectPrior

SEED = 0
WIDTH, HEIGHT = 640, 480
TARGETS = 3


def _homes(count: int) -> dict[str, Any]:
    """Robot id -> (scene, its absent targets) for the first ``count`` fleet homes."""
    prior = ObjectPrior.load()
    homes = {}
    for robot, episode in zip(fleet_robots(count), FLEET_EPISODES):
        _, scene, _ = make_episode(SEED, episode, prior)
        absent = [c for c in prior.classes if c not in scene.classes()]
        homes[robot] = (scene, absent[:TARGETS])
    return homes


def _frames(homes: dict[str, Any], per_robot: int) -> dict[str, list[RgbdFrame]]:
    from ovamos.world.render import SceneRenderer
    frames = {}
    for robot, (scene, _) in homes.items():
        with SceneRenderer(scene, WIDTH, HEIGHT) as renderer:
            frames[robot] = [renderer.render(x, y, yaw, seq=i)
                             for i, (x, y, yaw) in enumerate(camera_poses(GroundTruth(scene), per_robot))]
    return frames


def _throughput(backend: PerceptionBackend, jobs: list[list[Job]], detect: bool,
                repeats: int = 1) -> dict[str, float]:
    """Frames per second over ``jobs`` (rounds of one job per robot), one call per job (``batch1``)
    and one per round (``batched``): the median of ``repeats`` passes, the two ways alternating so
    that drift on the machine hits both alike."""
    runs: dict[str, list[float]] = {"batch1": [], "batched": []}
    for _ in range(repeats):
        for mode, fps in runs.items():
            start = time.perf_counter()
            for round_jobs in jobs:
                for batch in ([round_jobs] if mode == "batched" else [[job] for job in round_jobs]):
                    backend.process(batch, detect)
            fps.append(sum(map(len, jobs)) / (time.perf_counter() - start))
    return {mode: statistics.median(fps) for mode, fps in runs.items()}


def _rounds(frames: dict[str, list[RgbdFrame]], homes: dict[str, Any], rounds: int) -> list[list[Job]]:
    return [[Job(robot, frames[robot][i], tuple(homes[robot][1])) for robot in frames] for i in range(rounds)]


def bench_perception(counts: Sequence[int], sim_rounds: int, hf: bool, hf_detect: bool,
                     progress: Console | None) -> dict[str, Any]:
    """Aggregate frames/s per robot count, batch 1 vs batched, for the sim and (if ``hf``) hf backends."""
    homes = _homes(max(counts))
    frames = _frames(homes, max(sim_rounds, 1))
    sim = SimBackend(homes[next(iter(homes))][0], robots={r: scene for r, (scene, _) in homes.items()})
    out: dict[str, Any] = {"sim": {}, "sim_rounds": sim_rounds}
    for n in counts:
        subset = {r: frames[r] for r in list(frames)[:n]}
        out["sim"][n] = {mode: round(fps, 1)
                         for mode, fps in _throughput(sim, _rounds(subset, homes, sim_rounds), True, 3).items()}
        if progress:
            progress.print(f"sim perception, {n} robots: {out['sim'][n]}")
    if hf:
        out["hf_detect"] = hf_detect
        out["hf"] = _bench_hf(counts, homes, frames, hf_detect, progress)
    return out


def _bench_hf(counts: Sequence[int], homes: dict[str, Any], frames: dict[str, list[RgbdFrame]], detect: bool,
              progress: Console | None) -> dict[int, dict[str, float]]:
    import torch

    from ovamos.bench.random_models import loaded
    from ovamos.services.perception.config import HfBackendConfig
    from ovamos.services.perception.hf.backend import HfBackend
    from ovamos.services.perception.hf.loading import Placement
    placement = Placement.resolve("cpu", False)
    backend = HfBackend(*loaded("full", placement), placement, HfBackendConfig())
    backend.process(_rounds(frames, homes, 1)[0][:1], detect)  # warm-up: allocations, kernels, caches
    out: dict[int, dict[str, float]] = {}
    for n in counts:
        jobs = _rounds({r: frames[r] for r in list(frames)[:n]}, homes, 1)
        out[n] = {mode: round(fps, 3) for mode, fps in _throughput(backend, jobs, detect).items()}
        if progress:
            progress.print(f"hf perception ({torch.get_num_threads()} CPU threads), {n} robots: {out[n]}")
    return out


class StepClock:
    """Decisions and step latencies of every robot, from the frames and commands on the bus."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._captured: dict[tuple[str, int], float] = {}
        self._commands: set[tuple[str, int]] = set()
        self.open = False  # counting only inside the window
        self.decisions: defaultdict[str, int] = defaultdict(int)
        self.latencies: defaultdict[str, list[float]] = defaultdict(list)

    def on_frame(self, robot: str, frame: RgbdFrame) -> None:
        with self._lock:  # the first frame after a command: re-published ones keep its stamp
            self._captured.setdefault((robot, frame.after_action), frame.stamp)

    def on_command(self, robot: str, command: PlanCommand) -> None:
        with self._lock:
            if (robot, command.action_id) in self._commands:
                return  # a re-sent copy
            self._commands.add((robot, command.action_id))
            captured = self._captured.get((robot, command.action_id - 1))
            if self.open and captured is not None:
                self.decisions[robot] += 1
                self.latencies[robot].append(command.stamp - captured)


def _percentile(values: list[float], q: float) -> float:
    return statistics.quantiles(values, n=100, method="inclusive")[q - 1] if len(values) > 1 else values[0]


def bench_system(n: int, warmup_s: float, window_s: float, progress: Console | None) -> dict[str, Any]:
    """The fleet of ``n`` simulated robots over Zenoh: decisions/s and step latencies."""
    homes = _homes(n)
    episodes = dict(zip(homes, FLEET_EPISODES))
    http_port, zenoh_port = free_port(), free_port()
    clock = StepClock()
    with tempfile.TemporaryDirectory(prefix="ovamos-bench-fleet-") as tmp:
        folder = Path(tmp)
        configs = write_fleet_configs(folder / "config", seed=SEED, episodes=episodes, http_port=http_port)
        entries = fleet_entries(configs, robots=list(homes), zenoh_port=zenoh_port)
        with Supervisor(entries, log_dir=folder / "logs") as supervisor, \
                GatewayClient(f"http://127.0.0.1:{http_port}") as client, \
                Bus.open(build_config(connect=[loopback(zenoh_port)]), FLEET_ID, "bench-fleet") as bus:
            deadline = time.monotonic() + 120
            wait_for_services(client, list(homes), deadline)
            bus.subscribe_keyed(keys.rgbd(keys.ANY), RgbdFrame,
                                lambda key, f: clock.on_frame(keys.robot_of(key), f), keep=1)
            bus.subscribe_keyed(keys.plan_command(keys.ANY), PlanCommand,
                                lambda key, c: clock.on_command(keys.robot_of(key), c))
            for robot, (_, targets) in homes.items():
                client.submit(targets, robot_id=robot, max_steps=2000)
            time.sleep(warmup_s)
            clock.open = True
            time.sleep(window_s)
            clock.open = False
            restarts = sum(s.restarts for s in supervisor.status())
    per_robot = {robot: {"decisions": clock.decisions[robot],
                         "step_p50_ms": round(1e3 * statistics.median(lat), 1) if lat else None,
                         "step_p95_ms": round(1e3 * _percentile(lat, 95), 1) if lat else None}
                 for robot in homes for lat in [clock.latencies[robot]]}
    result = {"decisions_per_s": round(sum(clock.decisions.values()) / window_s, 2), "restarts": restarts,
              "robots": per_robot}
    if progress:
        progress.print(f"system, {n} robots: {result['decisions_per_s']} decisions/s, "
                       + ", ".join(f"{r} p50 {v['step_p50_ms']} ms p95 {v['step_p95_ms']} ms"
                                   for r, v in per_robot.items()))
    return result


def run_benchmark(robots: Sequence[int] = (1, 2, 4), window_s: float = 15.0, warmup_s: float = 5.0,
                  sim_rounds: int = 10, hf: bool = True, hf_detect: bool = False,
                  progress: Console | None = None) -> dict[str, Any]:
    if not robots or min(robots) < 1 or max(robots) > len(FLEET_EPISODES):
        raise ValueError(f"robot counts must be within 1..{len(FLEET_EPISODES)} (one home each)")
    if window_s <= 0 or warmup_s < 0 or sim_rounds < 1:
        raise ValueError("window_s must be > 0, warmup_s >= 0 and sim_rounds >= 1")
    counts = sorted(set(robots))
    result: dict[str, Any] = {"robots": counts, "window_s": window_s, "warmup_s": warmup_s,
                              "perception": bench_perception(counts, sim_rounds, hf, hf_detect, progress)}
    result["system"] = {n: bench_system(n, warmup_s, window_s, progress) for n in counts}
    return result


def print_table(console: Console, result: dict[str, Any]) -> None:
    perception, system = result["perception"], result["system"]
    hf_what = "scores + boxes + masks" if perception.get("hf_detect") else "scores (detect = false)"
    table = Table("robots", "sim frames/s: batch 1 / batched", f"hf CPU frames/s, {hf_what}: batch 1 / batched",
                  "decisions/s (all robots)", "step latency p50 / p95 (ms), per robot",
                  title=f"Fleet on one host; the system measured {result['window_s']:g} s after "
                        f"{result['warmup_s']:g} s")
    for n in result["robots"]:
        sim = perception["sim"][n]
        hf = perception.get("hf", {}).get(n)
        steps = system[n]["robots"]
        table.add_row(str(n), f"{sim['batch1']:.1f} / {sim['batched']:.1f}",
                      f"{hf['batch1']:.3f} / {hf['batched']:.3f}" if hf else "-",
                      f"{system[n]['decisions_per_s']:.2f}",
                      ", ".join(f"{v['step_p50_ms']} / {v['step_p95_ms']}" for v in steps.values()))
    console.print(table)
