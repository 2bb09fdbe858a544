"""Search benchmark: the paper's Tables I and II (SR and MSPL per policy) on simulated homes.

The entry point of ``ovamos bench search``: runs every (policy, episode) pair over worker
processes (:mod:`ovamos.bench.jobs`), scores them (:mod:`ovamos.bench.stats`), prints the tables
(:mod:`ovamos.bench.tables`) and writes the files and pictures (:mod:`ovamos.bench.draw`). Results stream back
as they finish and drive the progress bar.

The runner is deterministic, so the per-episode JSONL is sorted by (policy, episode) and written
without the wall-clock field: two runs with one seed give byte-identical files whatever the
worker count; timings go to their own file.

Each result is appended to ``episodes.jsonl`` as it finishes, beside a ``run.json`` naming the
run's settings, so a run cut short (a crash, a closed laptop) loses at most the episodes in flight:
``--resume`` keeps what the folder holds and runs only the missing (policy, episode) pairs. The
same mechanism adds policies or episodes to a finished run; its tables then cover all of them.

The work units run on a local process pool (``--workers N``, the default) or on a Dask cluster
(``--cluster``: :mod:`ovamos.bench.cluster`), with the same results and files: the engine is not a
setting of the run, so a run started on one resumes on the other. A unit that raises does not stop
the run: it is listed at the end (exit code 1) and, being absent from ``episodes.jsonl``, re-run by
``--resume``.

``replay`` draws one episode from above so that a person can see why it failed.
"""

from __future__ import annotations

import json
import time
from collections import Counter
from collections.abc import Callable, Iterable, Iterator, Sequence
from contextlib import ExitStack, closing, contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, get_args

from pydantic import ValidationError
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

from ovamos.bench.cluster import ClusterError, ClusterSpec, connect, iter_cluster, parse_cluster
from ovamos.bench.draw import draw_chart, draw_replay
from ovamos.bench.episode import EpisodeResult, StepLatency
from ovamos.bench.jobs import Finished, Job, init_worker, iter_results, jobs_for, load_episode, run_job
from ovamos.bench.policies import DEFAULT_POLICIES, POLICY_ORDER
from ovamos.bench.provenance import code_version
from ovamos.bench.stats import miss_reasons, paired_differences, policy_scores, time_by_step
from ovamos.bench.tables import print_table
from ovamos.bench.trajectory import write_tum
from ovamos.services.mapping.render import write_png
from ovamos.services.sim.odometry import odometry_errors
from ovamos.services.sim.wheels import Motion
from ovamos.shared.motion import MOTIONS
from ovamos.world.generate import home_tier
from ovamos.world.perception_presets import perception_preset

TIMING_FIELDS = {"seconds"}  # wall clock: kept out of the comparable JSONL
#: written only where they hold something (odometry errs): lines of ideal odometry stay as they were
ODOMETRY_FIELDS = ("believed", "odometry", "localization")

EPISODES_FILE, TIMINGS_FILE, SUMMARY_FILE, CHART_FILE, RUN_FILE, TRAJECTORIES = (
    "episodes.jsonl", "timings.jsonl", "summary.json", "chart.png", "run.json", "trajectories")
#: What an episode's outcome depends on besides the code, policy and index: a resumed run must match.
RUN_SETTINGS = ("seed", "perception", "homes", "max_steps", "base", "motion", "odometry", "localization",
                "step_latency")
#: the value of a setting a run.json from before it existed held
SETTING_DEFAULTS: dict[str, Any] = {"base": "kinematic", "motion": "stepwise", "odometry": "ideal",
                                    "localization": False, "step_latency": None}
BASES: tuple[str, ...] = get_args(Motion)  # the robots an episode can run on
#: the code version of an episode whose timing line does not name one
UNRECORDED = "unrecorded"


class SearchError(ValueError):
    """Bad arguments or input files: the CLI prints the message and exits 2."""


# -- arguments -------------------------------------------------------------------------------------
def parse_policies(text: str | Sequence[str]) -> tuple[str, ...]:
    """Policy names from "a,b" or a sequence, de-duplicated, in the paper's order."""
    names = [p.strip() for p in (text.split(",") if isinstance(text, str) else text) if p.strip()]
    unknown = [p for p in names if p not in POLICY_ORDER]
    if unknown or not names:
        raise SearchError(f"unknown or no policies {unknown or names} (known: {', '.join(POLICY_ORDER)})")
    return tuple(p for p in POLICY_ORDER if p in names)


