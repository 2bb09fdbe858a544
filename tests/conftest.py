"""Fixtures that start real processes and routers on free loopback ports, and always stop them."""

from __future__ import annotations

import json
import multiprocessing as mp
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Iterator

import pytest
import zenoh

from shared.procs import free_port, loopback, start_cli, stop
from shared.zconfig import build_config, open_session

StartCli = Callable[..., subprocess.Popen]


def wait_for(predicate: Callable[[], object], timeout: float = 20.0, what: str = "condition"
             ) -> object:
    """Poll until ``predicate()`` is truthy; fail the test with ``what`` after ``timeout``."""
    deadline = time.monotonic() + timeout
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() > deadline:
            pytest.fail(f"timed out after {timeout} s waiting for {what}")
        time.sleep(0.1)


def port_open(port: int) -> bool:
    with socket.socket() as s:
        return s.connect_ex(("127.0.0.1", port)) == 0


@pytest.fixture
def cli() -> Iterator[StartCli]:
    """Start ``ovamos ...`` processes; every one is stopped at teardown."""
    started: list[subprocess.Popen] = []

    def start(*args: str) -> subprocess.Popen:
        proc = start_cli(list(args), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        started.append(proc)
        return proc

    yield start
    for proc in started:
        stop(proc)
        if proc.stderr:
            proc.stderr.close()
    assert all(p.poll() is not None for p in started)


@pytest.fixture
def router_port(cli: StartCli) -> int:
    """A router process on a free loopback port."""
    port = free_port()
    cli("router", "--listen", loopback(port), "--log-level", "WARNING")
    wait_for(lambda: port_open(port), what=f"router on port {port}")
    return port


@pytest.fixture
def inproc_router() -> Iterator[str]:
    """A router session inside the test process (fast, for bus-level tests)."""
    endpoint = loopback(free_port())
    session = open_session(build_config("router", listen=[endpoint]))
    yield endpoint
    session.close()


@pytest.fixture
def client(inproc_router: str) -> Iterator[zenoh.Session]:
    session = open_session(build_config(connect=[inproc_router]))
    yield session
    session.close()


def status_cli(port: int, robot_id: str = "*") -> list[dict]:
    """What ``ovamos status --json`` prints, parsed."""
    out = subprocess.run([sys.executable, "-m", "services.cli", "status", "--json",
                          "--connect", loopback(port), "--robot-id", robot_id, "--timeout", "1"],
                         capture_output=True, text=True, timeout=60, check=True)
    return json.loads(out.stdout)


@pytest.fixture(autouse=True, scope="session")
def _no_children_left() -> Iterator[None]:
    yield
    leftover = mp.active_children()
    for child in leftover:
        child.kill()
    assert not leftover, f"processes left behind: {leftover}"
