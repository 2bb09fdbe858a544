"""Soak benchmark: one stack left up for task after task, as a lab leaves it for a day.

The demo's processes (router, mapping, perception, planner, the simulated robot in lock-step,
the gateway) over real Zenoh and HTTP, in the demo's house, take a sequence of tasks one after
the other on the same map: the demo's own targets, other objects the house holds (some asked
for again), one it does not hold, and a task cancelled on the way. Per task: the result, the
steps and seconds it took, why it failed (the planner's words), and each service's resident
memory after it. Each task that can succeed is also run from a fresh start (in process, from the
episode's start pose: the lock-step services follow the same trajectory), so the table shows
what the carried map costs or saves.
"""

from __future__ import annotations

import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from rich.console import Console
from rich.table import Table

from ovamos.bench.episode import EpisodeConfig, run_episode
from ovamos.demo import DEMO_EPISODE, DEMO_SEED, SERVICES, demo_entries, wait_for_services, write_configs
from ovamos.services.gateway.client import GatewayClient
from ovamos.services.gateway.models import TaskView
from ovamos.shared.procs import free_port
from ovamos.supervisor import Supervisor
from ovamos.world.episodes import make_episode
from ovamos.world.prior import ObjectPrior

ROBOT = "sim"
ABSENT_STEPS = 60
"""Step limit of the task whose target the house does not hold: it can only fail, and a short one
keeps the soak short (its reason is what is checked)."""
CANCEL_AFTER_STEPS = 10
STARTUP_TIMEOUT_S = 120.0
TASK_TIMEOUT_S = 900.0


@dataclass(frozen=True)
class SoakTask:
    """One task of the sequence; ``cancel_after`` steps: cancelled then (None: run to its end)."""

    targets: tuple[str, ...]
    max_steps: int | None = None
    cancel_after: int | None = None

    @property
    def can_succeed(self) -> bool:
        return self.max_steps is None and self.cancel_after is None


def soak_tasks(count: int, seed: int = DEMO_SEED, episode: int = DEMO_EPISODE) -> list[SoakTask]:
    """``count`` tasks in the house of episode (``seed``, ``episode``): the episode's targets, then
    a cycle of pairs and singles of classes a STOP can succeed for (each pair asked for twice,
    the second time on a map that holds it), a class the house does not hold, and a cancelled
    task. Drawn from ``seed`` and ``episode``: the same sequence every time."""
    spec, scene, truth = make_episode(seed, episode)
    prior = ObjectPrior.load()
    # furniture, the objects a lab asks for by name ("the sofa"): a small object is often missed
    # from a fresh start as well, and its task would measure the detector, not the carried map
    present = sorted(c for c in truth.stoppable_classes(spec.start.x, spec.start.y) if not prior[c].small)
    absent = sorted(c for c in set(prior.classes) - set(scene.classes()) if not prior[c].small)
    if len(present) < 3 or not absent:
        raise ValueError(f"episode {seed}-{episode}: its house has too few classes for a soak")
    rng = np.random.default_rng([seed, episode, 32])
    tasks = [SoakTask(spec.targets)]
    while len(tasks) < count:
        pair = tuple(str(c) for c in rng.choice(present, 2, replace=False))
        single = (str(rng.choice(present)),)
        tasks += [SoakTask(pair), SoakTask((str(rng.choice(absent)),), max_steps=ABSENT_STEPS),
                  SoakTask(pair), SoakTask(single, cancel_after=CANCEL_AFTER_STEPS), SoakTask(single)]
    return tasks[:count]


def fresh_steps(tasks: list[SoakTask], seed: int = DEMO_SEED, episode: int = DEMO_EPISODE
                ) -> dict[tuple[str, ...], tuple[bool, int]]:
    """Per target set of the tasks that can succeed: (success, steps) from a fresh start."""
    spec, scene, truth = make_episode(seed, episode)
    out: dict[tuple[str, ...], tuple[bool, int]] = {}
    for task in tasks:
        if task.can_succeed and task.targets not in out:
            result = run_episode(spec.model_copy(update={"targets": task.targets}), scene, truth, EpisodeConfig())
            out[task.targets] = (result.success, result.steps)
    return out


