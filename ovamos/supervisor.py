"""A small process supervisor (behind ``ovamos up PROFILE`` and ``ovamos demo``).

Each service runs as its own ``ovamos`` process (a fresh interpreter, never a
fork: a fork after a Zenoh session was opened hangs the child's
``zenoh.open()``), so one crashing service never takes the others down, and a
crashed one is started again with exponential backoff: quickly after a one-off
crash, slowly for one that keeps failing (a bad config must not spin the CPU).
The supervisor itself opens no Zenoh session.

Routers start first and the services only once a router's port accepts
connections; services would wait for it anyway, but starting them into a
router that never comes up would hide the real problem. Everything stops in
reverse order, so services leave (undeclare their liveliness) while their
router is still there to tell the others.

A child's stdout and stderr go to ``<log dir>/<name>.log`` (appended, one
header line per start): that is where a person reads why something crashed.
A log over ``max_log_bytes`` is rotated when its child (re)starts (``.log.1``
.. ``.log.3``), so a crash loop cannot fill the robot's disk.

No child outlives the supervisor: while it runs, SIGTERM / SIGHUP / SIGINT that
would end the process without clean-up unwind the main thread instead
(:func:`ovamos.shared.procs.signals_unwind`), so ``with Supervisor(...)`` stops every child
on them as on any exception; :meth:`run_forever` has its own handlers (a clean stop).
On Linux each child also gets SIGTERM from the kernel if the supervisor dies
without stopping it (SIGKILL, a crash).

What to run comes from elsewhere: a deployment profile (:mod:`ovamos.profiles`,
``ovamos up``) or the demo (:mod:`ovamos.demo`) hand over a list of :class:`Entry`.
"""

from __future__ import annotations

import logging
import signal
import socket
import subprocess
import threading
import time
from collections.abc import Callable, Sequence
from contextlib import ExitStack
from dataclasses import dataclass
from enum import Enum
from pathlib import Path
from types import TracebackType
from typing import Self

from pydantic import BaseModel, ConfigDict, Field
from rich.table import Table

from ovamos.shared.procs import deferred_signals, signals_unwind, start_cli
from ovamos.shared.procs import stop as stop_process

log = logging.getLogger("ovamos.supervisor")

DEFAULT_LOG_DIR = Path("state/logs")


class SupervisorError(RuntimeError):
    """The supervised system could not be brought up (a router that never opened its port)."""


# -- entries and restart policy -----------------------------------------------------------------
@dataclass(frozen=True)
class Entry:
    """One supervised process: ``ovamos ARGV...`` under a unique name.

    ``ready`` (host, port) marks a router: it starts before every entry without
    one, and those start only once that address accepts TCP connections.
    ``delay_s`` waits this long after the previous entry was scheduled.
    """

    name: str
    argv: tuple[str, ...]
    delay_s: float = 0.0
    ready: tuple[str, int] | None = None


