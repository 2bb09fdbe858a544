"""The search benchmark's work units: one (policy, episode) pair, run in a worker process.

An episode costs seconds to tens of seconds of CPU (render, perception, map and a decision per
step) and episodes are independent, so the work units are (policy, episode index) pairs spread
over worker processes. Workers are started with "spawn": a fresh interpreter per worker inherits
no MuJoCo/EGL context or thread state from the parent. Results stream back as they finish, each
naming the worker that ran it. Dask runs the same units on a cluster (:mod:`ovamos.bench.cluster`).

An episode's outcome depends only on (seed, index, policy, step limit, perception preset, home
tier, base, motion): the runner is deterministic (a wheeled base runs in simulated time).
"""

from __future__ import annotations

import functools
import multiprocessing as mp
import os
import socket
from collections.abc import Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass, field
from typing import Any, cast

from ovamos.bench.episode import EpisodeConfig, EpisodeResult, StepLatency, episode_config, run_episode
from ovamos.services.mapping.config import MappingConfig
from ovamos.services.mapping.localization import LocalizationConfig
from ovamos.services.planner.agent import AgentConfig
from ovamos.services.sim.odometry import odometry_errors
from ovamos.services.sim.robot import MotionConfig
from ovamos.shared.motion import DriveMode
from ovamos.world.episodes import make_episode
from ovamos.world.evaluator import GroundTruth
from ovamos.world.perception_presets import perception_preset
from ovamos.world.prior import ObjectPrior
from ovamos.world.scene import Scene


class EpisodeFailed(RuntimeError):
    """An episode raised; the message names the work unit (it must survive pickling)."""


@dataclass(frozen=True)
class Job:
    """One work unit and what its outcome depends on besides the code."""

    policy: str
    seed: int
    index: int
    max_steps: int | None = None
    perception: str = "ideal"
    homes: str = "default"
    base: str = "kinematic"
    motion: str = "stepwise"
    odometry: str = "ideal"
    localization: bool = False
    step_latency: float | None = None  # seconds a step costs besides its motion (None: StepLatency's)

    @property
    def name(self) -> str:
        return f"{self.policy} {self.seed}-{self.index}"


@functools.cache
def load_prior() -> ObjectPrior:
    """The object prior, read once per process (every episode and the perception model use it)."""
    return ObjectPrior.load()


@functools.lru_cache(maxsize=4)
def load_episode(seed: int, index: int, homes: str = "default") -> tuple[Any, Scene, GroundTruth]:
    """An episode's spec, scene and ground truth: cached because the policies of one episode
    share them, and generating a scene and its distance fields costs about a second."""
    return make_episode(seed, index, load_prior(), homes)


def init_worker() -> None:
    """Per worker process: headless rendering (EGL) unless the user chose a GL backend, and the
    prior loaded once before the first episode. Cheap when called again (a Dask worker runs it
    in every task: it has no initializer of its own)."""
    os.environ.setdefault("MUJOCO_GL", "egl")
    load_prior()


def run_job(job: Job) -> EpisodeResult:
    """The episode of ``job`` with its policy (the step limit overridden for quick runs)."""
    spec, scene, truth = load_episode(job.seed, job.index, job.homes)
    if job.max_steps is not None:
        spec = spec.model_copy(update={"max_steps": job.max_steps})
    config = EpisodeConfig(perception=perception_preset(job.perception), base=job.base,
                           agent=AgentConfig(motion=cast(DriveMode, job.motion)),
                           motion=MotionConfig(odometry=odometry_errors(job.odometry)),
                           mapping=MappingConfig(localization=LocalizationConfig(enabled=job.localization)),
                           latency=StepLatency.totalling(job.step_latency))
    return run_episode(spec, scene, truth, episode_config(job.policy, config), load_prior())


@dataclass(frozen=True)
class Finished:
    """A work unit as the driver receives it: its result, or the error it raised (naming the
    unit), and ``where`` it ran (``worker``: a Dask worker's address, else ``host:pid``; ``pid``)."""

    job: Job
    result: EpisodeResult | None = None
    error: str | None = None
    where: dict[str, str | int] = field(default_factory=dict)


def work(job: Job) -> dict[str, Any]:
    """Worker entry: a plain dict crosses the process boundary, an episode's error as a value (the
    driver decides whether the run goes on) and the process that ran it."""
    pid = os.getpid()
    where = {"worker": f"{socket.gethostname()}:{pid}", "pid": pid}
    try:
        return {"result": run_job(job).model_dump(mode="json"), **where}
    except Exception as exc:
        return {"error": f"episode {job.name}: {type(exc).__name__}: {exc}", **where}


def finished(job: Job, payload: dict[str, Any]) -> Finished:
    """The driver's side of :func:`work`."""
    result = payload.get("result")
    return Finished(job, None if result is None else EpisodeResult.model_validate(result), payload.get("error"),
                    {k: payload[k] for k in ("worker", "pid")})


def jobs_for(episodes: int, seed: int, policies: Sequence[str], max_steps: int | None = None,
             perception: str = "ideal", homes: str = "default", base: str = "kinematic",
             motion: str = "stepwise", odometry: str = "ideal", localization: bool = False,
             step_latency: float | None = None) -> list[Job]:
    """Episode-major order: a worker tends to get the policies of one episode in a row (its scene
    is cached), and a run cut short has covered every policy about equally."""
    return [Job(p, seed, i, max_steps, perception, homes, base, motion, odometry, localization, step_latency)
            for i in range(episodes) for p in policies]


def iter_results(jobs: Sequence[Job], workers: int, keep_going: bool = False) -> Iterator[Finished]:
    """Units as they finish: in this process for one worker, else from a spawn pool. A unit that
    raises comes back with its error when ``keep_going`` (the search benchmark's choice, as on a
    cluster: the run goes on and ``--resume`` re-runs it); else it raises :class:`EpisodeFailed`
    and the units not yet started are cancelled.

    A process pool executor rather than ``multiprocessing.Pool``: a worker that dies (a crash in
    the GL driver, the OOM killer) fails the run with BrokenProcessPool instead of hanging it.
    Close the iterator (``contextlib.closing``) to stop the pool when the caller stops early."""
    for unit in _pool(jobs, workers):
        if unit.error is not None and not keep_going:
            raise EpisodeFailed(unit.error)
        yield unit


def _pool(jobs: Sequence[Job], workers: int) -> Iterator[Finished]:
    if workers <= 1 or len(jobs) <= 1:
        init_worker()
        for job in jobs:
            yield finished(job, work(job))
        return
    pool = ProcessPoolExecutor(min(workers, len(jobs)), mp_context=mp.get_context("spawn"),
                               initializer=init_worker)
    try:
        futures = {pool.submit(work, job): job for job in jobs}
        for future in as_completed(futures):
            yield finished(futures[future], future.result())
    finally:
        pool.shutdown(wait=True, cancel_futures=True)
