"""Search benchmark: the paper's Tables I and II (SR and MSPL per policy) on simulated homes.

An episode costs seconds to tens of seconds of CPU (render, perception, map and a decision per
step) and episodes are independent, so the work units are (policy, episode index) pairs spread
over worker processes. Workers are started with "spawn": a fresh interpreter per worker inherits
no MuJoCo/EGL context or thread state from the parent. Results stream back as they finish and
drive the progress bar.

An episode's outcome depends only on (seed, index, policy, step limit): the runner is
deterministic. The per-episode JSONL is therefore sorted by (policy, episode) and written without
the wall-clock field, so two runs with one seed give byte-identical files whatever the worker
count; timings go to their own file.

``replay`` draws one episode from above (trajectory, STOPs, the targets' instances and a legend)
so that a person can see why it failed.
"""

from __future__ import annotations

import functools
import json
import math
import multiprocessing as mp
import os
import statistics
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from pydantic import ValidationError
from rich.console import Console
from rich.progress import (BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn,
                           TimeRemainingColumn)
from rich.table import Table

from bench.episode import EpisodeResult, episode_config, run_episode
from bench.funnel import Miss
from services.mapping.render import write_png
from services.sim.draw import MARGIN_M, draw_scene
from services.sim.episodes import make_episode
from services.sim.evaluator import GroundTruth
from services.sim.prior import ObjectPrior
from services.sim.world import Scene

#: Every policy, in the order the paper's tables list them (baselines, ablations, the method).
POLICY_ORDER = ("random", "vlfm", "finder", "ovamos-greedy", "ovamos-nodecay", "ovamos")
TABLE_I = ("random", "vlfm", "finder", "ovamos")
TABLE_II = ("ovamos-greedy", "ovamos-nodecay", "ovamos")
LABELS = {"random": "Random", "vlfm": "VLFM", "finder": "Finder", "ovamos": "OVAMOS",
          "ovamos-greedy": "w/o POMDP", "ovamos-nodecay": "w/o value decay"}
#: The paper's numbers: (SR in %, MSPL).
PAPER = {"random": (0.0, 0.0), "vlfm": (12.5, 0.075), "finder": (28.3, 0.198),
         "ovamos": (55.0, 0.497), "ovamos-greedy": (27.5, 0.154), "ovamos-nodecay": (45.0, 0.410)}
TIMING_FIELDS = {"seconds"}  # wall clock: kept out of the comparable JSONL

EPISODES_FILE, TIMINGS_FILE, SUMMARY_FILE, CHART_FILE = (
    "episodes.jsonl", "timings.jsonl", "summary.json", "chart.png")


class SearchError(ValueError):
    """Bad arguments or input files: the CLI prints the message and exits 2."""


class EpisodeFailed(RuntimeError):
    """An episode raised; the message names the work unit (it must survive pickling)."""


# -- arguments -------------------------------------------------------------------------------------
def parse_policies(text: str | Sequence[str]) -> tuple[str, ...]:
    """Policy names from "a,b" or a sequence, de-duplicated, in the paper's order."""
    names = [p.strip() for p in (text.split(",") if isinstance(text, str) else text) if p.strip()]
    unknown = [p for p in names if p not in POLICY_ORDER]
    if unknown or not names:
        raise SearchError(f"unknown or no policies {unknown or names} (known: {', '.join(POLICY_ORDER)})")
    return tuple(p for p in POLICY_ORDER if p in names)


def parse_episode_id(episode_id: str) -> tuple[int, int]:
    """``"SEED-INDEX"`` (the id :func:`make_episode` gives) -> (seed, index)."""
    seed, sep, index = episode_id.strip().rpartition("-")
    try:
        if not sep:
            raise ValueError
        parsed = int(seed), int(index)
    except ValueError:
        raise SearchError(f"episode id {episode_id!r} is not SEED-INDEX (e.g. 0-3)") from None
    if parsed[1] < 0:
        raise SearchError(f"episode id {episode_id!r}: the index must be >= 0")
    return parsed