def check_settings(perception: str, homes: str, base: str = "kinematic", motion: str = "stepwise",
                   odometry: str = "ideal", step_latency: float | None = None) -> None:
    """A perception preset, a home tier, a base, a motion, an odometry preset and a step latency
    that exist and go together (else a :class:`SearchError` naming them)."""
    if step_latency is not None and (not step_latency >= 0 or base == "kinematic"):
        raise SearchError(f"--step-latency {step_latency}: seconds >= 0 a step costs besides its motion, which "
                          "times a wheeled base's search (--base kobuki, opencr or odrive); the kinematic base "
                          "keeps no time")
    if base not in BASES:
        raise SearchError(f"unknown base {base!r}: one of {', '.join(BASES)}")
    if motion not in MOTIONS:
        raise SearchError(f"unknown motion {motion!r}: one of {', '.join(MOTIONS)}")
    if motion == "continuous" and base == "kinematic":
        raise SearchError("continuous motion drives paths on a wheeled base: add --base kobuki, opencr or odrive")
    try:
        perception_preset(perception)
        home_tier(homes)
        odometry_errors(odometry)
    except ValueError as exc:
        raise SearchError(str(exc)) from None


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
    perception: str = "ideal"
    homes: str = "default"
    base: str = "kinematic"
    motion: str = "stepwise"
    odometry: str = "ideal"
    localization: bool = False
    step_latency: float | None = None  # None: StepLatency's defaults
    resumed: int = 0  # results read back from the folder, not run (and not timed) by this run
    code: dict[str, int] = field(default_factory=dict)  # episodes per code version that ran them
    failed: list[str] = field(default_factory=list)  # the units that raised (their errors): not in results
    engine: str = ""  # what ran the units: the process pool or a Dask cluster


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


def run_search(episodes: int, seed: int = 0, policies: Sequence[str] = DEFAULT_POLICIES, workers: int = 2,
               max_steps: int | None = None, progress: Console | None = None, perception: str = "ideal",
               homes: str = "default", out: Path | None = None, resume: bool = False,
               base: str = "kinematic", motion: str = "stepwise", cluster: str | None = None,
               cluster_config: Path | None = None, odometry: str = "ideal", localization: bool = False,
               step_latency: float | None = None) -> SearchRun:
    """Run every (policy, episode) pair with the simulated perception ``perception`` (a preset
    name) in homes of tier ``homes`` on the robot ``base`` (kinematic, or a wheeled base's
    controller and simulated device in simulated time) driven ``motion`` (stepwise, or continuous
    on a wheeled base), its odometry erring as the preset ``odometry`` says, its map built with or
    without ``localization``, each step costing ``step_latency`` seconds besides its motion (a
    wheeled base's search time; None: :class:`StepLatency`'s defaults); ``max_steps`` overrides
    the paper's 500 (quick runs and tests only: the tables need the paper's limit).

    With ``out`` each result is appended to its ``episodes.jsonl`` as it finishes; with ``resume``
    the pairs that file already holds are kept, not run again, and the run covers them too.

    The units run on ``workers`` local processes, or with ``cluster`` (``local[:N]``,
    ``tcp://HOST:PORT``, ``slurm`` with ``cluster_config``) on Dask. A unit that raises is
    listed in the run's ``failed`` and the run goes on."""
    if episodes < 1 or workers < 1 or (max_steps is not None and max_steps < 1):
        raise SearchError(f"need episodes >= 1, workers >= 1 and max steps >= 1 "
                          f"(got {episodes}, {workers}, {max_steps})")
    if resume and out is None:
        raise SearchError("--resume needs --out DIR: the folder of the run to go on with")
    policies = parse_policies(policies)
    check_settings(perception, homes, base, motion, odometry, step_latency)
    try:
        spec = parse_cluster(cluster, cluster_config, workers) if cluster is not None else None
    except ClusterError as exc:
        raise SearchError(str(exc)) from None
    settings = {"seed": seed, "perception": perception, "homes": homes, "max_steps": max_steps, "base": base,
                "motion": motion, "odometry": odometry, "localization": localization, "step_latency": step_latency}
    kept = held_results(out, settings) if resume and out is not None else []
    done = {(r.policy, _episode_index(r)) for r in kept}  # run.json vouched for their seed
    jobs = [j for j in jobs_for(episodes, seed, policies, max_steps, perception, homes, base, motion, odometry,
                                localization, step_latency) if (j.policy, j.index) not in done]
    code = code_version()
    kept_code = code_versions(out, kept) if out is not None and kept else Counter[str]()
    if progress is not None and kept:
        versions = ", ".join(f"{v}: {n}" for v, n in kept_code.items())
        progress.print(f"resuming {out}: {len(kept)} episodes kept (by code version: {versions}), "
                       f"{len(jobs)} to run on {code}", highlight=False, soft_wrap=True)
    append = _start_file(out, settings, kept, code) if out is not None else None
    started = time.perf_counter()
    results, failed = list(kept), []
    engine = spec.describe() if spec is not None else f"process pool, {min(workers, max(len(jobs), 1))} workers"
    with ExitStack() as stack, _progress(progress, len(jobs)) as advance:
        for unit in stack.enter_context(closing(_units(jobs, workers, spec, stack, progress, code))):
            if unit.result is None:
                failed.append(unit.error or f"episode {unit.job.name}: no result")
                if progress is not None:
                    progress.print(f"failed: {failed[-1]}", highlight=False, soft_wrap=True, markup=False)
                continue
            pair = (unit.result.policy, _episode_index(unit.result))
            if pair in done:
                continue  # a unit the engine ran twice (a worker lost after it finished): counted once
            done.add(pair)
            results.append(unit.result)
            if append is not None:
                append(unit.result, unit.where.get("worker"))
            advance(unit.result)
    codes = kept_code + Counter({code: len(results) - len(kept)})  # (a count of 0 is dropped)
    return SearchRun(seed, max([episodes, *(_episode_index(r) + 1 for r in kept)]),
                     parse_policies([*policies, *(r.policy for r in kept)]), workers, max_steps,
                     sort_results(results), time.perf_counter() - started, perception, homes, base, motion,
                     odometry, localization, step_latency, len(kept), dict(codes), failed, engine)


