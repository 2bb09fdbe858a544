"""Starting and stopping ``ovamos`` processes (used by the demo, tests and benchmarks).

Children are fresh interpreters (never forked: a fork after a Zenoh session was
opened hangs the child's ``zenoh.open()``), each in its own process group, so
stopping one also stops anything it started.

A child in its own session gets none of its parent's signals, so the parent must
end it, and Python's default SIGTERM (and SIGHUP) action kills the interpreter
without running ``finally`` blocks or ``__exit__``: SIGTERM from systemd or
``timeout`` would leave every child running. While a command has children,
:func:`signals_unwind` turns those signals into an exception in the main thread
(:class:`Terminated`; SIGINT stays :class:`KeyboardInterrupt`), so the code that
stops the children runs; :func:`deferred_signals` holds them back while a child is
being started or stopped, so that neither is cut in half. A parent that is
SIGKILLed runs no clean-up at all: on Linux its children are asked to get SIGTERM
from the kernel when it dies (``PR_SET_PDEATHSIG``, :func:`die_with_parent`).
"""

from __future__ import annotations

import ctypes
import logging
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from types import FrameType, TracebackType
from typing import IO, Any

log = logging.getLogger("ovamos.procs")


def free_port() -> int:
    """A TCP port on 127.0.0.1 that nothing listens on right now."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def loopback(port: int) -> str:
    return f"tcp/127.0.0.1:{port}"


# -- the parent's death ---------------------------------------------------------------------
_PR_SET_PDEATHSIG = 1


def _load_prctl() -> Callable[..., int] | None:
    if not sys.platform.startswith("linux"):
        return None
    try:
        return ctypes.CDLL(None, use_errno=True).prctl
    except (OSError, AttributeError):
        return None


_prctl = _load_prctl()  # resolved here: a child between fork and exec must not load libraries


def die_with_parent(parent_pid: int, sig: int = signal.SIGTERM) -> bool:
    """Have the kernel send ``sig`` to this process when its parent ends, even by SIGKILL; if
    ``parent_pid`` is already gone (this process was adopted), send it now. Linux only (False
    elsewhere).

    The kernel's "parent" is the *thread* that started this process: started from a thread
    that ends before the process should, a child would get ``sig`` then.
    """
    if _prctl is None or _prctl(_PR_SET_PDEATHSIG, int(sig), 0, 0, 0) != 0:
        return False
    if os.getppid() != parent_pid:
        os.kill(os.getpid(), sig)
    return True


def run_dying_with_parent(parent_pid: int, target: Callable[..., object], *args: Any) -> None:
    """A ``multiprocessing`` target: :func:`die_with_parent` (``parent_pid``: the starter's
    ``os.getpid()``), then ``target(*args)``. Start the process from the main thread."""
    die_with_parent(parent_pid)
    target(*args)


def start_cli(args: Sequence[str], *, stdout: IO | int | None = None,
              stderr: IO | int | None = None, die_with_parent: bool | None = None) -> subprocess.Popen:
    """Start ``ovamos ARGS...`` with this interpreter in a new process group (and session).

    ``die_with_parent`` (Linux): the child gets SIGTERM when the thread calling this ends, as
    when this process is SIGKILLed. By default only when called from the main thread, which
    lives as long as the process; pass True from a thread that outlives the child.
    """
    if die_with_parent is None:
        die_with_parent = threading.current_thread() is threading.main_thread()
    preexec = None
    if die_with_parent and _prctl is not None:
        parent, prctl = os.getpid(), _prctl

        def preexec() -> None:  # in the child before exec: nothing that takes a lock
            prctl(_PR_SET_PDEATHSIG, int(signal.SIGTERM), 0, 0, 0)
            if os.getppid() != parent:
                os._exit(128 + signal.SIGTERM)

    return subprocess.Popen([sys.executable, "-m", "ovamos.cli", *args], stdout=stdout,
                            stderr=stderr, start_new_session=True, preexec_fn=preexec)


# -- stopping -------------------------------------------------------------------------------
def stop(proc: subprocess.Popen, timeout: float = 5.0) -> int:
    """SIGTERM the process group, SIGKILL it if it has not exited after ``timeout``.

    What the child left running in its group (a process it started that does not exit with
    it) gets the rest of ``timeout`` after the child's exit, then SIGKILL.
    """
    deadline = time.monotonic() + timeout
    if proc.poll() is None:
        _signal_group(proc, signal.SIGTERM)
        try:
            proc.wait(timeout)
        except subprocess.TimeoutExpired:
            _signal_group(proc, signal.SIGKILL)
            proc.wait()
    if group_members(proc.pid):  # they exist: the group id is still theirs, not reused
        _signal_group(proc, signal.SIGTERM)
        while group_members(proc.pid) and time.monotonic() < deadline:
            time.sleep(0.05)
        if group_members(proc.pid):
            _signal_group(proc, signal.SIGKILL)
    return proc.returncode


def kill(proc: subprocess.Popen) -> None:
    """SIGKILL, as a crash would: no clean-up runs in the child."""
    _signal_group(proc, signal.SIGKILL)
    proc.wait()


def stop_spawned(proc: Any, timeout: float = 10.0, term_timeout: float = 5.0) -> int | None:
    """Join a ``multiprocessing`` process that was asked to end; SIGTERM it after ``timeout``,
    SIGKILL after ``term_timeout`` more. Returns its exit code (None: it was never started)."""
    if proc.pid is None:
        return None
    proc.join(timeout)
    if proc.is_alive():
        proc.terminate()
        proc.join(term_timeout)
    if proc.is_alive():
        proc.kill()
        proc.join()
    return proc.exitcode


def group_members(pgid: int) -> list[int]:
    """The live (not zombie) processes of process group ``pgid`` (Linux: from /proc; elsewhere
    ``[pgid]`` while anything of the group exists)."""
    proc = Path("/proc")
    if not (proc / "self" / "stat").exists():
        try:
            os.killpg(pgid, 0)
            return [pgid]
        except (ProcessLookupError, PermissionError):
            return []
    members = []
    for entry in proc.iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
        except OSError:
            continue
        state, _ppid, pgrp = stat[stat.rindex(")") + 2:].split()[:3]
        if int(pgrp) == pgid and state not in "ZX":
            members.append(int(entry.name))
    return members


def _signal_group(proc: subprocess.Popen, sig: int) -> None:
    try:
        os.killpg(proc.pid, sig)
    except ProcessLookupError:
        pass


# -- signals while children run ---------------------------------------------------------------
class Terminated(SystemExit):
    """SIGTERM or SIGHUP arrived while :func:`signals_unwind` was on: unwinding stops the
    children, and when the last scope closes the signal's default action ends the process (so
    its parent sees it killed by the signal, as it asked). Caught and never re-raised, or with
    no scope closing, it exits with 128 + the signal's number, as a shell reports it."""

    def __init__(self, signum: int) -> None:
        super().__init__(128 + signum)
        self.signum = signum

    def __str__(self) -> str:
        return f"terminated by {signal.Signals(self.signum).name}"