def _episode_index(result: EpisodeResult) -> int:
    return parse_episode_id(result.episode_id)[1]


# -- one work unit (in a worker process, or in this one) ----------------------------------------------
@dataclass(frozen=True)
class Job:
    """One work unit and what its outcome depends on besides the code."""

    policy: str
    seed: int
    index: int
    max_steps: int | None = None

    @property
    def name(self) -> str:
        return f"{self.policy} {self.seed}-{self.index}"


@functools.cache
def _prior() -> ObjectPrior:
    """The object prior, read once per process (every episode and the perception model use it)."""
    return ObjectPrior.load()


@functools.lru_cache(maxsize=4)
def _episode(seed: int, index: int) -> tuple[Any, Scene, GroundTruth]:
    """An episode's spec, scene and ground truth: cached because the policies of one episode
    share them, and generating a scene and its distance fields costs about a second."""
    return make_episode(seed, index, _prior())


def init_worker() -> None:
    """Per worker process: headless rendering (EGL) unless the user chose a GL backend, and the
    prior loaded once before the first episode."""
    os.environ.setdefault("MUJOCO_GL", "egl")
    _prior()


def run_job(job: Job) -> EpisodeResult:
    """The episode of ``job`` with its policy (the step limit overridden for quick runs)."""
    spec, scene, truth = _episode(job.seed, job.index)
    if job.max_steps is not None:
        spec = spec.model_copy(update={"max_steps": job.max_steps})
    return run_episode(spec, scene, truth, episode_config(job.policy), _prior())


def _work(job: Job) -> dict[str, Any]:
    """Worker entry: a plain dict crosses the process boundary; errors name the unit."""
    try:
        return run_job(job).model_dump(mode="json")
    except Exception as exc:
        raise EpisodeFailed(f"episode {job.name}: {type(exc).__name__}: {exc}") from None


def jobs_for(episodes: int, seed: int, policies: Sequence[str], max_steps: int | None = None
             ) -> list[Job]:
    """Episode-major order: a worker tends to get the policies of one episode in a row (its scene
    is cached), and a run cut short has covered every policy about equally."""
    return [Job(p, seed, i, max_steps) for i in range(episodes) for p in policies]


def iter_results(jobs: Sequence[Job], workers: int) -> Iterator[EpisodeResult]:
    """Results as they finish: in this process for one worker, else from a spawn pool.

    A process pool executor rather than ``multiprocessing.Pool``: a worker that dies (a crash in
    the GL driver, the OOM killer) fails the run with BrokenProcessPool instead of hanging it, and
    on any error the episodes not yet started are cancelled."""
    if workers <= 1 or len(jobs) <= 1:
        init_worker()
        for job in jobs:
            yield EpisodeResult.model_validate(_work(job))
        return
    pool = ProcessPoolExecutor(min(workers, len(jobs)), mp_context=mp.get_context("spawn"),
                               initializer=init_worker)
    try:
        for future in as_completed([pool.submit(_work, job) for job in jobs]):
            yield EpisodeResult.model_validate(future.result())
    finally:
        pool.shutdown(wait=True, cancel_futures=True)


# -- a run ----------------------------------------------------------------------------------------
@dataclass
class SearchRun:
    seed: int
    episodes: int
    policies: tuple[str, ...]
    workers: int
    max_steps: int | None
    results: list[EpisodeResult]  # sorted by (policy, episode index)
    seconds: float


def sort_results(results: Iterable[EpisodeResult]) -> list[EpisodeResult]:
    return sorted(results, key=lambda r: (r.policy, _episode_index(r)))


def _mark(result: EpisodeResult) -> str:
    found = "found all" if result.success else f"found {len(set(result.found))}/{len(result.targets)}"
    return f"{result.policy} {result.episode_id}: {found}"


