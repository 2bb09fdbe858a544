"""The search benchmark's work units on a Dask cluster: ``ovamos bench search --cluster ...``.

The units (:class:`ovamos.bench.jobs.Job`, a frozen dataclass) travel to the workers with their
tasks and each worker generates its scene from the seed: a worker needs the project installed and
nothing else (no shared filesystem). Three engines, one iterator:

- ``local[:N]``: a :class:`distributed.LocalCluster` on 127.0.0.1, N worker processes of one
  thread each, no dashboard;
- ``tcp://HOST:PORT``: a scheduler started elsewhere (``dask scheduler`` and ``dask worker`` by
  hand, or the lab's tooling);
- ``slurm``: dask-jobqueue's :class:`SLURMCluster`, its settings (queue, cores, memory, walltime,
  jobs) from a TOML file (:class:`SlurmConfig`).

Before the first unit is submitted every worker imports the project (:func:`check_workers`): a
worker that cannot is named in the error instead of failing each unit it is given. A worker that
dies mid-episode has its unit re-run elsewhere by the scheduler; a unit that raises comes back as a
:class:`~ovamos.bench.jobs.Finished` with its error and the run goes on.

Dask is imported here only, and only when a cluster is asked for: it is the optional extra
``ovamos[cluster]``.
"""

from __future__ import annotations

import ipaddress
import os
import signal
import threading
import tomllib
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal
from urllib.parse import urlsplit

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from ovamos.bench.jobs import Finished, Job, finished

INSTALL = "pip install 'ovamos[cluster]'"
#: how long a local or tcp cluster may take to show its first worker (SLURM: the config's)
START_TIMEOUT_S = 60.0


class ClusterError(ValueError):
    """A bad --cluster value or config, Dask missing, or a worker that cannot run the units."""


class SlurmConfig(BaseModel):
    """``--cluster slurm``'s settings: the ``[slurm]`` table of the ``--cluster-config`` TOML file.
    Each SLURM job runs ``cores`` worker processes of one thread (an episode is single-threaded)."""

    model_config = ConfigDict(extra="forbid")

    scheduler_host: str = Field(description="This machine's address that the compute nodes reach "
                                            "(the scheduler binds to it).")
    queue: str | None = Field(None, description="The partition (#SBATCH -p).")
    account: str | None = Field(None, description="The account billed (#SBATCH -A).")
    cores: int = Field(ge=1, le=1024, description="Cores per job: that many one-thread workers.")
    memory: str = Field(pattern=r"^\d+(\.\d+)?\s*(k|K|M|G|T|KB|MB|GB|TB|KiB|MiB|GiB|TiB)$",
                        description="Memory per job, e.g. 64GB (about 1 GB per worker).")
    walltime: str = Field(pattern=r"^(\d+-)?\d{1,3}:\d{2}(:\d{2})?$",
                          description="Time limit per job, HH:MM:SS (or D-HH:MM:SS).")
    jobs: int = Field(1, ge=1, le=1000, description="SLURM jobs to submit (nodes, with cores = a node's).")
    python: str | None = Field(None, description="The Python on the nodes with ovamos installed "
                                                 "(default: this one's path).")
    interface: str | None = Field(None, description="The workers' network interface (e.g. ib0).")
    job_script_prologue: list[str] = Field(default_factory=list, description="Shell lines run before the "
                                                                             "worker (module load, venv).")
    job_extra_directives: list[str] = Field(default_factory=list, description="More #SBATCH options.")
    start_timeout_s: float = Field(3600.0, gt=0, description="How long to wait for the first worker "
                                                             "(jobs wait in the queue).")

    @classmethod
    def load(cls, path: Path) -> SlurmConfig:
        try:
            table = tomllib.loads(Path(path).read_text()).get("slurm")
        except (OSError, tomllib.TOMLDecodeError) as exc:
            raise ClusterError(f"cannot read the cluster config {path}: {exc}") from None
        if not isinstance(table, dict):
            raise ClusterError(f"{path}: no [slurm] table (see docs/benchmarks/cluster.md)")
        try:
            return cls.model_validate(table)
        except ValidationError as exc:
            problems = "; ".join(f"{'.'.join(map(str, e['loc'])) or 'slurm'}: {e['msg']}" for e in exc.errors())
            raise ClusterError(f"{path}: bad [slurm] settings: {problems}") from None

    def cluster_kwargs(self) -> dict[str, Any]:
        """dask-jobqueue's SLURMCluster arguments for these settings."""
        prologue = ["export MUJOCO_GL=${MUJOCO_GL:-egl}", *(f"export {k}='{v}'" for k, v in WORKER_ENV.items()),
                    *self.job_script_prologue]
        kwargs: dict[str, Any] = {
            "queue": self.queue, "account": self.account, "cores": self.cores, "processes": self.cores,
            "memory": self.memory, "walltime": self.walltime, "interface": self.interface,
            "job_script_prologue": prologue, "job_extra_directives": self.job_extra_directives,
            "scheduler_options": {"host": self.scheduler_host, "dashboard": False,
                                  "dashboard_address": f"{_host(self.scheduler_host)}:0"},
            "worker_extra_args": ["--no-dashboard"],
        }
        if self.python is not None:
            kwargs["python"] = self.python
        return {k: v for k, v in kwargs.items() if v is not None}