#: signals whose default action would end the process without clean-up (SIGINT: Python's own
#: KeyboardInterrupt, taken over only to be deferred like the others)
UNWOUND = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)
_ENDING = (signal.SIGTERM, signal.SIGHUP)

_lock = threading.Lock()
_depth = 0                                    # signals_unwind() scopes open
_saved: dict[int, Any] = {}                   # signals handled by _on_signal -> handler before
_deferring = 0                                # deferred_signals() blocks open in the main thread
_pending: int | None = None                   # the first signal held back by them
_terminated: int | None = None                # the signal a Terminated was raised for


def _raise(signum: int) -> BaseException:
    global _terminated
    if signum == signal.SIGINT:
        return KeyboardInterrupt()
    _terminated = _terminated or signum
    return Terminated(signum)


def _on_signal(signum: int, frame: FrameType | None) -> None:
    global _pending
    if _depth == 0:  # left installed by a scope closed outside the main thread: act as before
        previous = _saved.get(signum, signal.SIG_DFL)
        if callable(previous):
            previous(signum, frame)
        elif previous != signal.SIG_IGN:
            signal.signal(signum, signal.SIG_DFL)
            os.kill(os.getpid(), signum)
        return
    if _deferring:
        _pending = _pending if _pending in _ENDING else signum  # SIGTERM outranks SIGINT
        return
    raise _raise(signum)