@contextmanager
def _progress(console: Console | None, total: int) -> Iterator[Callable[[EpisodeResult], None]]:
    """A bar (episodes done / total, elapsed, ETA) on a terminal; on anything else (a log file,
    CI) a line per episode, because a bar is only drawn there when the run ends."""
    if console is None:
        yield lambda result: None
        return
    if not console.is_terminal:
        started, done = time.perf_counter(), 0

        def line(result: EpisodeResult) -> None:
            nonlocal done
            done += 1
            elapsed = time.perf_counter() - started
            eta = elapsed / done * (total - done)
            console.print(f"[{done}/{total} {elapsed / 60:.1f} min, ETA {eta / 60:.1f} min] {_mark(result)}",
                          highlight=False, soft_wrap=True)
        yield line
        return
    columns = (TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(),
               TextColumn("episodes"), TimeElapsedColumn(), TextColumn("ETA"), TimeRemainingColumn())
    with Progress(*columns, console=console) as bar:
        task = bar.add_task("search", total=total)
        yield lambda result: bar.update(task, advance=1, description=_mark(result))


def run_search(episodes: int, seed: int = 0, policies: Sequence[str] = POLICY_ORDER, workers: int = 2,
               max_steps: int | None = None, progress: Console | None = None) -> SearchRun:
    """Run every (policy, episode) pair; ``max_steps`` overrides the paper's 500 (quick runs and
    tests only: the tables need the paper's limit)."""
    if episodes < 1 or workers < 1 or (max_steps is not None and max_steps < 1):
        raise SearchError(f"need episodes >= 1, workers >= 1 and max steps >= 1 "
                          f"(got {episodes}, {workers}, {max_steps})")
    policies = parse_policies(policies)
    jobs = jobs_for(episodes, seed, policies, max_steps)
    started = time.perf_counter()
    results = []
    with _progress(progress, len(jobs)) as advance:
        for result in iter_results(jobs, workers):
            results.append(result)
            advance(result)
    return SearchRun(seed, episodes, policies, workers, max_steps, sort_results(results),
                     time.perf_counter() - started)


# -- scores ---------------------------------------------------------------------------------------
def policy_scores(results: Sequence[EpisodeResult]) -> dict[str, dict[str, float | int]]:
    """Per policy (paper order): SR in %, MSPL, episodes, and the % of all targets found (a
    finer signal than SR when few episodes succeed)."""
    scores: dict[str, dict[str, float | int]] = {}
    for policy in sorted({r.policy for r in results}, key=_policy_rank):
        mine = [r for r in results if r.policy == policy]
        found = sum(len(set(r.found) & set(r.targets)) for r in mine)
        scores[policy] = {"sr": round(100 * statistics.fmean(r.success for r in mine), 1),
                          "mspl": round(statistics.fmean(r.spl for r in mine), 3),
                          "episodes": len(mine),
                          "targets_found": round(100 * found / sum(len(r.targets) for r in mine), 1),
                          "wrong_stops": sum(not stop.success for r in mine for stop in r.stops)}
    return scores


def miss_reasons(results: Sequence[EpisodeResult]) -> dict[str, dict[str, int]]:
    """Per policy: how many targets were missed at each stage (:class:`Miss`), and how many were
    searched for. Results read from files written before the funnel was recorded count nothing."""
    out: dict[str, dict[str, int]] = {}
    for r in sorted(results, key=lambda r: _policy_rank(r.policy)):
        counts = out.setdefault(r.policy, {"targets": 0, **{m.value: 0 for m in Miss}})
        for funnel in r.funnel:
            counts["targets"] += 1
            if (miss := funnel.miss) is not None:
                counts[miss.value] += 1
    return out