def _units(jobs: Sequence[Job], workers: int, spec: ClusterSpec | None, stack: ExitStack,
           progress: Console | None, code: str) -> Iterator[Finished]:
    """The units as they finish, errors as values: from the process pool, or from a Dask cluster
    that ``stack`` shuts down (a bad cluster is a :class:`SearchError`)."""
    if spec is None or not jobs:
        return iter_results(jobs, workers, keep_going=True)
    if progress is not None:
        progress.print(f"starting {spec.describe()}", highlight=False, soft_wrap=True)
    try:
        warn = None if progress is None else (lambda text: progress.print(text, highlight=False, markup=False))
        client = stack.enter_context(connect(spec, code, warn))
    except ClusterError as exc:
        raise SearchError(str(exc)) from None
    return iter_cluster(jobs, client)


def held_results(out: Path, settings: dict[str, Any]) -> list[EpisodeResult]:
    """The episodes a run in ``out`` already finished, if it ran with ``settings`` (else a
    :class:`SearchError` naming what differs: mixing them would make a table of two benchmarks).
    A last line cut short by a crash is dropped; that episode runs again."""
    episodes = out / EPISODES_FILE
    if not episodes.exists():
        return []
    try:
        held = json.loads((out / RUN_FILE).read_text())
    except (OSError, ValueError) as exc:
        raise SearchError(f"cannot resume {out}: its {RUN_FILE} does not say which settings its episodes were "
                          f"run with ({exc})") from None
    held = {k: held.get(k, SETTING_DEFAULTS.get(k)) for k in RUN_SETTINGS}
    differ = [f"{k} {held[k]!r} there, {settings[k]!r} here" for k in RUN_SETTINGS if held[k] != settings[k]]
    if differ:
        raise SearchError(f"cannot resume {out}: its episodes were run with other settings ({'; '.join(differ)})")
    return read_results(episodes, torn_tail=True)


def code_versions(out: Path, kept: Sequence[EpisodeResult]) -> Counter[str]:
    """How many of the ``kept`` episodes each code version ran, from their timing lines in ``out``
    ("unrecorded": a line from before versions were recorded, or none)."""
    timings = out / TIMINGS_FILE
    lines = timings.read_text().splitlines() if timings.exists() else []
    versions = dict(t for t in map(_timing, lines) if t is not None)
    return Counter(versions.get((r.episode_id, r.policy), UNRECORDED) for r in kept)


