"""Robots' identities in the access control, through real routers with real certificates: a fleet
robot's certificate (CN ``robot-<id>``) is bound to its own keys on the laptop's router, so one
robot's key can neither publish another robot's odometry nor read its commands.

Every link here is on 127.0.0.1 (the laptop's router, a robot's router linked to it over mTLS, and
a client of each), so no second host is needed; the operator's role (engaging the e-stop but not
clearing it) is checked over two hosts in tests/test_netns_link.py.
"""

from __future__ import annotations

import json
import subprocess
import sys
import threading
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
import zenoh

from ovamos.shared.bus.acl import AclConfigError, bind_robots, robot_common_names
from ovamos.shared.bus.zconfig import build_config
from ovamos.shared.certs import init_ca, issue
from ovamos.shared.procs import free_port, loopback
from tests.polling import port_open, wait_for

pytestmark = [pytest.mark.system, pytest.mark.serial]  # real-time devices, rates or deadlines: run alone, after the parallel tests (make test-all)

REPO = Path(__file__).resolve().parents[1]
ZENOH = REPO / "deploy" / "zenoh"
PROBE = REPO / "tests" / "netns_probe.py"
FLEET = ("r1", "r2")
SENTINEL = b"sentinel"  # put last, on a key every setup lets through


@pytest.fixture(scope="module")
def certs(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("acl") / "certs"
    init_ca(folder)
    issue(folder, "laptop", hosts=["127.0.0.1"])
    for name in ("robot", "robot-r1", "robot-r2"):
        issue(folder, name)
    return folder


def _laptop_acl() -> dict:
    cfg = build_config("router", file=ZENOH / "laptop-router-secure.json5", require_certs=False)
    return json.loads(cfg.get_json("access_control"))


def test_each_robot_gets_a_subject_of_its_own_bound_to_its_keys() -> None:
    acl = bind_robots(_laptop_acl(), FLEET)
    subjects = {s["id"]: s for s in acl["subjects"]}
    assert "robot" not in subjects
    assert subjects["robot-r1"]["cert_common_names"] == ["robot-r1"]
    assert subjects["robot-r2"]["cert_common_names"] == ["robot-r2"]
    rules = {r["id"]: r for r in acl["rules"]}
    # what r1 publishes, and what it is sent, name r1's keys only
    assert rules["robot-data-in/ingress/own/r1"]["key_exprs"] == [
        "ovamos/r1/sensors/rgbd", "ovamos/r1/odom", "ovamos/r1/driver/state", "ovamos/r1/camera/state"]
    assert "ovamos/r1/driver/estop/clear" in rules["commands-out/egress/own/r1"]["key_exprs"]
    assert all(k.startswith("ovamos/r1/") for k in rules["commands-subscribed/ingress/own/r1"]["key_exprs"])
    # the laptop's own interest keeps its wildcards (`ovamos status`, a perception serving every robot)
    assert rules["robot-data-subscribed/egress/any/r1"]["key_exprs"][0] == "ovamos/*/sensors/rgbd"
    policy = next(p for p in acl["policies"] if p["subjects"] == ["robot-r2"])
    assert all(r.endswith("/r2") for r in policy["rules"])
    # the one robot of a single-robot deployment keeps the CN its certificates always had
    assert robot_common_names("robot1", only=True) == ["robot-robot1", "robot"]
    single = {s["id"]: s for s in bind_robots(_laptop_acl(), ["robot1"])["subjects"]}
    assert single["robot-robot1"]["cert_common_names"] == ["robot-robot1", "robot"]


def test_certs_issue_makes_a_fleet_robots_certificate(tmp_path: Path) -> None:
    init_ca(tmp_path)
    done = subprocess.run([sys.executable, "-m", "ovamos.cli", "certs", "issue", str(tmp_path), "robot-r2"],
                          capture_output=True, text=True, timeout=60, cwd=REPO)
    assert done.returncode == 0, done.stderr
    assert "CN robot-r2" in " ".join(done.stdout.split())


def test_a_robot_rule_that_is_not_per_robot_is_refused() -> None:
    acl = _laptop_acl()
    next(r for r in acl["rules"] if r["id"] == "robot-data-in")["key_exprs"].append("**")
    with pytest.raises(AclConfigError, match=r"rule 'robot-data-in' of subject 'robot' names \*\*"):
        bind_robots(acl, FLEET)
    with pytest.raises(AclConfigError, match="needs the robots it stands for"):
        bind_robots(_laptop_acl(), [])


def test_configs_without_a_robot_subject_are_left_as_they_are() -> None:
    for name in ("router.json5", "robot-router-secure.json5"):
        acl = json.loads(build_config("router", file=ZENOH / name, require_certs=False).get_json("access_control"))
        assert bind_robots(acl, FLEET) is acl, name


class Link:
    """The laptop's router and robot r1's, linked over mTLS, with a client of each."""

    def __init__(self, root: Path, certs: Path, robot_cert: str, laptop_args: list[str]) -> None:
        root.mkdir()
        self.laptop_log, self.robot_log = root / "laptop-router.log", root / "robot-router.log"
        laptop_port, link_port, robot_port = free_port(), free_port(), free_port()
        self.procs = [
            self._start([sys.executable, str(PROBE), "router", "--config", str(ZENOH / "laptop-router-secure.json5"),
                         "--certs", str(certs), "--cert", "laptop", "--listen", loopback(laptop_port),
                         "--listen", f"tls/127.0.0.1:{link_port}", *laptop_args], self.laptop_log),
            self._start([sys.executable, "-m", "ovamos.cli", "router", "--config",
                         str(ZENOH / "robot-router-secure.json5"), "--certs", str(certs), "--cert", robot_cert,
                         "--robot-id", "r1", "--listen", loopback(robot_port),
                         "--connect", f"tls/127.0.0.1:{link_port}"], self.robot_log)]
        for port in (laptop_port, robot_port):
            wait_for(lambda port=port: port_open(port), 20, f"a router on port {port}")
        self.laptop = zenoh.open(build_config("client", connect=[loopback(laptop_port)]))
        self.robot = zenoh.open(build_config("client", connect=[loopback(robot_port)]))
        self._lock = threading.Lock()
        self.on_laptop: list[str] = []
        self.sentinels: set[str] = set()  # keys a sentinel arrived on
        self.on_robot: list[str] = []
        self._subs = [self.laptop.declare_subscriber("ovamos/*/odom", lambda s: self._got(self.on_laptop, s))]
        self._subs += [self.robot.declare_subscriber(f"ovamos/{robot}/plan/command",
                                                     lambda s: self._got(self.on_robot, s)) for robot in FLEET]

    @staticmethod
    def _start(argv: list[str], log: Path) -> subprocess.Popen:
        return subprocess.Popen(argv, stdout=log.open("wb"), stderr=subprocess.STDOUT, cwd=REPO)

    def _got(self, into: list[str], sample: zenoh.Sample) -> None:
        with self._lock:
            into.append(str(sample.key_expr))
            if sample.payload.to_bytes() == SENTINEL:
                self.sentinels.add(str(sample.key_expr))

    def exchange(self) -> tuple[set[str], set[str]]:
        """Once r1's odometry reaches the laptop (the link is up): r1's router publishes r1's and r2's
        odometry, the laptop commands both robots; the keys each side received."""
        def linked() -> bool:
            self.robot.put("ovamos/r1/odom", b"{}")
            return bool(self.on_laptop)
        wait_for(linked, 30, "r1's odometry on the laptop (the TLS link up)", interval=0.2)
        for robot in FLEET:
            self.robot.put(f"ovamos/{robot}/odom", b"{}")
            self.laptop.put(f"ovamos/{robot}/plan/command", b"{}")
        # sentinels on keys every setup lets through, put last: once both are in, whatever was put
        # before them on the same sessions and link has come, or was refused
        self.robot.put("ovamos/r1/odom", SENTINEL)
        self.laptop.put("ovamos/r1/plan/command", SENTINEL)
        wait_for(lambda: self.sentinels == {"ovamos/r1/odom", "ovamos/r1/plan/command"}, 20,
                 "the sentinels through the link")
        with self._lock:
            return set(self.on_laptop), set(self.on_robot)

    def close(self) -> None:
        for session in (self.laptop, self.robot):
            session.close()
        for proc in self.procs:
            proc.terminate()
        for proc in self.procs:
            try:
                proc.wait(10)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()


@pytest.fixture
def link(tmp_path: Path, certs: Path) -> Iterator[Callable[[str, list[str]], Link]]:
    made: list[Link] = []

    def make(robot_cert: str, laptop_args: list[str]) -> Link:
        made.append(Link(tmp_path / str(len(made)), certs, robot_cert, laptop_args))
        return made[-1]
    try:
        yield make
    finally:
        for each in made:
            each.close()


def test_a_fleet_robots_key_reaches_only_its_own_keys_through_the_secure_routers(
        link: Callable[[str, list[str]], Link]) -> None:
    # as it was: every robot's certificate had CN "robot", matched on any robot's keys
    before = link("robot", ["--unchecked"])
    on_laptop, on_robot = before.exchange()
    assert on_laptop == {"ovamos/r1/odom", "ovamos/r2/odom"}, "the fault is not reproduced"
    assert on_robot == {"ovamos/r1/plan/command", "ovamos/r2/plan/command"}
    # each robot its own certificate, bound by the laptop's router to its own keys
    after = link("robot-r1", ["--robot", "r1", "--robot", "r2"])
    on_laptop, on_robot = after.exchange()
    assert on_laptop == {"ovamos/r1/odom"}, "r1's key published r2's odometry"
    assert on_robot == {"ovamos/r1/plan/command"}, "r1's key read r2's commands"
    log = after.laptop_log.read_text()
    assert "access control denied Put (ingress) on ovamos/r2/odom from CN robot-r1" in log
    assert "(egress) on ovamos/r2/plan/command to CN robot-r1" in log