def paired_differences(results: Sequence[EpisodeResult], reference: str = "ovamos",
                       resamples: int = 2000, seed: int = 0) -> dict[str, dict[str, Any]]:
    """Each policy against ``reference`` on the episodes both ran: the mean difference in SR (%)
    and MSPL with a 95 % bootstrap interval over episodes.

    Why: with 120 episodes one episode is 0.8 points of SR, and policies share episodes, so an
    ordering is only worth reporting when the paired interval excludes zero. The resampling is
    seeded: the same results give the same intervals."""
    by_policy: dict[str, dict[str, EpisodeResult]] = {}
    for r in results:
        by_policy.setdefault(r.policy, {})[r.episode_id] = r
    ref = by_policy.get(reference, {})
    rng = np.random.default_rng(seed)
    out: dict[str, dict[str, Any]] = {}
    for policy in sorted(by_policy, key=_policy_rank):
        shared = sorted(set(ref) & set(by_policy[policy]))
        if policy == reference or not shared:
            continue
        diff = np.array([[ref[e].success - by_policy[policy][e].success,
                          ref[e].spl - by_policy[policy][e].spl] for e in shared], dtype=float)
        means = diff[rng.integers(0, len(shared), (resamples, len(shared)))].mean(axis=1)
        lo, hi = np.percentile(means, [2.5, 97.5], axis=0)
        mean = diff.mean(axis=0)
        out[policy] = {"episodes": len(shared),
                       "sr_diff": round(100 * mean[0], 1), "sr_ci": [round(100 * lo[0], 1), round(100 * hi[0], 1)],
                       "mspl_diff": round(mean[1], 3), "mspl_ci": [round(lo[1], 3), round(hi[1], 3)]}
    return out


def _policy_rank(policy: str) -> int:
    return POLICY_ORDER.index(policy) if policy in POLICY_ORDER else len(POLICY_ORDER)


def summary(run: SearchRun) -> dict[str, Any]:
    """The ``--json`` object: scores per policy, the run's settings and its wall time."""
    return {"policies": policy_scores(run.results), "vs_ovamos": paired_differences(run.results),
            "missed": miss_reasons(run.results),
            "seconds": round(run.seconds, 1),
            "episodes_per_min": round(60 * len(run.results) / max(run.seconds, 1e-9), 2),
            "seed": run.seed, "episodes": run.episodes, "workers": run.workers,
            "max_steps": run.max_steps}


def print_table(console: Console, result: dict[str, Any]) -> None:
    """Table I (baselines vs. the method) and Table II (ablations), ours beside the paper's."""
    scores = result["policies"]
    limit = "" if result.get("max_steps") is None else f", max {result['max_steps']} steps (quick run)"
    for title, rows in (("Table I: comparison with baselines", TABLE_I),
                        ("Table II: ablations", TABLE_II)):
        present = [p for p in rows if p in scores]
        if not present:
            continue
        table = Table("method", "episodes", "SR", "MSPL", "targets found", "wrong STOPs", "paper SR",
                      "paper MSPL", title=f"{title} (seed {result['seed']}{limit})")
        for policy in present:
            s, (paper_sr, paper_mspl) = scores[policy], PAPER[policy]
            label = "OVAMOS (full)" if rows is TABLE_II and policy == "ovamos" else LABELS[policy]
            table.add_row(label, str(s["episodes"]), f"{s['sr']:.1f}%", f"{s['mspl']:.3f}",
                          f"{s['targets_found']:.1f}%", str(s.get("wrong_stops", "")),
                          f"{paper_sr:.1f}%", f"{paper_mspl:.3f}")
        console.print(table)
    paired = result.get("vs_ovamos", {})
    if paired:
        table = Table("method", "episodes", "OVAMOS SR minus it", "95% CI", "OVAMOS MSPL minus it", "95% CI",
                      title="OVAMOS against each policy on the same episodes (bootstrap)")
        for policy, d in paired.items():
            table.add_row(LABELS.get(policy, policy), str(d["episodes"]), f"{d['sr_diff']:+.1f}",
                          f"[{d['sr_ci'][0]:+.1f}, {d['sr_ci'][1]:+.1f}]", f"{d['mspl_diff']:+.3f}",
                          f"[{d['mspl_ci'][0]:+.3f}, {d['mspl_ci'][1]:+.3f}]")
        console.print(table)
    missed = {p: m for p, m in result.get("missed", {}).items() if m["targets"]}
    if missed:
        table = Table("method", "targets", *(m.value for m in Miss),
                      title="Targets missed, by the first stage they never reached")
        for policy, m in missed.items():
            table.add_row(LABELS.get(policy, policy), str(m["targets"]), *(str(m[k.value]) for k in Miss))
        console.print(table)
    total = sum(s["episodes"] for s in scores.values())
    console.print(f"{total} episodes in {result['seconds']:.0f} s on {result['workers']} worker(s): "
                  f"{result['episodes_per_min']:.1f} episodes/min")


