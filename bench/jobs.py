"""The search benchmark's work units: one (policy, episode) pair, run in a worker process.

An episode costs seconds to tens of seconds of CPU (render, perception, map and a decision per
step) and episodes are independent, so the work units are (policy, episode index) pairs spread
over worker processes. Workers are started with "spawn": a fresh interpreter per worker inherits
no MuJoCo/EGL context or thread state from the parent. Results stream back as they finish.

An episode's outcome depends only on (seed, index, policy, step limit, perception preset, home
tier, base, motion): the runner is deterministic (a wheeled base runs in simulated time).
"""

from __future__ import annotations

import functools
import multiprocessing as mp
import os
from collections.abc import Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass
from typing import Any, cast

from ovamos.bench.episode import EpisodeConfig, EpisodeResult, episode_config, run_episode
from ovamos.services.planner.agent import AgentConfig, DriveMode
from ovamos.services.sim.episodes import make_episode
from ovamos.services.sim.evaluator import GroundTruth
from ovamos.services.sim.perception_presets import perception_preset
from ovamos.services.sim.prior import ObjectPrior
from ovamos.services.sim.world import Scene


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
    prior loaded once before the first episode."""
    os.environ.setdefault("MUJOCO_GL", "egl")
    load_prior()


def run_job(job: Job) -> EpisodeResult:
    """The episode of ``job`` with its policy (the step limit overridden for quick runs)."""
    spec, scene, truth = load_episode(job.seed, job.index, job.homes)
    if job.max_steps is not None:
        spec = spec.model_copy(update={"max_steps": job.max_steps})
    config = EpisodeConfig(perception=perception_preset(job.perception), base=job.base,
                           agent=AgentConfig(motion=cast(DriveMode, job.motion)))
    return run_episode(spec, scene, truth, episode_config(job.policy, config), load_prior())


def _work(job: Job) -> dict[str, Any]:
    """Worker entry: a plain dict crosses the process boundary; errors name the unit."""
    try:
        return run_job(job).model_dump(mode="json")
    except Exception as exc:
        raise EpisodeFailed(f"episode {job.name}: {type(exc).__name__}: {exc}") from None


def jobs_for(episodes: int, seed: int, policies: Sequence[str], max_steps: int | None = None,
             perception: str = "ideal", homes: str = "default", base: str = "kinematic",
             motion: str = "stepwise") -> list[Job]:
    """Episode-major order: a worker tends to get the policies of one episode in a row (its scene
    is cached), and a run cut short has covered every policy about equally."""
    return [Job(p, seed, i, max_steps, perception, homes, base, motion) for i in range(episodes) for p in policies]


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
