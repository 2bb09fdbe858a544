"""Fixtures that start real processes and routers on free loopback ports, and always stop them."""

from __future__ import annotations

import multiprocessing as mp
import subprocess
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
import zenoh

from ovamos.services.gateway.client import GatewayClient
from ovamos.shared.bus.zconfig import build_config, open_session
from ovamos.shared.procs import free_port, loopback, start_cli, stop
from tests.gateway_mocks import MockPlanner, RunningGateway, gateway_config
from tests.polling import port_open, wait_for

StartCli = Callable[..., subprocess.Popen]


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


@pytest.fixture(autouse=True, scope="session")
def _no_children_left() -> Iterator[None]:
    yield
    leftover = mp.active_children()
    for child in leftover:
        child.kill()
    assert not leftover, f"processes left behind: {leftover}"


# -- the gateway (tests/test_gateway_*.py) ---------------------------------------------------------
@pytest.fixture
def planner(inproc_router: str) -> Iterator[MockPlanner]:
    mock = MockPlanner(inproc_router)
    yield mock
    mock.close()


@pytest.fixture
def gateway(inproc_router: str, tmp_path: Path) -> Iterator[RunningGateway]:
    running = RunningGateway(inproc_router, gateway_config(tmp_path / "state"))
    yield running
    running.close()


@pytest.fixture
def api(gateway: RunningGateway) -> Iterator[GatewayClient]:
    with GatewayClient(gateway.url) as client:
        yield client