# -- files ----------------------------------------------------------------------------------------
def jsonl_line(result: EpisodeResult) -> str:
    """One comparable JSONL line: everything but the wall clock."""
    return result.model_dump_json(exclude=TIMING_FIELDS) + "\n"


def read_results(path: Path) -> list[EpisodeResult]:
    """Episodes from a JSONL this module wrote (wall clock absent: 0); a bad line names itself."""
    results = []
    try:
        lines = Path(path).read_text().splitlines()
    except OSError as exc:
        raise SearchError(f"cannot read {path}: {exc}") from None
    for n, line in enumerate(lines, 1):
        if line.strip():
            try:
                results.append(EpisodeResult.model_validate({"seconds": 0.0, **json.loads(line)}))
            except (ValueError, ValidationError) as exc:
                raise SearchError(f"{path}:{n}: not an episode result: {exc}") from None
    return results


def write_outputs(out: Path, run: SearchRun, result: dict[str, Any]) -> list[Path]:
    """episodes.jsonl (comparable across runs), timings.jsonl, summary.json and chart.png."""
    out.mkdir(parents=True, exist_ok=True)
    episodes, timings, summary_file = out / EPISODES_FILE, out / TIMINGS_FILE, out / SUMMARY_FILE
    episodes.write_text("".join(jsonl_line(r) for r in run.results))
    timings.write_text("".join(json.dumps({"episode_id": r.episode_id, "policy": r.policy,
                                           "seconds": r.seconds, "steps": r.steps}) + "\n"
                               for r in run.results))
    summary_file.write_text(json.dumps(result, indent=2) + "\n")
    return [episodes, timings, summary_file, write_png(out / CHART_FILE, draw_chart(result["policies"]))]


# -- pictures -------------------------------------------------------------------------------------
FONT = cv2.FONT_HERSHEY_SIMPLEX
INK = (30, 30, 30)
SR_COLOUR, MSPL_COLOUR = (180, 110, 30), (40, 140, 240)   # BGR: blue, orange
SUCCESS_COLOUR, FAILURE_COLOUR = (40, 160, 40), (40, 40, 220)
MISSED_COLOUR = (200, 40, 200)


