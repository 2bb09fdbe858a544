"""A secure laptop + robot deployment on two network namespaces: real TCP between two network
stacks, the routers linked over mTLS with access control, and the link failing mid-task.

The laptop namespace runs the laptop profile's router (``laptop-router-secure.json5``) with the
gateway, perception (simulated backend), mapping and the planner; the robot namespace the robot
profile's router (``robot-router-secure.json5``) with the simulated robot driving its simulated
ODrive motor controllers (``motion = "odrive"``: the real base driver over a virtual CAN bus). A
third namespace holds an intruder. Processes in a namespace are reached through
``tests/netns_probe.py`` run inside it; the clocks are the machine's, the same everywhere.

One deployment serves the module (starting it costs ~20 s); the tests run in file order and
each submits its own task. Select them with ``-k netns``; they are skipped, with the reason,
where network namespaces cannot be made (not root, no ``ip``).
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from ovamos.demo import write_configs
from ovamos.services.base_driver.config import DriverConfig
from ovamos.shared.certs import init_ca, issue
from tests.netns import LINKS, Hosts, unavailable_reason
from tests.polling import wait_for

REPO = Path(__file__).resolve().parents[1]
ROBOT = "robot1"
EPISODE = 1          # seed 0: the spray bottle and the countertop are found by about step 25
HTTP_PORT = 8080
LAPTOP_LINK = LINKS["lr"][1]                    # the laptop's TLS listener, as the robot sees it
LAPTOP_FROM_INTRUDER, ROBOT_FROM_INTRUDER = LINKS["il"][3], LINKS["ir"][3]
LINK_PORT, OPERATOR_PORT = 7450, 7451
COMMAND_TIMEOUT_S = 0.5
TASK_TIMEOUT_S = 240.0
#: an interrupted task's budget: it must go on to its end (all found, or this many steps) after the
#: interruption. How long a later task's search takes depends on where the earlier ones left the
#: robot and what its map has decayed (16 to 70 steps here, at ~1.5 s a step); the budget keeps
#: these tests about the link, at ~40 s at most.
INTERRUPTED_STEPS = 25

_reason = unavailable_reason()
pytestmark = [pytest.mark.system, pytest.mark.skipif(_reason is not None, reason=f"no network namespaces here: {_reason}")]


class Lines:
    """A process whose stdout is JSON lines, collected by a thread."""

    def __init__(self, argv: list[str], log: Path) -> None:
        self.items: list[dict[str, Any]] = []
        self._lock = threading.Lock()
        self.proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=log.open("ab"), text=True,
                                     start_new_session=True, cwd=REPO)
        self._thread = threading.Thread(target=self._read, daemon=True)
        self._thread.start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            try:
                item = json.loads(line)
            except ValueError:
                continue
            with self._lock:
                self.items.append(item)

    def snapshot(self, key: str | None = None, since: float = 0.0) -> list[dict[str, Any]]:
        with self._lock:
            return [i for i in self.items if (key is None or i.get("key") == key) and i["t"] >= since]

    def stop(self) -> None:
        _stop_group(self.proc)


def _stop_group(proc: subprocess.Popen, timeout: float = 15.0) -> None:
    if proc.poll() is None:
        try:
            os.killpg(proc.pid, signal.SIGTERM)
            proc.wait(timeout)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
        except ProcessLookupError:
            pass


def _descendants(pid: int) -> list[int]:
    """Every process below ``pid`` (the supervisor's children start their own sessions)."""
    parents: dict[int, list[int]] = {}
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                ppid = int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1])
            except (OSError, IndexError, ValueError):
                continue
            parents.setdefault(ppid, []).append(int(entry.name))
    out, todo = [], [pid]
    while todo:
        for child in parents.get(todo.pop(), []):
            out.append(child)
            todo.append(child)
    return out