def _is_main() -> bool:
    return threading.current_thread() is threading.main_thread()


@contextmanager
def signals_unwind() -> Iterator[None]:
    """While open: SIGTERM / SIGHUP raise :class:`Terminated` in the main thread, SIGINT
    :class:`KeyboardInterrupt`, so ``finally`` and ``__exit__`` stop the children; the handlers
    before come back when the last scope closes (scopes nest, and may close in any order), and
    then, after a Terminated, the signal ends the process.

    Only signals whose handler is the default (SIGINT: Python's) are taken: a program's own
    handler (``ovamos up``'s, the demo's keep-running one, a service's) stays in charge, and a
    handler installed inside the scope is left in place when it closes. Python sets handlers in
    the main thread only: opened elsewhere, this does nothing.
    """
    global _depth, _terminated
    if not _is_main():
        yield
        return
    with _lock:
        if _depth == 0:
            _terminated = None  # one left by a scope closed outside the main thread: not this one's
            for sig in UNWOUND:
                current = signal.getsignal(sig)
                if current is _on_signal:
                    continue  # left from before (see _on_signal): _saved still holds what it replaced
                if current in (signal.SIG_DFL, signal.default_int_handler):
                    _saved[sig] = current
                    signal.signal(sig, _on_signal)
        _depth += 1
    try:
        yield
    finally:
        with _lock:
            _depth -= 1
            last = _depth == 0 and _is_main()
            if last:
                for sig, previous in list(_saved.items()):
                    if signal.getsignal(sig) is _on_signal:
                        signal.signal(sig, previous)
                    del _saved[sig]
        if last:
            _end_if_terminated()


def _end_if_terminated() -> None:
    """After the last scope: a Terminated raised (or a SIGTERM / SIGHUP held back) ends the
    process by that signal's default action, now that what it started is stopped."""
    global _terminated, _pending
    signum = _terminated or (_pending if _pending in _ENDING else None)
    if signum is None:
        return
    _terminated = None
    if _pending == signum:
        _pending = None
    log.warning("%s: what this process started is stopped; ending", signal.Signals(signum).name)
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (AttributeError, OSError, ValueError):
            pass
    signal.signal(signum, signal.SIG_DFL)
    os.kill(os.getpid(), signum)  # ends here; were the signal blocked, the Terminated unwinds on


class deferred_signals:
    """Hold back what :func:`signals_unwind` would raise while a child is started (until its
    handle is stored) or stopped; it is raised when the outermost of these blocks ends.

    A block ending with an exception keeps it if it already unwinds for a signal (Terminated,
    or KeyboardInterrupt when the held signal is SIGINT); otherwise the held signal's exception
    replaces it. No effect outside the main thread (signal handlers run in the main thread only).
    """

    def __enter__(self) -> None:
        global _deferring
        self._main = _is_main()
        if self._main:
            _deferring += 1

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        global _deferring, _pending
        if not self._main:
            return
        _deferring -= 1
        if _deferring or _pending is None:
            return
        signum, _pending = _pending, None
        if isinstance(exc, Terminated) or (signum == signal.SIGINT and isinstance(exc, KeyboardInterrupt)):
            return
        raise _raise(signum) from exc