def _put(image: np.ndarray, text: str, at: tuple[int, int], scale: float = 0.45,
         colour: tuple[int, int, int] = INK, centred: bool = False) -> None:
    if centred:
        width = cv2.getTextSize(text, FONT, scale, 1)[0][0]
        at = (at[0] - width // 2, at[1])
    cv2.putText(image, text, at, FONT, scale, colour, 1, cv2.LINE_AA)


def draw_chart(scores: dict[str, dict[str, Any]], height: int = 440) -> np.ndarray:
    """Grouped bars per policy: SR (as a fraction) and MSPL on one 0..1 axis, the paper's values
    as black ticks across the bars. A BGR image."""
    policies = [p for p in POLICY_ORDER if p in scores]
    left, top, bottom, group = 70, 75, 60, 150
    image = np.full((height, max(left + group * len(policies) + 20, 460), 3), 255, np.uint8)
    plot_h = height - top - bottom

    def y(value: float) -> int:
        return int(round(top + plot_h * (1 - min(max(value, 0.0), 1.0))))

    for tick in np.linspace(0, 1, 5):
        cv2.line(image, (left, y(tick)), (image.shape[1] - 10, y(tick)), (220, 220, 220), 1)
        _put(image, f"{tick:.2f}", (left - 45, y(tick) + 5), 0.4)
    _put(image, "Search benchmark: SR (as a fraction) and MSPL per policy", (left, 24), 0.5)
    _chart_key(image, left, 40)
    for i, policy in enumerate(policies):
        x0 = left + i * group + 25
        paper = (PAPER[policy][0] / 100, PAPER[policy][1]) if policy in PAPER else (None, None)
        ours = (scores[policy]["sr"] / 100, scores[policy]["mspl"])
        for j, (value, ref, colour) in enumerate(zip(ours, paper, (SR_COLOUR, MSPL_COLOUR))):
            xa = x0 + j * 50
            cv2.rectangle(image, (xa, y(value)), (xa + 45, y(0)), colour, -1)
            _put(image, f"{value:.2f}", (xa + 22, y(value) - 6), 0.4, centred=True)
            if ref is not None:
                cv2.line(image, (xa - 3, y(ref)), (xa + 48, y(ref)), (0, 0, 0), 2)
        _put(image, LABELS.get(policy, policy), (x0 + 47, y(0) + 22), 0.45, centred=True)
        _put(image, f"n={scores[policy]['episodes']}", (x0 + 47, y(0) + 42), 0.4, centred=True)
    return image


def _chart_key(image: np.ndarray, x: int, y: int) -> None:
    """SR and MSPL swatches and the paper's tick, in one row from (x, y) (the row's top)."""
    for name, colour in (("SR", SR_COLOUR), ("MSPL", MSPL_COLOUR)):
        cv2.rectangle(image, (x, y), (x + 14, y + 14), colour, -1)
        _put(image, name, (x + 20, y + 13), 0.45)
        x += 90
    cv2.line(image, (x, y + 7), (x + 24, y + 7), (0, 0, 0), 2)
    _put(image, "the paper", (x + 30, y + 13), 0.45)


def _world_to_px(image: np.ndarray, px_per_m: float) -> Callable[[float, float], tuple[int, int]]:
    """World metres -> pixels of a :func:`draw_scene` picture (same margin, y up)."""
    height = image.shape[0]
    return lambda x, y: (int(round((x + MARGIN_M) * px_per_m)),
                         int(round(height - (y + MARGIN_M) * px_per_m)))


def _draw_trajectory(image: np.ndarray, px: Callable[[float, float], tuple[int, int]],
                     trajectory: Sequence[Sequence[float]]) -> None:
    """The path coloured by time (cold = early, hot = late), so its direction and revisits show."""
    points = [px(x, y) for x, y, _ in trajectory]
    if len(points) < 2:
        return
    ramp = cv2.applyColorMap(np.linspace(0, 255, len(points) - 1).astype(np.uint8).reshape(-1, 1),
                             cv2.COLORMAP_JET).reshape(-1, 3)
    for (a, b), colour in zip(zip(points, points[1:]), ramp):
        cv2.line(image, a, b, tuple(int(c) for c in colour), 2, cv2.LINE_AA)


def _draw_pose(image: np.ndarray, px: Callable[[float, float], tuple[int, int]],
               pose: Sequence[float], fill: tuple[int, int, int], text: str, px_per_m: float) -> None:
    x, y, yaw = pose
    centre = px(x, y)
    cv2.circle(image, centre, int(0.2 * px_per_m), fill, -1, cv2.LINE_AA)
    cv2.circle(image, centre, int(0.2 * px_per_m), (0, 0, 0), 2, cv2.LINE_AA)
    cv2.line(image, centre, px(x + 0.4 * math.cos(yaw), y + 0.4 * math.sin(yaw)), (0, 0, 0), 2,
             cv2.LINE_AA)
    _put(image, text, (centre[0] - 5, centre[1] + 5), 0.45, (0, 0, 0))


def _draw_targets(image: np.ndarray, px: Callable[[float, float], tuple[int, int]], scene: Scene,
                  result: EpisodeResult, px_per_m: float) -> None:
    """A ring round every instance of every target: green when that target was found, magenta
    when it was missed; labelled T1.. in target order."""
    found = set(result.found)
    for n, target in enumerate(result.targets, 1):
        colour = SUCCESS_COLOUR if target in found else MISSED_COLOUR
        for obj in scene.instances(target):
            radius = int((0.5 * math.hypot(obj.sx, obj.sy) + 0.15) * px_per_m)
            centre = px(obj.x, obj.y)
            cv2.circle(image, centre, radius, colour, 3, cv2.LINE_AA)
            at = (min(centre[0] + radius, image.shape[1] - 30), max(centre[1] - radius, 18))
            _put(image, f"T{n}", at, 0.55, colour)  # kept inside the picture


def _draw_stops(image: np.ndarray, px: Callable[[float, float], tuple[int, int]],
                result: EpisodeResult, px_per_m: float) -> None:
    for n, stop in enumerate(result.stops, 1):
        colour = SUCCESS_COLOUR if stop.success else FAILURE_COLOUR
        centre = px(stop.x, stop.y)
        cv2.circle(image, centre, int(0.22 * px_per_m), colour, -1, cv2.LINE_AA)
        cv2.circle(image, centre, int(1.0 * px_per_m), colour, 1, cv2.LINE_AA)  # the 1 m (straight)
        _put(image, f"S{n}", (centre[0] - 9, centre[1] + 5), 0.45, (255, 255, 255))


def legend_lines(result: EpisodeResult) -> list[tuple[str, tuple[int, int, int]]]:
    """The replay's text: outcome, targets, path, why the agent stopped, every STOP."""
    found = set(result.found)
    verdict = "SUCCESS" if result.success else f"FAILURE: found {len(found & set(result.targets))}" \
                                               f"/{len(result.targets)}"
    lines = [(f"episode {result.episode_id}  policy {result.policy}", INK),
             (f"{verdict}   SPL {result.spl:.3f}", SUCCESS_COLOUR if result.success else FAILURE_COLOUR),
             (f"scene seed {result.scene_seed}", INK), ("targets:", INK)]
    why = {f.label: f.miss for f in result.funnel}
    lines += [(f"  T{n} {t}: " + ("found" if t in found else "missed" + (f" ({why[t].value})" if why.get(t) else "")),
               SUCCESS_COLOUR if t in found else MISSED_COLOUR) for n, t in enumerate(result.targets, 1)]
    lines += [(f"steps {result.steps}, decisions {result.decisions}, blocked {result.blocked}", INK),
              (f"path {result.path_m:.1f} m, shortest tour {result.shortest_m:.1f} m", INK),
              (f"agent: {result.state} {result.reason}".strip(), INK),
              (f"STOPs ({len(result.stops)}):", INK)]
    lines += [(f"  S{n} step {s.step} {s.label}: {'ok' if s.success else 'WRONG'}, "
               f"{s.distance_m:.2f} m to nearest", SUCCESS_COLOUR if s.success else FAILURE_COLOUR)
              for n, s in enumerate(result.stops, 1)]
    lines += [("", INK), ("key:", INK), ("  S = start, E = end (arrow: heading)", INK),
              ("  path: blue (early) -> red (late)", INK),
              ("  S1..: STOP, green ok / red wrong; thin ring 1 m", INK),
              ("  T1..: target instances, green found / magenta missed", INK)]
    return lines


def _legend(lines: Sequence[tuple[str, tuple[int, int, int]]], height: int, width: int = 480
            ) -> np.ndarray:
    panel = np.full((max(height, 22 * len(lines) + 30), width, 3), 250, np.uint8)
    for k, (text, colour) in enumerate(lines):
        _put(panel, text[:60], (12, 28 + 22 * k), 0.48, colour)
    return panel


def draw_replay(result: EpisodeResult, scene: Scene, px_per_m: float = 60.0) -> np.ndarray:
    """The scene from above with the episode drawn on it, and a legend to its right (BGR)."""
    image = draw_scene(scene, px_per_m=px_per_m)
    px = _world_to_px(image, px_per_m)
    _draw_targets(image, px, scene, result, px_per_m)
    _draw_trajectory(image, px, result.trajectory)
    _draw_stops(image, px, result, px_per_m)
    _draw_pose(image, px, result.trajectory[0], (255, 255, 255), "S", px_per_m)
    _draw_pose(image, px, result.trajectory[-1], (200, 200, 200), "E", px_per_m)
    panel = _legend(legend_lines(result), image.shape[0])
    if panel.shape[0] > image.shape[0]:
        image = cv2.copyMakeBorder(image, 0, panel.shape[0] - image.shape[0], 0, 0,
                                   cv2.BORDER_CONSTANT, value=(255, 255, 255))
    return np.hstack([image, panel])


def find_result(results: Iterable[EpisodeResult], episode_id: str, policy: str) -> EpisodeResult:
    for result in results:
        if result.episode_id == episode_id and result.policy == policy:
            return result
    raise SearchError(f"no episode {episode_id} with policy {policy} in the file")


def replay(episode_id: str, out: Path, policy: str = "ovamos", source: Path | None = None,
           max_steps: int | None = None) -> tuple[Path, EpisodeResult]:
    """Draw one episode: re-run it (deterministic), or read it from ``source`` (a JSONL this
    module wrote). The scene is always regenerated from the id; a file whose scene seed differs
    was made by another generator and is refused rather than drawn on the wrong house."""
    seed, index = parse_episode_id(episode_id)
    (policy,) = parse_policies(policy)
    init_worker()
    spec, scene, _ = _episode(seed, index)
    if source is None:
        result = run_job(Job(policy, seed, index, max_steps))
    else:
        result = find_result(read_results(source), spec.episode_id, policy)
        if result.scene_seed != spec.scene_seed:
            raise SearchError(f"{source}: episode {episode_id} has scene seed {result.scene_seed}, "
                              f"this code generates {spec.scene_seed}")
    out.mkdir(parents=True, exist_ok=True)
    path = write_png(out / f"replay-{spec.episode_id}-{policy}.png", draw_replay(result, scene))
    return path, result


# -- the command ----------------------------------------------------------------------------------
def main(*, episodes: int = 120, seed: int = 0, policies: str = ",".join(POLICY_ORDER), workers: int = 2,
         as_json: bool = False, out: Path | None = None, max_steps: int | None = None,
         replay_id: str | None = None, policy: str = "ovamos", source: Path | None = None,
         console: Console | None = None, err: Console | None = None) -> int:
    """``ovamos bench search``: the benchmark, or with ``replay_id`` one episode's picture.
    Raises :class:`SearchError` for bad arguments; returns the exit code."""
    console = console or Console()
    err = err or Console(stderr=True)
    if replay_id is not None:
        if out is None:
            raise SearchError("--replay needs --out DIR for the picture")
        path, result = replay(replay_id, out, policy, source, max_steps)
        if as_json:
            print(json.dumps({"png": str(path), **result.model_dump(mode="json", exclude={"trajectory"})}))
        else:
            console.print(f"episode {result.episode_id} ({result.policy}): "
                          f"{'success' if result.success else 'failure'}, found {list(result.found)} of "
                          f"{list(result.targets)}, {result.steps} steps -> {path}")
        return 0
    run = run_search(episodes, seed, parse_policies(policies), workers, max_steps, progress=err)
    result = summary(run)
    if out is not None:
        written = write_outputs(out, run, result)
        err.print(f"wrote {', '.join(str(p) for p in written)}")
    if as_json:
        print(json.dumps(result))
    else:
        print_table(console, result)
    return 0