def _start_file(out: Path, settings: dict[str, Any], kept: Sequence[EpisodeResult], code: str
                ) -> Callable[[EpisodeResult, Any], None]:
    """Write run.json, the kept episodes and their timings; return the function that appends
    each new result to both files (its timing line naming ``code``, the version running it, and
    the worker that ran it: ``host:pid`` in the process pool, a Dask worker's address). Each line
    is flushed as it is written: a run stopped by Ctrl-C keeps every episode that finished."""
    out.mkdir(parents=True, exist_ok=True)
    (out / RUN_FILE).write_text(json.dumps(settings) + "\n")
    episodes, timings = out / EPISODES_FILE, out / TIMINGS_FILE
    pairs = {(r.episode_id, r.policy) for r in kept}
    old = timings.read_text().splitlines() if kept and timings.exists() else []
    timings.write_text("".join(f"{line}\n" for line in old if (t := _timing(line)) is not None and t[0] in pairs))
    episodes.write_text("".join(jsonl_line(r) for r in kept))

    def append(result: EpisodeResult, worker: Any = None) -> None:
        with timings.open("a") as file:
            file.write(json.dumps({"episode_id": result.episode_id, "policy": result.policy,
                                   "seconds": result.seconds, "steps": result.steps, "code": code,
                                   "worker": worker}) + "\n")
        with episodes.open("a") as file:
            file.write(jsonl_line(result))
    return append


def _timing(line: str) -> tuple[tuple[str, str], str] | None:
    """A timing line's (episode id, policy) and the code version that ran it."""
    try:
        timing = json.loads(line)
        return (timing["episode_id"], timing["policy"]), str(timing.get("code", UNRECORDED))
    except (ValueError, KeyError, TypeError):
        return None  # a line cut short: its episode was not kept either


def summary(run: SearchRun) -> dict[str, Any]:
    """The ``--json`` object: scores per policy, the run's settings and its wall time."""
    return {"policies": policy_scores(run.results), "vs_ovamos": paired_differences(run.results),
            "vs_plus": paired_differences(run.results, reference="ovamos-plus"),
            "missed": miss_reasons(run.results), "time_by_step": time_by_step(run.results),
            "seconds": round(run.seconds, 1),
            "episodes_per_min": round(60 * (len(run.results) - run.resumed) / max(run.seconds, 1e-9), 2),
            "resumed": run.resumed, "code": run.code, "failed": run.failed, "engine": run.engine,
            "seed": run.seed, "episodes": run.episodes, "workers": run.workers,
            "max_steps": run.max_steps, "perception": run.perception, "homes": run.homes, "base": run.base,
            "motion": run.motion, "odometry": run.odometry, "localization": run.localization,
            "step_latency_s": round(StepLatency.totalling(run.step_latency).total_s, 3)}


# -- files ----------------------------------------------------------------------------------------
def jsonl_line(result: EpisodeResult) -> str:
    """One comparable JSONL line: everything but the wall clock."""
    absent = {name for name in ODOMETRY_FIELDS if getattr(result, name) is None}
    return result.model_dump_json(exclude=TIMING_FIELDS | absent) + "\n"


def read_results(path: Path, torn_tail: bool = False) -> list[EpisodeResult]:
    """Episodes from a JSONL this module wrote (wall clock absent: 0); a bad line names itself.
    With ``torn_tail`` a last line without its newline (a write cut short) is dropped, not refused."""
    results = []
    try:
        text = Path(path).read_text()
    except OSError as exc:
        raise SearchError(f"cannot read {path}: {exc}") from None
    lines = text.splitlines()
    if torn_tail and text and not text.endswith("\n"):
        lines.pop()
    for n, line in enumerate(lines, 1):
        if line.strip():
            try:
                results.append(EpisodeResult.model_validate({"seconds": 0.0, **json.loads(line)}))
            except (ValueError, ValidationError) as exc:
                raise SearchError(f"{path}:{n}: not an episode result: {exc}") from None
    return results


def write_outputs(out: Path, run: SearchRun, result: dict[str, Any]) -> list[Path]:
    """episodes.jsonl sorted (comparable across runs), summary.json and chart.png; timings.jsonl
    was written as the episodes finished; where odometry erred, each episode's true and believed
    trajectories in TUM format (``trajectories/POLICY-EPISODE-{true,believed}.tum``, for evo's own
    command line and other SLAM tools)."""
    out.mkdir(parents=True, exist_ok=True)
    episodes, summary_file = out / EPISODES_FILE, out / SUMMARY_FILE
    episodes.write_text("".join(jsonl_line(r) for r in run.results))
    summary_file.write_text(json.dumps(result, indent=2) + "\n")
    written = [episodes, out / TIMINGS_FILE, summary_file, write_png(out / CHART_FILE, draw_chart(result["policies"]))]
    drifted = [r for r in run.results if r.believed is not None]
    if drifted:
        folder = out / TRAJECTORIES
        folder.mkdir(exist_ok=True)
        for r in drifted:
            assert r.believed is not None
            write_tum(folder / f"{r.policy}-{r.episode_id}-true.tum", r.trajectory)
            write_tum(folder / f"{r.policy}-{r.episode_id}-believed.tum", r.believed)
        written.append(folder)
    return written


