"""Starting and stopping ``ovamos`` processes (used by the demo, tests and benchmarks).

Children are fresh interpreters (never forked: a fork after a Zenoh session was
opened hangs the child's ``zenoh.open()``), each in its own process group, so
stopping one also stops anything it started.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
from typing import IO
from collections.abc import Sequence


def free_port() -> int:
    """A TCP port on 127.0.0.1 that nothing listens on right now."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def loopback(port: int) -> str:
    return f"tcp/127.0.0.1:{port}"


def start_cli(args: Sequence[str], *, stdout: IO | int | None = None,
              stderr: IO | int | None = None) -> subprocess.Popen:
    """Start ``ovamos ARGS...`` with this interpreter in a new process group."""
    return subprocess.Popen([sys.executable, "-m", "ovamos.cli", *args], stdout=stdout,
                            stderr=stderr, start_new_session=True)


def stop(proc: subprocess.Popen, timeout: float = 5.0) -> int:
    """SIGTERM the process group, SIGKILL it if it has not exited after ``timeout``."""
    if proc.poll() is None:
        _signal_group(proc, signal.SIGTERM)
        try:
            proc.wait(timeout)
        except subprocess.TimeoutExpired:
            _signal_group(proc, signal.SIGKILL)
            proc.wait()
    return proc.returncode


def kill(proc: subprocess.Popen) -> None:
    """SIGKILL, as a crash would: no clean-up runs in the child."""
    _signal_group(proc, signal.SIGKILL)
    proc.wait()


def _signal_group(proc: subprocess.Popen, sig: int) -> None:
    try:
        os.killpg(proc.pid, sig)
    except ProcessLookupError:
        pass
