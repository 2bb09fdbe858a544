"""Polling helpers for tests: wait for a condition, a port, or what `ovamos status` reports.

Kept out of conftest.py so helper modules can import them (pytest loads conftest under its own
module name, and importing it again from a helper would load a second copy).
"""

from __future__ import annotations

import json
import socket
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import pytest

from ovamos.shared.procs import loopback


def wait_for(predicate: Callable[[], object], timeout: float = 20.0, what: str | Callable[[], str] = "condition",
             interval: float = 0.1) -> object:
    """Poll every ``interval`` s until ``predicate()`` is truthy; fail the test with ``what`` after
    ``timeout`` (a callable: asked then, so the message can say what was still missing)."""
    deadline = time.monotonic() + timeout
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() > deadline:
            pytest.fail(f"timed out after {timeout} s waiting for {what() if callable(what) else what}")
        time.sleep(interval)


def port_open(port: int) -> bool:
    with socket.socket() as s:
        return s.connect_ex(("127.0.0.1", port)) == 0


def ovamos_unwrapped(*args: str, timeout: float = 60) -> subprocess.CompletedProcess:
    """Run the CLI from the repo's root; its output with rich's line wrapping undone (one space
    between words), so a test can look for a whole message."""
    done = subprocess.run([sys.executable, "-m", "ovamos.cli", *args], capture_output=True, text=True,
                          timeout=timeout, cwd=Path(__file__).resolve().parents[1])
    done.stdout, done.stderr = " ".join(done.stdout.split()), " ".join(done.stderr.split())
    return done


def status_cli(port: int, robot_id: str = "*") -> list[dict]:
    """What ``ovamos status --json`` prints, parsed."""
    out = subprocess.run([sys.executable, "-m", "ovamos.cli", "status", "--json",
                          "--connect", loopback(port), "--robot-id", robot_id, "--timeout", "1"],
                         capture_output=True, text=True, timeout=60, check=True)
    return json.loads(out.stdout)