def find_result(results: Iterable[EpisodeResult], episode_id: str, policy: str) -> EpisodeResult:
    for result in results:
        if result.episode_id == episode_id and result.policy == policy:
            return result
    raise SearchError(f"no episode {episode_id} with policy {policy} in the file")


def replay(episode_id: str, out: Path, policy: str = "ovamos", source: Path | None = None,
           max_steps: int | None = None, perception: str = "ideal", homes: str = "default",
           base: str = "kinematic", motion: str = "stepwise", odometry: str = "ideal",
           localization: bool = False, step_latency: float | None = None) -> tuple[Path, EpisodeResult]:
    """Draw one episode: re-run it (deterministic), or read it from ``source`` (a JSONL this
    module wrote). The scene is always regenerated from the id; a file whose scene seed differs
    was made by another generator and is refused rather than drawn on the wrong house."""
    seed, index = parse_episode_id(episode_id)
    (policy,) = parse_policies(policy)
    check_settings(perception, homes, base, motion, odometry, step_latency)
    init_worker()
    spec, scene, _ = load_episode(seed, index, homes)
    if source is None:
        result = run_job(Job(policy, seed, index, max_steps, perception, homes, base, motion, odometry, localization,
                             step_latency))
    else:
        result = find_result(read_results(source), spec.episode_id, policy)
        if result.scene_seed != spec.scene_seed:
            raise SearchError(f"{source}: episode {episode_id} has scene seed {result.scene_seed}, "
                              f"this code generates {spec.scene_seed}")
    out.mkdir(parents=True, exist_ok=True)
    path = write_png(out / f"replay-{spec.episode_id}-{policy}.png", draw_replay(result, scene))
    return path, result


# -- the command ----------------------------------------------------------------------------------
def main(*, episodes: int = 120, seed: int = 0, policies: str = ",".join(DEFAULT_POLICIES), workers: int = 2,
         as_json: bool = False, out: Path | None = None, max_steps: int | None = None,
         replay_id: str | None = None, policy: str = "ovamos", source: Path | None = None,
         perception: str = "ideal", homes: str = "default", resume: bool = False, base: str = "kinematic",
         motion: str = "stepwise", cluster: str | None = None, cluster_config: Path | None = None,
         odometry: str = "ideal", localization: bool = False, step_latency: float | None = None,
         console: Console | None = None, err: Console | None = None) -> int:
    """``ovamos bench search``: the benchmark, or with ``replay_id`` one episode's picture.
    Raises :class:`SearchError` for bad arguments; returns the exit code."""
    console = console or Console()
    err = err or Console(stderr=True)
    if replay_id is not None:
        if out is None:
            raise SearchError("--replay needs --out DIR for the picture")
        path, result = replay(replay_id, out, policy, source, max_steps, perception, homes, base, motion,
                              odometry, localization, step_latency)
        if as_json:
            print(json.dumps({"png": str(path), **result.model_dump(mode="json", exclude={"trajectory"})}))
        else:
            console.print(f"episode {result.episode_id} ({result.policy}): "
                          f"{'success' if result.success else 'failure'}, found {list(result.found)} of "
                          f"{list(result.targets)}, {result.steps} steps -> {path}")
        return 0
    try:
        run = run_search(episodes, seed, parse_policies(policies), workers, max_steps, progress=err,
                         perception=perception, homes=homes, out=out, resume=resume, base=base,
                         motion=motion, cluster=cluster, cluster_config=cluster_config, odometry=odometry,
                         localization=localization, step_latency=step_latency)
    except KeyboardInterrupt:
        if out is not None and (out / EPISODES_FILE).exists():
            held = len((out / EPISODES_FILE).read_text().splitlines())
            err.print(f"interrupted: {held} episodes are in {out / EPISODES_FILE}; --resume runs the rest",
                      highlight=False, markup=False, soft_wrap=True)
        raise
    result = summary(run)
    if out is not None:
        written = write_outputs(out, run, result)
        err.print(f"wrote {', '.join(str(p) for p in written)}")
    if as_json:
        print(json.dumps(result))
    else:
        print_table(console, result)
    if run.failed:
        err.print(f"{len(run.failed)} episode(s) failed (not in the results; --resume re-runs them):",
                  highlight=False, markup=False)
        for error in run.failed:
            err.print(f"  {error}", highlight=False, markup=False, soft_wrap=True)
        return 1
    return 0