class Backoff(BaseModel):
    """Restart delays: ``initial_s * factor**(n-1)`` for the n-th crash in a row, capped at ``max_s``.

    A child that stayed up ``reset_after_s`` counts as healthy again, so a
    service that crashes once a day restarts at once, not after 30 s.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)
    initial_s: float = Field(default=0.5, gt=0)
    factor: float = Field(default=2.0, ge=1)
    max_s: float = Field(default=30.0, gt=0)
    reset_after_s: float = Field(default=60.0, gt=0)

    def delay(self, failures: int) -> float:
        """Seconds to wait before restarting after the ``failures``-th crash in a row (>= 1)."""
        return min(self.initial_s * self.factor ** max(failures - 1, 0), self.max_s)

    def failures_after(self, failures: int, uptime_s: float) -> int:
        """The crash-in-a-row count after one more crash following ``uptime_s`` of running."""
        return 1 if uptime_s >= self.reset_after_s else failures + 1


def exit_reason(returncode: int) -> str:
    """``exit code 2`` or ``killed by SIGKILL``: what a person needs to tell a bug from an OOM kill."""
    if returncode >= 0:
        return f"exit code {returncode}"
    try:
        return f"killed by {signal.Signals(-returncode).name}"
    except ValueError:
        return f"killed by signal {-returncode}"


def rotate(path: Path, max_bytes: int, keep: int = 3) -> None:
    """Shift ``path`` to ``path.1`` (``.1`` to ``.2``, ... the oldest dropped) once it is over
    ``max_bytes``."""
    if not path.exists() or path.stat().st_size <= max_bytes:
        return
    for i in range(keep - 1, 0, -1):
        older = path.with_name(f"{path.name}.{i}")
        if older.exists():
            older.replace(path.with_name(f"{path.name}.{i + 1}"))
    path.replace(path.with_name(f"{path.name}.1"))


# -- supervisor -----------------------------------------------------------------------------
class State(str, Enum):
    PENDING = "pending"    # not started yet (waits for its start delay)
    RUNNING = "running"
    BACKOFF = "backoff"    # crashed, waits to be restarted
    EXITED = "exited"      # ended with exit code 0: done, not restarted
    STOPPED = "stopped"    # stopped by the supervisor


@dataclass(frozen=True)
class ChildStatus:
    """One row of :meth:`Supervisor.status` (see :func:`status_table`)."""

    name: str
    state: State
    pid: int | None
    restarts: int
    last_exit: str
    uptime_s: float | None
    next_start_in_s: float | None
    log_path: Path
    first_started_at: float | None   # time.monotonic()
    ready_at: float | None           # time.monotonic() a router's port opened


@dataclass(frozen=True)
class RestartEvent:
    """A crash and the restart it scheduled (kept for tests, the demo and the status table)."""

    name: str
    reason: str
    uptime_s: float
    delay_s: float
    at: float                       # time.monotonic()


@dataclass
class _Child:
    entry: Entry
    log_path: Path
    state: State = State.PENDING
    proc: subprocess.Popen | None = None
    restarts: int = 0
    failures: int = 0
    started_at: float = 0.0
    first_started_at: float | None = None
    ready_at: float | None = None
    next_start_at: float = 0.0
    last_exit: str = ""


class Supervisor:
    """Start, watch, restart and stop a set of ``ovamos`` processes.

    Use as a context manager (``with Supervisor(entries) as sup:``), or call
    :meth:`start` / :meth:`stop`; a monitor thread polls the children. From a
    command line, :meth:`run_forever` does the same in the main thread until
    SIGINT / SIGTERM.
    """

    def __init__(self, entries: Sequence[Entry], *, log_dir: Path = DEFAULT_LOG_DIR,
                 backoff: Backoff | None = None, stop_timeout_s: float = 10.0,
                 ready_timeout_s: float = 60.0, poll_s: float = 0.2,
                 max_log_bytes: int = 10_000_000) -> None:
        names = [e.name for e in entries]
        duplicates = sorted({n for n in names if names.count(n) > 1})
        if duplicates:
            raise ValueError(f"entry names must be unique (they name the log files): {duplicates}")
        routers = [e for e in entries if e.ready is not None]
        ordered = routers + [e for e in entries if e.ready is None]
        self.log_dir = Path(log_dir)
        self.backoff = backoff or Backoff()
        self.stop_timeout_s = stop_timeout_s
        self.ready_timeout_s = ready_timeout_s
        self.poll_s = poll_s
        self.max_log_bytes = max_log_bytes
        self.restart_events: list[RestartEvent] = []
        self._children = [_Child(e, self.log_dir / f"{e.name}.log") for e in ordered]
        self._lock = threading.RLock()
        self._stopping = threading.Event()
        self._stopped = threading.Event()   # every child stopped (the monitor thread waits for it)
        self._monitor: threading.Thread | None = None
        self._signals: ExitStack | None = None

    # -- life cycle ---------------------------------------------------------------------------
    def start(self, *, monitor: bool = True) -> None:
        """Start routers and wait for their ports, then schedule the rest; returns once routers are up.

        Raises :class:`SupervisorError` (after stopping what it started) when a
        router exits or does not open its port within ``ready_timeout_s``. From here
        to :meth:`stop`, SIGTERM / SIGHUP / SIGINT left at their default unwind the main
        thread (:func:`~ovamos.shared.procs.signals_unwind`) so that the caller's ``finally`` /
        ``__exit__`` stops the children.
        """
        if self._signals is None:
            self._signals = ExitStack()
            self._signals.enter_context(signals_unwind())
        self.log_dir.mkdir(parents=True, exist_ok=True)
        try:
            for child in self._children:
                if child.entry.ready is not None:
                    self._spawn(child)
                    self._await_ready(child)
            self._schedule_services()
            self.poll()
        except BaseException:
            self.stop()
            raise
        if monitor and not self._stopping.is_set():
            self._monitor = threading.Thread(target=self._monitor_loop, name="supervisor", daemon=True)
            self._monitor.start()

    def poll(self) -> None:
        """One supervision step: notice exits, schedule restarts, start what is due."""
        with self._lock:
            if self._stopping.is_set():
                return
            now = time.monotonic()
            for child in self._children:
                if child.state is State.RUNNING and child.proc is not None and child.proc.poll() is not None:
                    self._on_exit(child, now)
                if child.state in (State.PENDING, State.BACKOFF) and now >= child.next_start_at:
                    self._spawn(child)

    def stop(self) -> None:
        """Stop every child in reverse start order (SIGTERM, SIGKILL after ``stop_timeout_s``).

        A signal arriving meanwhile is held back until every child is stopped.
        """
        with deferred_signals():
            self._stopping.set()
            with self._lock:  # a poll under way finishes first; later ones start nothing
                for child in reversed(self._children):
                    self._terminate(child)
            self._stopped.set()
            if self._monitor is not None and self._monitor is not threading.current_thread():
                self._monitor.join()
            if self._signals is not None:
                self._signals.close()
                self._signals = None

    def request_stop(self) -> None:
        """Ask :meth:`run_forever` (or a pending :meth:`start`) to end; safe from a signal handler."""
        self._stopping.set()

    def run_forever(self, on_started: Callable[[Supervisor], None] | None = None) -> int:
        """Run until SIGINT / SIGTERM (main thread only), then stop everything; returns 0."""
        handlers = {sig: signal.signal(sig, lambda *_: self.request_stop())
                    for sig in (signal.SIGINT, signal.SIGTERM)}
        try:
            self.start(monitor=False)
            if on_started is not None and not self._stopping.is_set():
                on_started(self)
            while not self._stopping.wait(self.poll_s):
                self.poll()
        finally:
            self.stop()
            for sig, handler in handlers.items():
                signal.signal(sig, handler)
        return 0

    def __enter__(self) -> Self:
        self.start()
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.stop()

    # -- views ----------------------------------------------------------------------------------
    def status(self) -> list[ChildStatus]:
        """A consistent snapshot of every child, in start order."""
        with self._lock:
            now = time.monotonic()
            return [_status(c, now) for c in self._children]

    def process(self, name: str) -> subprocess.Popen | None:
        """The current process of child ``name`` (tests and the demo kill it to rehearse a crash)."""
        with self._lock:
            child = self._child(name)
            return child.proc if child.state is State.RUNNING else None

    # -- internals ------------------------------------------------------------------------------
    def _child(self, name: str) -> _Child:
        for child in self._children:
            if child.entry.name == name:
                return child
        raise KeyError(f"no supervised process named {name!r}")

    def _monitor_loop(self) -> None:
        while not self._stopping.wait(self.poll_s):
            try:
                self.poll()
            except Exception:  # a bug here must not leave the children unsupervised silently
                log.exception("supervisor poll failed; retrying")
        # The children this thread (re)started get SIGTERM from the kernel when it ends (see
        # ovamos.shared.procs.start_cli): it ends after stop() stopped them, in order.
        self._stopped.wait()

    def _schedule_services(self) -> None:
        """Non-router entries start from now on, each ``delay_s`` after the one before."""
        at = time.monotonic()
        for child in self._children:
            if child.entry.ready is None:
                at += child.entry.delay_s
                child.next_start_at = at

    def _spawn(self, child: _Child) -> None:
        restart = child.first_started_at is not None
        # The thread that starts a child must outlive it for die_with_parent (the kernel's
        # "parent" is a thread): the main thread does, and the monitor thread (see _monitor_loop).
        thread = threading.current_thread()
        lasting = thread is threading.main_thread() or thread is self._monitor
        with deferred_signals():  # until the child is recorded as running, so stop() stops it
            try:
                rotate(child.log_path, self.max_log_bytes)
                with child.log_path.open("ab") as out:
                    out.write(f"=== {time.strftime('%Y-%m-%d %H:%M:%S')} start: ovamos "
                              f"{' '.join(child.entry.argv)}\n".encode())
                    out.flush()
                    child.proc = start_cli(child.entry.argv, stdout=out, stderr=subprocess.STDOUT,
                                           die_with_parent=lasting)
            except OSError as exc:
                child.proc = None
                self._schedule_restart(child, f"could not start ({exc})", 0.0, time.monotonic())
                return
            now = time.monotonic()
            child.state, child.started_at = State.RUNNING, now
            child.first_started_at = child.first_started_at or now
            child.restarts += restart
        log.info("%s %s (pid %d): ovamos %s; output -> %s", "restarted" if restart else "started",
                 child.entry.name, child.proc.pid, " ".join(child.entry.argv), child.log_path)

    def _await_ready(self, child: _Child) -> None:
        """Block until the router's port accepts connections (or the supervisor is stopped)."""
        assert child.entry.ready is not None and child.proc is not None
        host, port = child.entry.ready
        deadline = time.monotonic() + self.ready_timeout_s
        while not self._stopping.is_set():
            if child.proc.poll() is not None:
                raise SupervisorError(f"{child.entry.name} ended ({exit_reason(child.proc.returncode)}) "
                                      f"before {host}:{port} accepted connections; see {child.log_path}")
            if port_open(host, port):
                child.ready_at = time.monotonic()
                log.info("%s accepts connections on %s:%d", child.entry.name, host, port)
                return
            if time.monotonic() > deadline:
                raise SupervisorError(f"{child.entry.name} did not open {host}:{port} within "
                                      f"{self.ready_timeout_s:.0f} s; see {child.log_path}")
            self._stopping.wait(0.05)

    def _on_exit(self, child: _Child, now: float) -> None:
        assert child.proc is not None
        uptime = now - child.started_at
        reason = exit_reason(child.proc.returncode)
        child.last_exit = reason
        if child.proc.returncode == 0:
            child.state = State.EXITED
            log.info("%s (pid %d) ended normally after %.1f s; not restarted (log: %s)",
                     child.entry.name, child.proc.pid, uptime, child.log_path)
            return
        self._schedule_restart(child, reason, uptime, now)

    def _schedule_restart(self, child: _Child, reason: str, uptime: float, now: float) -> None:
        child.failures = self.backoff.failures_after(child.failures, uptime)
        delay = self.backoff.delay(child.failures)
        child.state, child.next_start_at, child.last_exit = State.BACKOFF, now + delay, reason
        self.restart_events.append(RestartEvent(child.entry.name, reason, uptime, delay, now))
        log.warning("%s %s after %.1f s; restart #%d in %.1f s (see %s)", child.entry.name, reason,
                    uptime, child.restarts + 1, delay, child.log_path)

    def _terminate(self, child: _Child) -> None:
        if child.state is State.RUNNING and child.proc is not None:
            running = child.proc.poll() is None
            returncode = stop_process(child.proc, self.stop_timeout_s)
            child.last_exit = exit_reason(returncode)
            if running:
                log.info("stopped %s (pid %d): %s", child.entry.name, child.proc.pid, child.last_exit)
        if child.state is not State.EXITED:
            child.state = State.STOPPED


