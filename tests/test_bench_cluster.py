"""The search benchmark on Dask (bench/cluster.py): ``--cluster local:N``, a scheduler and workers
started by hand (``tcp://``), the SLURM job script, and the faults: a worker killed mid-run, a
worker that cannot import the project, a unit that raises, Ctrl-C and ``--resume``.

Every scheduler and worker binds to 127.0.0.1, with no dashboard. Episodes are cut to a few steps on
the kinematic base: what is checked (which units ran, where, and their result lines) does not
depend on their length.
"""

from __future__ import annotations

import io
import json
import os
import signal
import subprocess
import sys
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import psutil
import pytest
from distributed import Client
from rich.console import Console

from ovamos.bench import cluster
from ovamos.bench.cluster import ClusterError, check_workers, parse_cluster, slurm_cluster
from ovamos.bench.search import EPISODES_FILE, RUN_FILE, TIMINGS_FILE, SearchError, jsonl_line, main, run_search
from ovamos.shared.procs import stop
from tests.polling import wait_for

pytestmark = pytest.mark.system  # schedulers and worker processes: make test-all

SEED, EPISODES, STEPS = 0, 3, 4
SLOW_STEPS = 500  # the interrupted run's units: the paper's limit, seconds each
POLICIES = ("random", "ovamos")
UNITS = EPISODES * len(POLICIES)
DASK = str(Path(sys.executable).with_name("dask"))
ENV = {**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
WORKER_ENV = {**ENV, **cluster.WORKER_ENV}  # as the docs start a worker


def lines(results) -> list[str]:
    """The result lines, order aside."""
    return sorted(jsonl_line(r) for r in results)


def file_lines(path: Path) -> list[str]:
    return path.read_text().splitlines(keepends=True) if path.exists() else []


def pairs(path: Path) -> list[tuple[str, str]]:
    return [(t["policy"], t["episode_id"]) for t in map(json.loads, file_lines(path))]


def listens_on_loopback_only(*pids: int) -> bool:
    """Every listening socket of these processes is on 127.0.0.1 (Dask's HTTP servers included)."""
    bound = [c.laddr for p in pids for c in psutil.Process(p).net_connections("inet") if c.status == psutil.CONN_LISTEN]
    assert bound and all(address.ip == "127.0.0.1" for address in bound), bound
    return True


@pytest.fixture(scope="module")
def baseline(tmp_path_factory: pytest.TempPathFactory) -> list[str]:
    """The result lines of the process pool (--workers 2); its timing lines name its worker processes."""
    out = tmp_path_factory.mktemp("pool")
    run = run_search(EPISODES, SEED, POLICIES, workers=2, max_steps=STEPS, out=out)
    workers = [t["worker"] for t in map(json.loads, file_lines(out / TIMINGS_FILE))]
    pids = {int(w.rsplit(":", 1)[1]) for w in workers}
    assert len(workers) == UNITS and len(pids) == 2 and os.getpid() not in pids, workers
    return lines(run.results)


@pytest.fixture(scope="module")
def scheduler(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    """``dask scheduler`` on a free port of 127.0.0.1, as its own process: its address."""
    folder = tmp_path_factory.mktemp("scheduler")
    file = folder / "scheduler.json"
    proc = subprocess.Popen([DASK, "scheduler", "--host", "127.0.0.1", "--port", "0", "--no-dashboard",
                             "--dashboard-address", "127.0.0.1:0", "--scheduler-file", str(file)], cwd=folder, start_new_session=True,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        wait_for(lambda: file.exists() and file.stat().st_size > 0 and json.loads(file.read_text()).get("address"),
                 timeout=60, what="the dask scheduler's file")
        address = json.loads(file.read_text())["address"]
        assert address.startswith("tcp://127.0.0.1:") and listens_on_loopback_only(proc.pid)
        yield address
    finally:
        stop(proc)


@pytest.fixture
def dask_client(scheduler: str) -> Iterator[Client]:
    client = Client(scheduler, timeout=30)
    try:
        yield client
    finally:
        client.close()


@pytest.fixture
def start_worker(scheduler: str, dask_client: Client, tmp_path: Path) -> Iterator[Callable[..., tuple[str, int]]]:
    """Start ``dask worker`` processes on 127.0.0.1 (no nanny: the worker is the process; one
    thread); each returns (its address, its pid) once the scheduler has it. All stopped after, and
    gone from the scheduler before the next test."""
    started: list[subprocess.Popen] = []

    def start(*extra: str) -> tuple[str, int]:
        name = f"test-worker-{len(started)}"
        proc = subprocess.Popen([DASK, "worker", scheduler, "--host", "127.0.0.1", "--nthreads", "1",
                                 "--no-nanny", "--no-dashboard", "--dashboard-address", "127.0.0.1:0", "--name", name, "--local-directory",
                                 str(tmp_path / name), *extra], cwd=tmp_path, env=WORKER_ENV,
                                start_new_session=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        started.append(proc)

        def joined() -> str | None:
            assert proc.poll() is None, "the dask worker exited"
            info = dask_client.scheduler_info(n_workers=-1)["workers"]
            return next((a for a in info if info[a].get("name") == name), None)
        address = str(wait_for(joined, timeout=60, what="a dask worker to join"))
        assert address.startswith("tcp://127.0.0.1:") and listens_on_loopback_only(proc.pid)
        return address, proc.pid

    try:
        yield start
    finally:
        for proc in started:
            stop(proc)
        wait_for(lambda: not dask_client.scheduler_info(n_workers=-1)["workers"], timeout=30, what="the workers to leave")


# -- engines --------------------------------------------------------------------------------------
def test_a_local_cluster_writes_the_result_lines_of_the_process_pool(baseline: list[str], tmp_path: Path) -> None:
    run = run_search(EPISODES, SEED, POLICIES, max_steps=STEPS, cluster="local:2", out=tmp_path)
    assert lines(run.results) == baseline and not run.failed
    assert sorted(file_lines(tmp_path / EPISODES_FILE)) == baseline  # appended as they came
    workers = {t["worker"] for t in map(json.loads, file_lines(tmp_path / TIMINGS_FILE))}
    assert len(pairs(tmp_path / TIMINGS_FILE)) == UNITS
    assert workers and all(w.startswith("tcp://127.0.0.1:") for w in workers), workers
    assert run.engine == "Dask local cluster, 2 workers"


def test_a_scheduler_and_workers_started_by_hand_run_the_benchmark(baseline: list[str], scheduler: str,
                                                                    start_worker, tmp_path: Path) -> None:
    started = {start_worker()[0], start_worker()[0]}
    run = run_search(EPISODES, SEED, POLICIES, max_steps=STEPS, cluster=scheduler, out=tmp_path)
    assert lines(run.results) == baseline and not run.failed
    ran = [t["worker"] for t in map(json.loads, file_lines(tmp_path / TIMINGS_FILE))]
    assert len(ran) == UNITS and set(ran) <= started


# -- faults ---------------------------------------------------------------------------------------
def test_a_worker_killed_mid_run_has_its_unit_run_elsewhere_once(baseline: list[str], scheduler: str,
                                                                  dask_client: Client, start_worker,
                                                                  tmp_path: Path) -> None:
    pids = dict([start_worker(), start_worker()])
    timings = tmp_path / TIMINGS_FILE
    with ThreadPoolExecutor(1) as pool:
        running = pool.submit(run_search, EPISODES, SEED, POLICIES, max_steps=STEPS, cluster=scheduler,
                              out=tmp_path)
        wait_for(lambda: file_lines(timings) or running.done(), timeout=120, what="the first result")
        # a worker with a unit in hand, killed before it can report it
        busy = wait_for(lambda: next((w for w, keys in dask_client.processing().items() if keys and w in pids), None)
                        or running.done(), timeout=30, what="a busy worker")
        assert not running.done(), "the run ended before a worker could be killed"
        done_at_kill = len(file_lines(timings))
        os.kill(pids[str(busy)], signal.SIGKILL)
        run = running.result(timeout=150)
    assert done_at_kill < UNITS and not run.failed
    assert lines(run.results) == baseline
    assert sorted(pairs(timings)) == sorted(set(pairs(timings))) and len(pairs(timings)) == UNITS
    assert sorted(file_lines(tmp_path / EPISODES_FILE)) == baseline


def test_a_worker_that_cannot_import_the_project_is_named(scheduler: str, dask_client: Client, start_worker,
                                                          tmp_path: Path) -> None:
    hide = tmp_path / "hide_ovamos.py"  # the worker's process as if ovamos were not installed there
    hide.write_text("import sys\nsys.modules['ovamos'] = None\n")
    good, _ = start_worker()
    bad, _ = start_worker("--preload", str(hide))
    with pytest.raises(ClusterError) as error:
        check_workers(dask_client)
    assert bad in str(error.value) and good not in str(error.value) and "ovamos" in str(error.value)
    with pytest.raises(SearchError, match=f"{bad}: ModuleNotFoundError"):
        run_search(1, SEED, ("random",), max_steps=STEPS, cluster=scheduler, out=tmp_path / "run")
    assert not file_lines(tmp_path / "run" / EPISODES_FILE)  # refused before any unit ran


def test_a_unit_that_raises_is_listed_and_rerun_by_resume(baseline: list[str], scheduler: str,
                                                          dask_client: Client, start_worker, tmp_path: Path,
                                                          capsys: pytest.CaptureFixture[str]) -> None:
    """The one monkeypatch here: no valid input makes an episode raise, so each worker's
    ``run_job`` is wrapped to raise for (random, 0-1) while the run goes on."""
    start_worker(), start_worker()

    def break_one() -> None:
        import ovamos.bench.jobs as jobs
        real = jobs.run_job

        def run_job(job):
            if (job.policy, job.index) == ("random", 1):
                raise RuntimeError("the simulator crashed")
            return real(job)
        jobs.real_run_job, jobs.run_job = real, run_job

    def mend() -> None:
        import ovamos.bench.jobs as jobs
        jobs.run_job = jobs.real_run_job

    dask_client.run(break_one)
    err = io.StringIO()
    code = main(episodes=EPISODES, seed=SEED, policies=",".join(POLICIES), max_steps=STEPS, out=tmp_path,
                cluster=scheduler, as_json=True, err=Console(file=err, width=300))
    assert code == 1
    assert "1 episode(s) failed" in err.getvalue()
    assert "random 0-1: RuntimeError: the simulator crashed" in err.getvalue()
    result = json.loads(capsys.readouterr().out)
    assert result["failed"] == ["episode random 0-1: RuntimeError: the simulator crashed"]
    assert result["policies"]["random"]["episodes"] == EPISODES - 1
    assert len(file_lines(tmp_path / EPISODES_FILE)) == UNITS - 1
    dask_client.run(mend)
    again = run_search(EPISODES, SEED, POLICIES, max_steps=STEPS, cluster=scheduler, out=tmp_path, resume=True)
    assert again.resumed == UNITS - 1 and not again.failed
    assert lines(again.results) == baseline
    assert sorted(pairs(tmp_path / TIMINGS_FILE)) == sorted({(p, f"{SEED}-{i}") for p in POLICIES
                                                             for i in range(EPISODES)})


def _interruptible() -> None:
    """In the child: SIGINT as a terminal's foreground command has it. A shell without job control
    starts a background command (``make test-all &``) with SIGINT ignored, its children inherit
    that, and a command started so rightly stays deaf to Ctrl-C."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def test_ctrl_c_on_a_local_cluster_keeps_what_finished_and_resume_completes_it(tmp_path: Path) -> None:
    """Units of ``SLOW_STEPS`` steps (seconds each): the run cannot finish between its first result
    and the Ctrl-C (at ``STEPS`` the six units took well under a second)."""
    episodes = tmp_path / EPISODES_FILE
    proc = subprocess.Popen([sys.executable, "-m", "ovamos.cli", "bench", "search", "--episodes", str(EPISODES),
                             "--seed", str(SEED), "--policies", ",".join(POLICIES), "--max-steps", str(SLOW_STEPS),
                             "--cluster", "local:1", "--out", str(tmp_path)], env=ENV, start_new_session=True,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, preexec_fn=_interruptible)
    try:
        wait_for(lambda: file_lines(episodes) or proc.poll() is not None, timeout=120, what="the first result")
        workers = psutil.Process(proc.pid).children(recursive=True)
        assert listens_on_loopback_only(proc.pid, *(w.pid for w in workers))
        os.killpg(proc.pid, signal.SIGINT)  # Ctrl-C as a terminal sends it: to the driver and its workers
        proc.wait(60)
    finally:
        stop(proc)
        stderr = proc.stderr.read() if proc.stderr else ""
    kept = file_lines(episodes)
    assert workers and 1 <= len(kept) < UNITS, stderr
    assert f"interrupted: {len(kept)} episodes are in" in " ".join(stderr.split()) and "Traceback" not in stderr
    assert all(line.endswith("\n") for line in kept)
    wait_for(lambda: not any(w.is_running() and w.status() != psutil.STATUS_ZOMBIE for w in workers),
             timeout=30, what="the local cluster's workers to exit")
    # finished on another engine: the runner in this process (--workers 1)
    run = run_search(EPISODES, SEED, POLICIES, workers=1, max_steps=SLOW_STEPS, out=tmp_path, resume=True)
    assert run.resumed == len(kept) and len(run.results) == UNITS and set(kept) <= set(lines(run.results))
    assert len(pairs(tmp_path / TIMINGS_FILE)) == UNITS == len(set(pairs(tmp_path / TIMINGS_FILE)))
    assert json.loads((tmp_path / RUN_FILE).read_text())["seed"] == SEED


# -- SLURM and the arguments ----------------------------------------------------------------------
SLURM_TOML = """\
[slurm]
scheduler_host = "127.0.0.1"
queue = "cpu"
account = "robots"
cores = 32
memory = "64GB"
walltime = "04:00:00"
jobs = 4
python = "/opt/ovamos/.venv/bin/python"
job_script_prologue = ["source /opt/ovamos/.venv/bin/activate"]
"""


def test_the_slurm_job_script_carries_the_config(tmp_path: Path) -> None:
    config = tmp_path / "slurm.toml"
    config.write_text(SLURM_TOML)
    spec = parse_cluster("slurm", config)
    assert spec.slurm is not None and spec.slurm.jobs == 4
    cluster = slurm_cluster(spec.slurm)
    try:
        script = cluster.job_script()
        assert cluster.scheduler_address.startswith("tcp://127.0.0.1:")
    finally:
        cluster.close()
    directives = [line for line in script.splitlines() if line.startswith("#SBATCH")]
    for expected in ("#SBATCH -p cpu", "#SBATCH -A robots", "#SBATCH -n 1", "#SBATCH --cpus-per-task=32",
                     "#SBATCH --mem=60G", "#SBATCH -t 04:00:00"):
        assert expected in directives, script
    assert "source /opt/ovamos/.venv/bin/activate" in script and "export MUJOCO_GL=" in script
    assert """export DASK_DISTRIBUTED__NANNY__PRE_SPAWN_ENVIRON='{"MALLOC_TRIM_THRESHOLD_": None,""" in script
    worker = next(line for line in script.splitlines() if "dask_worker" in line or "dask worker" in line)
    assert worker.startswith("/opt/ovamos/.venv/bin/python") and cluster.scheduler_address in worker
    for option in ("--nthreads 1", "--nworkers 32", "--no-dashboard"):
        assert option in worker, worker


@pytest.mark.parametrize(("change", "message"), [
    ("cores = 0", "cores: Input should be greater than or equal to 1"),
    ('walltime = "four hours"', "walltime: String should match pattern"),
    ('memory = "lots"', "memory: String should match pattern"),
    ("nodes = 4", "nodes: Extra inputs are not permitted"),
])
def test_a_bad_slurm_config_names_the_setting(tmp_path: Path, change: str, message: str) -> None:
    key = change.split(" =")[0]
    text = "".join(line + "\n" for line in SLURM_TOML.splitlines() if not line.startswith(f"{key} ="))
    config = tmp_path / "slurm.toml"
    config.write_text(text + change + "\n")
    with pytest.raises(ClusterError, match=f"{config}: bad \\[slurm\\] settings: .*{message}"):
        parse_cluster("slurm", config)


@pytest.mark.parametrize(("value", "message"), [
    ("locl", "unknown --cluster 'locl': one of local, local:N, tcp://HOST:PORT or slurm"),
    ("local:0", "the worker count must be a whole number >= 1"),
    ("local:two", "the worker count must be a whole number >= 1"),
    ("tcp://127.0.0.1", "a scheduler address is tcp://HOST:PORT"),
    ("slurm", "--cluster slurm needs --cluster-config FILE.toml"),
])
def test_a_bad_cluster_value_is_refused_with_what_is_accepted(value: str, message: str) -> None:
    with pytest.raises(SearchError, match=message.replace("(", r"\(").replace("+", r"\+")):
        run_search(1, SEED, ("random",), max_steps=STEPS, cluster=value)


def test_the_command_refuses_a_bad_cluster_and_nothing_but_the_cluster_module_imports_dask() -> None:
    done = subprocess.run([sys.executable, "-m", "ovamos.cli", "bench", "search", "--cluster", "tcp://nowhere"],
                          capture_output=True, text=True, timeout=120, env=ENV)
    assert done.returncode == 2 and "tcp://HOST:PORT" in " ".join(done.stderr.split())
    probe = ("import sys, ovamos.cli, ovamos.bench.search, ovamos.bench.jobs, ovamos.bench.cluster; "
             "print(sorted(m for m in sys.modules if m.split('.')[0] in ('dask', 'distributed', 'dask_jobqueue')))")
    imported = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=120, env=ENV)
    assert imported.returncode == 0 and imported.stdout.strip() == "[]", imported.stderr