def rss_mb(pid: int | None) -> float | None:
    """Resident memory of a process (MB), from /proc (None: gone, or no /proc)."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    except (OSError, ValueError):
        return None
    return None


def _run_one(client: GatewayClient, task: SoakTask) -> TaskView:
    """Submit ``task``, cancel it after its steps if it says so, wait for its end."""
    task_id = client.submit(list(task.targets), robot_id=ROBOT, max_steps=task.max_steps).id
    deadline = time.monotonic() + TASK_TIMEOUT_S
    view = client.get(task_id)
    while not view.final and time.monotonic() < deadline:
        if task.cancel_after is not None and view.steps >= task.cancel_after:
            return client.cancel(task_id)
        time.sleep(0.2)
        view = client.get(task_id)
    return view if view.final else client.cancel(task_id)


def run_soak(tasks: list[SoakTask], *, seed: int = DEMO_SEED, episode: int = DEMO_EPISODE,
             out_dir: Path | None = None, on_task: Callable[[dict[str, Any]], None] | None = None
             ) -> dict[str, Any]:
    """Run ``tasks`` one after the other on one stack; one row per task (see the module)."""
    rows: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory(prefix="ovamos-soak-") as tmp:
        folder = out_dir or Path(tmp)
        http_port, zenoh_port = free_port(), free_port()
        configs = write_configs(folder / "config", seed=seed, episode=episode, robot_id=ROBOT, http_port=http_port)
        entries = demo_entries(configs, robot_id=ROBOT, zenoh_port=zenoh_port)
        with Supervisor(entries, log_dir=folder / "logs") as supervisor, \
                GatewayClient(f"http://127.0.0.1:{http_port}") as client:
            deadline = time.monotonic() + STARTUP_TIMEOUT_S
            wait_for_services(client, [ROBOT], deadline)
            for i, task in enumerate(tasks):
                started = time.monotonic()
                view = _run_one(client, task)
                pids = {s.name: s.pid for s in supervisor.status()}
                row = {"task": i + 1, "targets": list(task.targets), "status": view.status.value,
                       "steps": view.steps, "seconds": round(time.monotonic() - started, 1),
                       "distance_m": round(view.distance_m, 2), "message": view.message,
                       "misses": [m.model_dump(mode="json") for m in view.misses],
                       "can_succeed": task.can_succeed,
                       "rss_mb": {name: round(mb, 1) for name in SERVICES
                                  if (mb := rss_mb(pids.get(name))) is not None}}
                rows.append(row)
                if on_task is not None:
                    on_task(row)
            restarts = {s.name: s.restarts for s in supervisor.status()}
    return {"episode": f"{seed}-{episode}", "tasks": rows, "restarts": restarts}


def run_benchmark(count: int, *, fresh: bool = True, progress: Console | None = None) -> dict[str, Any]:
    """The soak of ``count`` tasks, with each task's fresh-start steps (``fresh``)."""
    tasks = soak_tasks(count)
    reference = fresh_steps(tasks) if fresh else {}

    def report(row: dict[str, Any]) -> None:
        if progress is not None:
            progress.print(f"task {row['task']}/{count} {'+'.join(row['targets'])}: {row['status']} in "
                           f"{row['steps']} steps, {row['seconds']} s {row['message']}")

    result = run_soak(tasks, on_task=report)
    for row in result["tasks"]:
        ok, steps = reference.get(tuple(row["targets"]), (None, None)) if row["can_succeed"] else (None, None)
        row["fresh_success"], row["fresh_steps"] = ok, steps
    first, last = result["tasks"][0]["rss_mb"], result["tasks"][-1]["rss_mb"]
    result["rss_growth"] = {name: round(last[name] / first[name], 3) for name in first if name in last}
    return result


def print_table(console: Console, result: dict[str, Any]) -> None:
    table = Table("task", "targets", "result", "steps", "fresh", "s", "ms/step", "why", *SERVICES,
                  title=f"soak, episode {result['episode']}: RSS (MB) after each task")
    for row in result["tasks"]:
        fresh = "-" if row.get("fresh_steps") is None else str(row["fresh_steps"])
        table.add_row(str(row["task"]), "+".join(row["targets"]), row["status"], str(row["steps"]), fresh,
                      f"{row['seconds']:.0f}", f"{1000 * row['seconds'] / max(row['steps'], 1):.0f}",
                      row["message"] if row["status"] != "done" else "",
                      *(f"{row['rss_mb'].get(s, float('nan')):.0f}" for s in SERVICES))
    console.print(table)
    growth = ", ".join(f"{name} x{g:.2f}" for name, g in result["rss_growth"].items())
    console.print(f"RSS after the last task / after the first: {growth}; restarts: {result['restarts']}")