def _cmdline(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode()
    except OSError:
        return ""


class Deployment:
    def __init__(self, hosts: Hosts, root: Path) -> None:
        self.hosts, self.root = hosts, root
        self.certs, self.logs = root / "certs", root / "logs"
        self.ups: dict[str, subprocess.Popen] = {}
        self.watchers: dict[str, Lines] = {}

    # -- set-up ----------------------------------------------------------------------------------
    def make_certs(self) -> None:
        init_ca(self.certs)
        issue(self.certs, "laptop", hosts=[LAPTOP_LINK, LAPTOP_FROM_INTRUDER])
        issue(self.certs, "robot", hosts=[ROBOT_FROM_INTRUDER])
        issue(self.certs, "operator")
        issue(self.certs, "intruder")
        other = self.root / "other-ca"
        init_ca(other, common_name="another CA")
        issue(other, "laptop")

    def write_profiles(self) -> None:
        configs = write_configs(self.root / "config", seed=0, episode=EPISODE, robot_id=ROBOT,
                                http_port=HTTP_PORT, base="odrive")
        sim = json.loads(configs["sim"].read_text())
        sim["driver"] = {"command_timeout_s": COMMAND_TIMEOUT_S}  # a lost link stops a primitive
        configs["sim"].write_text(json.dumps(sim))
        zenoh, restart = REPO / "deploy" / "zenoh", "[restart]\ninitial_s = 0.2\nmax_s = 1.0\n"
        laptop = [f'robot_id = "{ROBOT}"', "[router]", f'config = "{zenoh}/laptop-router-secure.json5"',
                  'cert = "laptop"',
                  f'listen = ["tcp/127.0.0.1:7447", "tls/{LAPTOP_LINK}:{LINK_PORT}", '
                  f'"tls/{LAPTOP_FROM_INTRUDER}:{LINK_PORT}"]']
        for name in ("mapping", "perception", "planner", "gateway"):
            laptop += ["[[services]]", f'service = "{name}"', f'config = "{configs[name]}"',
                       f'zenoh = "{zenoh}/service.json5"']
        robot = [f'robot_id = "{ROBOT}"', "[router]", f'config = "{zenoh}/robot-router-secure.json5"',
                 'cert = "robot"',
                 f'listen = ["tcp/127.0.0.1:7448", "tls/{ROBOT_FROM_INTRUDER}:{OPERATOR_PORT}"]',
                 f'connect = ["tls/{LAPTOP_LINK}:{LINK_PORT}"]',
                 "[[services]]", 'service = "sim"', f'config = "{configs["sim"]}"',
                 f'zenoh = "{zenoh}/robot-service.json5"']
        (self.root / "laptop.toml").write_text("\n".join(laptop) + "\n" + restart)
        (self.root / "robot.toml").write_text("\n".join(robot) + "\n" + restart)

    def start(self) -> None:
        for role in ("laptop", "robot"):
            argv = self.hosts.argv(role, [sys.executable, "-m", "ovamos.cli", "up", str(self.root / f"{role}.toml"),
                                          "--certs", str(self.certs), "--log-dir", str(self.logs / role)])
            out = (self.root / f"up-{role}.log").open("ab")
            self.ups[role] = subprocess.Popen(argv, stdout=out, stderr=subprocess.STDOUT, cwd=REPO,
                                              start_new_session=True)
        probe = [sys.executable, str(REPO / "tests" / "netns_probe.py"), "watch", "--robot-id", ROBOT]
        self.watchers["robot"] = Lines(self.hosts.argv("robot", [*probe, "--connect", "tcp/127.0.0.1:7448",
                                                                 "--keys", "odom,driver_state"]),
                                       self.root / "watch-robot.log")
        self.watchers["laptop"] = Lines(self.hosts.argv("laptop", [*probe, "--connect", "tcp/127.0.0.1:7447",
                                                                   "--keys", "task_events,driver_state"]),
                                        self.root / "watch-laptop.log")

    def wait_ready(self) -> None:
        wanted = {"mapping", "perception", "planner", "gateway", "sim"}
        wait_for(lambda: wanted <= {s["service"] for s in self.status("laptop")}, 120,
                   "every service alive, seen from the laptop (the robot's over the TLS link)")
        wait_for(lambda: self.watchers["laptop"].snapshot("driver_state"), 30,
                   "the robot's driver state on the laptop")

    def stop(self) -> None:
        for watcher in self.watchers.values():
            watcher.stop()
        for role in ("robot", "laptop"):
            proc = self.ups.get(role)
            if proc is None:
                continue
            below = _descendants(proc.pid)
            _stop_group(proc, timeout=30)
            for pid in below:  # anything the supervisor could not stop
                try:
                    os.kill(pid, signal.SIGKILL)
                except ProcessLookupError:
                    pass

    # -- tools -----------------------------------------------------------------------------------
    def run_in(self, role: str, argv: list[str], timeout: float = 60) -> subprocess.CompletedProcess:
        return subprocess.run(self.hosts.argv(role, argv), capture_output=True, text=True, timeout=timeout,
                              cwd=REPO)

    def gateway(self, method: str, path: str, body: dict[str, Any] | None = None) -> tuple[int, dict[str, Any]]:
        """An HTTP request to the laptop's gateway, from the laptop: (status, JSON answer)."""
        script = ("import json, sys, urllib.error, urllib.request\n"
                  f"req = urllib.request.Request('http://127.0.0.1:{HTTP_PORT}' + sys.argv[2], method=sys.argv[1], "
                  "data=sys.argv[3].encode() or None, headers={'Content-Type': 'application/json'})\n"
                  "try:\n    r = urllib.request.urlopen(req, timeout=30)\n"
                  "except urllib.error.HTTPError as e:\n    r = e\n"
                  "print(r.status, r.read().decode())\n")
        done = self.run_in("laptop", [sys.executable, "-c", script, method, path, json.dumps(body) if body else ""])
        assert done.returncode == 0, done.stderr
        code, _, text = done.stdout.partition(" ")
        return int(code), json.loads(text)

    def estop_latched(self) -> bool:
        code, state = self.gateway("GET", f"/v1/robots/{ROBOT}")
        assert code == 200, state
        return bool(state["driver"]["estop_latched"])

    def status(self, role: str) -> list[dict[str, Any]]:
        port = 7447 if role == "laptop" else 7448
        done = self.run_in(role, [sys.executable, "-m", "ovamos.cli", "status", "--json", "--connect",
                                  f"tcp/127.0.0.1:{port}", "--robot-id", ROBOT, "--timeout", "1"])
        return json.loads(done.stdout) if done.returncode == 0 and done.stdout.strip() else []

    def submit(self, *targets: str, max_steps: int = 150) -> str:
        done = self.run_in("laptop", [sys.executable, "-m", "ovamos.cli", "submit", *targets, "--gateway",
                                      f"http://127.0.0.1:{HTTP_PORT}", "--robot-id", ROBOT,
                                      "--max-steps", str(max_steps)])
        assert done.returncode == 0, done.stderr
        return done.stdout.split()[1].rstrip(":")

    def events(self, task_id: str, since: float = 0.0) -> list[dict[str, Any]]:
        return [e["msg"] for e in self.watchers["laptop"].snapshot("task_events", since)
                if e["msg"] and e["msg"].get("task_id") == task_id]

    def wait_task(self, task_id: str, timeout: float = TASK_TIMEOUT_S) -> dict[str, Any]:
        def final() -> dict[str, Any] | None:
            done = [e for e in self.events(task_id) if e["status"] in ("done", "failed", "cancelled")]
            return done[-1] if done else None
        return wait_for(final, timeout, f"task {task_id} to end")

    def wait_steps(self, task_id: str, steps: int, timeout: float = 120) -> None:
        wait_for(lambda: any(e["steps"] >= steps for e in self.events(task_id)), timeout, f"{steps} steps")

    def wait_moving(self, timeout: float = 30) -> float:
        """Until the wheels turn (a primitive under way); the odometry's time."""
        def moving() -> float | None:
            last = self.watchers["robot"].snapshot("odom", time.monotonic() - 0.2)
            fast = [o for o in last if abs(o["msg"]["linear"]) > 0.05 or abs(o["msg"]["angular"]) > 0.3]
            return fast[-1]["t"] if fast else None
        return wait_for(moving, timeout, "the wheels turning", interval=0.02)

    def stopped_at(self, since: float, until: float, hold_s: float = 0.25) -> float | None:
        """When the wheels first came to rest after ``since`` (still for ``hold_s``, by the odometry's
        wheel speeds), looked for up to ``until``; None when they never did."""
        odoms = [o for o in self.watchers["robot"].snapshot("odom", since) if o["t"] <= until + hold_s]
        rest = None
        for o in odoms:
            still = abs(o["msg"]["linear"]) < 0.005 and abs(o["msg"]["angular"]) < 0.01
            if not still:
                rest = None
            elif rest is None:
                rest = o["t"] if o["t"] <= until else None
            elif o["t"] - rest >= hold_s:
                return rest
        return None

    def starts(self) -> dict[str, int]:
        """How often each supervised process was started, from its log's headers."""
        counts = {}
        for role in ("laptop", "robot"):
            for log in (self.logs / role).glob("*.log"):
                counts[f"{role}/{log.stem}"] = sum(1 for line in log.read_text(errors="replace").splitlines()
                                                   if line.startswith("=== ") and " start: " in line)
        return counts

    def router_log(self, role: str) -> str:
        return (self.logs / role / "router.log").read_text(errors="replace")


@pytest.fixture(scope="module")
def deployment(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Deployment]:
    root = tmp_path_factory.mktemp("netns")
    hosts = Hosts.create(f"ov{os.getpid() % 1000000}")
    dep = Deployment(hosts, root)
    try:
        dep.make_certs()
        dep.write_profiles()
        dep.start()
        dep.wait_ready()
        yield dep
    finally:
        try:
            dep.stop()
        finally:
            hosts.destroy()


def _ramp(config: DriverConfig) -> float:
    return max(config.max_linear_m_s / config.max_linear_accel_m_s2,
               config.max_angular_rad_s / config.max_angular_accel_rad_s2)


def test_netns_a_whole_task_completes_over_mtls(deployment: Deployment) -> None:
    task = deployment.submit("spray_bottle", "countertop")
    final = deployment.wait_task(task)
    assert final["status"] == "done", final["message"]
    assert sorted(f["label"] for f in final["found"]) == ["countertop", "spray_bottle"]
    # the only way between the hosts is the TLS link: the laptop's router saw the robot's CN on it
    laptop_router = next(s for s in deployment.status("laptop") if s["service"] == "router"
                         and s["instance"] == "laptop")
    assert laptop_router["stats"]["info"]["access_control"]["tls_refused"] == 0
    assert all(n == 1 for n in deployment.starts().values()), deployment.starts()


def _attacks(dep: Deployment, attempts: list[tuple[str, list[str]]]) -> list[dict[str, Any]]:
    """Each (endpoint, credentials) tried by its own intruder process, all at once; what each got."""
    procs = [subprocess.Popen(dep.hosts.argv("intruder", [sys.executable, str(REPO / "tests" / "netns_probe.py"),
                                                           "attack", "--connect", endpoint, "--robot-id", ROBOT,
                                                           *creds]),
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=REPO)
             for endpoint, creds in attempts]
    results = []
    for proc in procs:
        out, err = proc.communicate(timeout=60)
        assert proc.returncode == 0, err[-2000:]
        results.append(json.loads(out.strip().splitlines()[-1]))
    return results


def _commands_received(dep: Deployment) -> tuple[int, int]:
    sim = next(s for s in dep.status("robot") if s["service"] == "sim")
    entry = sim["stats"]["counters"].get(f"ovamos/{ROBOT}/plan/command", {"received": 0})
    return entry["received"], sim["stats"]["info"]["counters"].get("commands", 0)


def test_netns_an_intruder_cannot_make_the_robot_move(deployment: Deployment) -> None:
    """No certificate, another CA's, a valid one of the wrong role, plaintext TCP: the robot's driver
    never sees a command, and the routers log and count what they refused. The operator's
    certificate engages the e-stop but cannot clear it (driver/estop/clear is the laptop's)."""
    dep, certs, other = deployment, deployment.certs, deployment.root / "other-ca"
    code, state = dep.gateway("POST", f"/v1/robots/{ROBOT}/estop", {"reason": "intruder test"})
    assert code == 200 and state["driver"]["estop_latched"], state
    try:
        before = _commands_received(dep)
        robot_tls, laptop_tls = f"tls/{ROBOT_FROM_INTRUDER}:{OPERATOR_PORT}", f"tls/{LAPTOP_FROM_INTRUDER}:{LINK_PORT}"
        ca = ["--ca", str(certs / "ca.pem")]
        forged = [*ca, "--cert", str(other / "laptop.pem"), "--key", str(other / "laptop.key")]
        refused = [(endpoint, creds) for endpoint in (robot_tls, laptop_tls)
                   for creds in (ca, forged)]  # no certificate; another CA's, even with the laptop's CN
        # plaintext TCP to the TLS ports, and to the routers' TCP ports (on loopback only)
        refused += [(endpoint, []) for endpoint in (
            f"tcp/{ROBOT_FROM_INTRUDER}:{OPERATOR_PORT}", f"tcp/{LAPTOP_FROM_INTRUDER}:{LINK_PORT}",
            f"tcp/{ROBOT_FROM_INTRUDER}:7448", f"tcp/{LAPTOP_FROM_INTRUDER}:7447")]
        # valid certificates of the wrong role get a session, and nothing through
        wrong_role = [("intruder", robot_tls), ("intruder", laptop_tls), ("operator", robot_tls), ("robot", laptop_tls)]
        let_in = [(endpoint, [*ca, "--cert", str(certs / f"{name}.pem"), "--key", str(certs / f"{name}.key")])
                  for name, endpoint in wrong_role]
        results = _attacks(dep, refused + let_in)
        for (endpoint, _), got in zip(refused, results):
            assert got["opened"] is False, f"{endpoint}: {got}"
        for (name, endpoint), got in zip(wrong_role, results[len(refused):]):
            assert got["opened"] is True, f"CN {name} at {endpoint}: {got}"
            if name != "robot":
                assert got["frames"] == 0, f"CN {name} read the camera"
        time.sleep(1.0)
        assert _commands_received(dep) == before, "a command reached the driver"
        robot_router = next(s for s in dep.status("robot") if s["service"] == "router")
        denied = robot_router["stats"]["counters"][f"ovamos/{ROBOT}/plan/command"]["denied"]
        assert denied >= 20  # 10 each from CN intruder and CN operator
        log = dep.router_log("robot")
        assert f"Put (ingress) on ovamos/{ROBOT}/plan/command from CN intruder" in log
        assert f"Put (ingress) on ovamos/{ROBOT}/plan/command from CN operator" in log
        assert "access control denied" in dep.router_log("laptop")
        # the operator's clears (driver/estop/clear, and engage=false on driver/estop) left it latched ...
        assert f"Put (ingress) on ovamos/{ROBOT}/driver/estop/clear from CN operator" in log
        assert dep.estop_latched(), "the operator's certificate released the e-stop"
    finally:  # the laptop's clear, through both routers, releases it (and leaves the robot free to move)
        code, state = dep.gateway("POST", f"/v1/robots/{ROBOT}/estop/clear", {"confirm": True})
    assert code == 200 and not state["driver"]["estop_latched"], state


def test_netns_a_plain_listener_off_loopback_gives_its_clients_nothing(deployment: Deployment) -> None:
    """The access control's ``local`` subject is plain TCP on the loopback interface: a plain listener
    on the robot network (the plain profile's advice, copied into a secure config, and started by
    Zenoh as written; ``ovamos router`` refuses it) lets the intruder open a session but gives it
    nothing. With the subject matching every TCP link, as it was, the intruder commands the robot."""
    dep = deployment
    shipped = REPO / "deploy" / "zenoh" / "laptop-router-secure.json5"
    as_before = dep.root / "laptop-router-any-interface.json5"
    as_before.write_text(shipped.read_text().replace('{ id: "local", interfaces: ["lo"], link_protocols: ["tcp"] }',
                                                     '{ id: "local", link_protocols: ["tcp"] }'))
    assert as_before.read_text() != shipped.read_text()
    got = {}
    for name, config, port in (("before", as_before, 7460), ("after", shipped, 7462)):
        exposed = f"tcp/{LAPTOP_FROM_INTRUDER}:{port + 1}"
        router = subprocess.Popen(dep.hosts.argv("laptop", [
            sys.executable, str(REPO / "tests" / "netns_probe.py"), "router", "--unchecked", "--config", str(config),
            "--certs", str(dep.certs), "--cert", "laptop", "--listen", f"tcp/127.0.0.1:{port}", "--listen", exposed]),
            stdout=(dep.root / f"router-{name}.log").open("ab"), stderr=subprocess.STDOUT, cwd=REPO,
            start_new_session=True)
        watcher = Lines(dep.hosts.argv("laptop", [sys.executable, str(REPO / "tests" / "netns_probe.py"), "watch",
                                                  "--robot-id", ROBOT, "--connect", f"tcp/127.0.0.1:{port}",
                                                  "--keys", "plan_command"]), dep.root / f"watch-{name}.log")
        try:
            wait_for(lambda: watcher.snapshot("ready"), 30, f"a client of the {name} router")
            opened = _attacks(dep, [(exposed, [])])[0]["opened"]
            time.sleep(0.5)
            got[name] = (opened, len(watcher.snapshot("plan_command")))
        finally:
            watcher.stop()
            _stop_group(router)
    assert got["before"][0] and got["before"][1] > 0, f"the fault is not reproduced: {got}"
    assert got["after"] == (True, 0), f"a plain link off loopback was given rights: {got}"


def _interrupted_task(dep: Deployment, interrupt: Callable[[], None], resume: Callable[[], None],
                      targets: tuple[str, ...]) -> tuple[dict[str, Any], float, float | None, dict[str, int]]:
    """Submit, and once the wheels turn mid-task interrupt the link for 5 s; the task must go on to
    its end: every target found or its :data:`INTERRUPTED_STEPS` used, more than 5 steps of them
    after the interruption. The final event, when the interruption began, when the wheels came to
    rest after it, and the processes' start counts from before."""
    starts = dep.starts()
    task = dep.submit(*targets, max_steps=INTERRUPTED_STEPS)
    dep.wait_steps(task, 3)
    dep.wait_moving()
    interrupt()
    t0 = time.monotonic()
    at_interrupt = max(e["steps"] for e in dep.events(task))
    time.sleep(5.0)
    resume()
    rest = dep.stopped_at(t0, t0 + 4.5)
    final = dep.wait_task(task)
    if final["status"] == "done":
        assert sorted(f["label"] for f in final["found"]) == sorted(targets)
    else:
        assert final["message"].startswith(f"step limit {INTERRUPTED_STEPS} reached: "), final  # and why
    assert final["steps"] > at_interrupt + 5, f"the task did not go on: {final}"
    return final, t0, rest, starts


def test_netns_a_link_cut_stops_the_wheels_and_the_task_goes_on_when_it_returns(deployment: Deployment) -> None:
    dep = deployment
    final, t0, rest, starts = _interrupted_task(dep, dep.hosts.cut, dep.hosts.restore, ("spray_bottle", "countertop"))
    bound = COMMAND_TIMEOUT_S + _ramp(DriverConfig()) + 0.3  # 0.3 s: odometry period, scheduling
    print(f"link cut: wheels at rest {None if rest is None else round(rest - t0, 2)} s after it (bound {bound:.2f} s)")
    assert rest is not None and rest - t0 <= bound, \
        f"wheels at rest {None if rest is None else rest - t0} s after the cut"
    # each side said what was wrong while the link was down
    warned = [s for s in dep.watchers["robot"].snapshot("driver_state", t0)
              if s["t"] < t0 + 5.5 and "planner unreachable" in s["msg"].get("warnings", [])]
    assert warned, "driver/state never said 'planner unreachable'"
    waiting = [e for e in dep.events(final["task_id"], t0) if e["message"] == "robot unreachable"]
    assert waiting, "task/events never said 'robot unreachable'"
    assert dep.starts() == starts, "a process was restarted"


def test_netns_the_laptop_router_killed_and_restarted_mid_task(deployment: Deployment) -> None:
    dep = deployment
    up = dep.ups["laptop"]

    def kill_router() -> None:
        routers = [p for p in _descendants(up.pid) if " router " in _cmdline(p)]
        assert len(routers) == 1, routers
        os.kill(routers[0], signal.SIGKILL)

    final, t0, rest, starts = _interrupted_task(dep, kill_router, lambda: None, ("spray_bottle", "countertop"))
    bound = COMMAND_TIMEOUT_S + _ramp(DriverConfig()) + 0.3
    print(f"router killed: wheels at rest {None if rest is None else round(rest - t0, 2)} s after it")
    assert rest is not None and rest - t0 <= bound, \
        f"wheels at rest {None if rest is None else rest - t0} s after the kill"
    after = dep.starts()
    assert after.pop("laptop/router") == starts.pop("laptop/router") + 1  # the supervisor restarted it
    assert after == starts, "a service was restarted"