def _status(child: _Child, now: float) -> ChildStatus:
    proc = child.proc if child.state is State.RUNNING else None
    waiting = child.state in (State.PENDING, State.BACKOFF)
    return ChildStatus(
        name=child.entry.name, state=child.state, pid=proc.pid if proc is not None else None,
        restarts=child.restarts, last_exit=child.last_exit,
        uptime_s=now - child.started_at if proc is not None else None,
        next_start_in_s=max(child.next_start_at - now, 0.0) if waiting else None,
        log_path=child.log_path, first_started_at=child.first_started_at, ready_at=child.ready_at)


def port_open(host: str, port: int, timeout: float = 0.5) -> bool:
    """Whether ``host:port`` accepts a TCP connection now."""
    try:
        with socket.create_connection((host, port), timeout=timeout):
            return True
    except OSError:
        return False


def status_table(statuses: Sequence[ChildStatus], title: str = "supervised processes") -> Table:
    """The supervisor's view as a rich table (``ovamos up`` prints it; the demo can show it live)."""
    table = Table("name", "state", "pid", "restarts", "up", "last exit", "log", title=title)
    for s in statuses:
        up = f"{s.uptime_s:.0f} s" if s.uptime_s is not None else (
            f"restart in {s.next_start_in_s:.1f} s" if s.state is State.BACKOFF and s.next_start_in_s
            is not None else "-")
        table.add_row(s.name, s.state.value, str(s.pid or "-"), str(s.restarts), up, s.last_exit or "-",
                      str(s.log_path))
    return table