@dataclass(frozen=True)
class ClusterSpec:
    """A parsed ``--cluster``: ``local`` (``workers`` processes), ``tcp`` (``address``) or
    ``slurm`` (``slurm``)."""

    kind: Literal["local", "tcp", "slurm"]
    workers: int = 0
    address: str = ""
    slurm: SlurmConfig | None = None

    def describe(self) -> str:
        if self.kind == "local":
            return f"Dask local cluster, {self.workers} workers"
        if self.kind == "tcp":
            return f"Dask scheduler {self.address}"
        assert self.slurm is not None
        return f"SLURM, {self.slurm.jobs} jobs x {self.slurm.cores} cores"


def parse_cluster(text: str, config: Path | None = None, workers: int = 2) -> ClusterSpec:
    """``local`` (``workers`` processes), ``local:N``, ``tcp://HOST:PORT`` or ``slurm`` (with
    ``config``, a TOML file); anything else is a :class:`ClusterError` saying what is accepted."""
    text = text.strip()
    accepted = "local, local:N, tcp://HOST:PORT or slurm (with --cluster-config FILE.toml)"
    if config is not None and text != "slurm":
        raise ClusterError("--cluster-config is for --cluster slurm")
    if text == "local" or text.startswith("local:"):
        count = text.partition(":")[2] or str(workers)
        if not count.isdigit() or int(count) < 1:
            raise ClusterError(f"--cluster {text!r}: the worker count must be a whole number >= 1 ({accepted})")
        return ClusterSpec("local", workers=int(count))
    if text.startswith("tcp://"):
        parts = urlsplit(text)
        try:
            port = parts.port
        except ValueError:
            port = None
        if not parts.hostname or port is None or parts.path not in ("", "/"):
            raise ClusterError(f"--cluster {text!r}: a scheduler address is tcp://HOST:PORT "
                               f"(e.g. tcp://127.0.0.1:8786)")
        return ClusterSpec("tcp", address=f"tcp://{_host(parts.hostname)}:{port}")
    if text == "slurm":
        if config is None:
            raise ClusterError("--cluster slurm needs --cluster-config FILE.toml: its [slurm] table "
                               "(queue, cores, memory, walltime, jobs)")
        return ClusterSpec("slurm", slurm=SlurmConfig.load(config))
    raise ClusterError(f"unknown --cluster {text!r}: one of {accepted}")


def _host(host: str) -> str:
    try:
        return f"[{host}]" if ipaddress.ip_address(host).version == 6 else host
    except ValueError:
        return host  # a name


#: Dask settings for the workers. The nanny's MALLOC_TRIM_THRESHOLD_ unset: setting it turns off
#: glibc's adaptive mmap threshold, so every frame-sized array is mapped and unmapped (an episode
#: spent 4-5x the system time of the process pool's). The statistical profiler off: it samples
#: the episode's stack every 10 ms for a dashboard that is not shown.
WORKER_CONFIG: dict[str, Any] = {"distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": None,
                                 "distributed.worker.profile.enabled": False}
#: the same as environment variables, for workers started by SLURM or by hand (``dask worker``)
WORKER_ENV = {"DASK_DISTRIBUTED__NANNY__PRE_SPAWN_ENVIRON":
              '{"MALLOC_TRIM_THRESHOLD_": None, "OMP_NUM_THREADS": 1, "MKL_NUM_THREADS": 1, '
              '"OPENBLAS_NUM_THREADS": 1}',
              "DASK_DISTRIBUTED__WORKER__PROFILE__ENABLED": "False"}


def dask_config() -> Any:
    """:data:`WORKER_CONFIG` for the block (the local cluster's nannies read it when created)."""
    import dask
    return dask.config.set(WORKER_CONFIG)


