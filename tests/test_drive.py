"""``ovamos drive``: one primitive through a running base (the simulated robot's, as processes over
Zenoh), measured by its odometry; refused while a planner drives the robot, or with no base."""

from __future__ import annotations

import re
import subprocess
import sys

import pytest

from ovamos.shared.procs import loopback
from tests.polling import wait_for

pytestmark = pytest.mark.system  # processes and routers: make test-all


def drive(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "ovamos.cli", "drive", *args], capture_output=True, text=True,
                          timeout=120)


def test_one_turn_each_way_is_thirty_degrees_of_odometry_and_a_planner_makes_it_refuse(cli, router_port: int) -> None:
    endpoint = loopback(router_port)
    missing = drive("left", "--robot-id", "r1", "--connect", endpoint, "--timeout", "2")
    assert missing.returncode == 2 and "no base driver answered for r1" in " ".join(missing.stderr.split())
    cli("run", "sim", "--robot-id", "r1", "--connect", endpoint)
    left = drive("left", "--robot-id", "r1", "--connect", endpoint)
    assert left.returncode == 0, left.stderr
    assert re.search(r"TURN_LEFT: done in [\d.]+ s; odometry: 0\.000 m, \+30\.0 deg", left.stdout), left.stdout
    right = drive("right", "--robot-id", "r1", "--connect", endpoint)
    assert right.returncode == 0 and "odometry: 0.000 m, -30.0 deg" in right.stdout, right.stdout + right.stderr
    forward = drive("forward", "--robot-id", "r1", "--connect", endpoint)
    assert forward.returncode == 0 and re.search(r"MOVE_FORWARD: (done|blocked)", forward.stdout), forward.stderr
    assert "0.250 m" in forward.stdout or "blocked" in forward.stdout
    cli("run", "planner", "--robot-id", "r1", "--connect", endpoint)
    refused = wait_for(lambda: (r := drive("left", "--robot-id", "r1", "--connect", endpoint)).returncode == 2 and r,
                       60, "refused once the planner is alive")
    assert "a planner is running for r1" in " ".join(refused.stderr.split())
    assert drive("sideways", "--robot-id", "r1", "--connect", endpoint).returncode == 2