@contextmanager
def _sigint_ignored() -> Iterator[None]:
    """SIGINT ignored while the local cluster's worker processes start (they inherit it): a Ctrl-C
    at the terminal reaches the whole process group, and the command, not each worker, should
    handle it (it cancels the units and shuts the cluster down, without a traceback per worker)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


def _dask() -> Any:
    try:
        import distributed
    except ImportError as exc:
        raise ClusterError(f"--cluster needs Dask distributed ({exc}): {INSTALL}") from None
    return distributed


def slurm_cluster(config: SlurmConfig) -> Any:
    """A started (empty) SLURMCluster for ``config``: its ``job_script()`` is what is submitted."""
    _dask()
    try:
        from dask_jobqueue import SLURMCluster
    except ImportError as exc:
        raise ClusterError(f"--cluster slurm needs dask-jobqueue ({exc}): {INSTALL}") from None
    return SLURMCluster(**config.cluster_kwargs())


@contextmanager
def connect(spec: ClusterSpec, code: str | None = None, warn: Callable[[str], None] | None = None
            ) -> Iterator[Any]:
    """A :class:`distributed.Client` on ``spec``'s cluster, every worker checked (``warn`` is told
    of workers whose code version is not ``code``, the one the timing lines record); what this
    started (a local or SLURM cluster) is shut down on leaving, Ctrl-C included."""
    distributed = _dask()
    cluster: Any = None
    client: Any = None
    try:
        if spec.kind == "local":
            with dask_config(), _sigint_ignored():
                cluster = distributed.LocalCluster(
                    n_workers=spec.workers, threads_per_worker=1, processes=True, host="127.0.0.1",
                    # no dashboards; the HTTP servers Dask starts anyway (health, metrics) on 127.0.0.1 too
                    scheduler_port=0, dashboard_address="127.0.0.1:0", worker_dashboard_address="127.0.0.1:0",
                    scheduler_kwargs={"dashboard": False},
                    env={"MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")})
            address, timeout = cluster, START_TIMEOUT_S
        elif spec.kind == "slurm":
            assert spec.slurm is not None
            cluster = slurm_cluster(spec.slurm)
            cluster.scale(jobs=spec.slurm.jobs)
            address, timeout = cluster, spec.slurm.start_timeout_s
        else:
            address, timeout = spec.address, START_TIMEOUT_S
        try:
            client = distributed.Client(address, timeout=START_TIMEOUT_S)
        except OSError as exc:
            raise ClusterError(f"cannot reach the Dask scheduler {spec.address}: {exc}") from None
        versions = check_workers(client, timeout)
        other = sorted(f"{worker} ({version})" for worker, version in versions.items() if version != code)
        if code is not None and warn is not None and other:
            warn(f"warning: worker(s) {', '.join(other)} run other code than this command ({code}), "
                 f"which the timing lines name")
        yield client
    finally:
        if client is not None:
            client.close()
        if cluster is not None:
            cluster.close()


def check_workers(client: Any, timeout: float = START_TIMEOUT_S) -> dict[str, str]:
    """Wait for a worker, then have every worker import the project; the workers and their code
    versions, or a :class:`ClusterError` naming each worker that cannot run the units."""
    try:
        client.wait_for_workers(1, timeout=timeout)
    except TimeoutError:
        raise ClusterError(f"no Dask worker joined {client.scheduler.address} within {timeout:.0f} s") from None

    def probe() -> str:  # defined here: pickled by value, so it runs where the project does not import
        import importlib
        importlib.import_module("ovamos.bench.jobs")
        return str(importlib.import_module("ovamos.bench.provenance").code_version())

    replies = client.run(probe, on_error="return")
    bad = {worker: reply for worker, reply in replies.items() if isinstance(reply, BaseException)}
    if bad:
        named = "; ".join(f"{worker}: {type(exc).__name__}: {exc}" for worker, exc in sorted(bad.items()))
        raise ClusterError(f"Dask worker(s) cannot import the project: {named} (install it on each worker's "
                           f"machine: pip install 'ovamos[sim,cluster]')")
    return {worker: str(reply) for worker, reply in replies.items()}


def run_unit(job: Job) -> dict[str, Any]:
    """A Dask task: :func:`ovamos.bench.jobs.work` on the worker, named by its address."""
    from distributed import get_worker

    from ovamos.bench.jobs import init_worker, work
    init_worker()
    return {**work(job), "worker": get_worker().address}


def iter_cluster(jobs: Sequence[Job], client: Any) -> Iterator[Finished]:
    """Units as they finish on ``client``'s cluster; one the cluster could not run (its workers
    killed too often, a worker that could not load it) comes back with that error. Closing the
    iterator cancels the units not finished."""
    from distributed import as_completed
    futures = {client.submit(run_unit, job, pure=False, key=f"ovamos-{job.policy}-{job.seed}-{job.index}-"
                                                            f"{os.urandom(4).hex()}"): job for job in jobs}
    try:
        for future in as_completed(futures):
            job = futures.pop(future)
            try:
                payload = future.result()
            except Exception as exc:
                payload = {"error": f"episode {job.name}: {type(exc).__name__}: {exc}", "worker": "", "pid": 0}
            future.release()
            yield finished(job, payload)
    finally:
        if futures:
            client.cancel(list(futures))
