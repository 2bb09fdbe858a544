"""Certificate faults at start-up: each one Zenoh alone starts with without a word (reproduced
first), then the clear error or warning ``ovamos router`` gives; the certificate folder's mode; a
secure router's plain listeners kept on loopback. Real routers and real certificates, every link on
127.0.0.1."""

from __future__ import annotations

import datetime as dt
import logging
import os
import re
import shutil
import stat
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
import zenoh

from ovamos.router import log_certificates
from ovamos.shared.bus.zconfig import TlsFiles, ZenohConfigError, build_config, check_plain_listeners, open_session
from ovamos.shared.certs import CertInfo, check_certificate, init_ca, issue
from ovamos.shared.procs import free_port, loopback
from tests.polling import ovamos_unwrapped as ovamos
from tests.polling import port_open, wait_for

pytestmark = pytest.mark.system  # processes, routers, browsers or real-time devices: make test-all

REPO = Path(__file__).resolve().parents[1]
SECURE_LAPTOP = REPO / "deploy" / "zenoh" / "laptop-router-secure.json5"
SECURE_ROBOT = REPO / "deploy" / "zenoh" / "robot-router-secure.json5"


@pytest.fixture
def certs(tmp_path: Path) -> Path:
    folder = tmp_path / "certs"
    init_ca(folder)
    issue(folder, "laptop", hosts=["127.0.0.1"])
    issue(folder, "robot")
    return folder


def _mismatched_key(certs: Path) -> None:
    shutil.copy(certs / "robot.key", certs / "laptop.key")


def _expired(certs: Path) -> None:
    issue(certs, "laptop", force=True, days=1, valid_from=dt.datetime(2020, 3, 1, tzinfo=dt.timezone.utc))


FAULTS: dict[str, tuple[Callable[[Path], None], str]] = {
    "a key that is not the certificate's": (
        _mismatched_key, r"laptop.key is not the key of certificate \S*laptop.pem: copy the pair"),
    "a key others can read": (
        lambda c: os.chmod(c / "laptop.key", 0o644), r"laptop.key is open to others \(mode 0644\): .* run "
                                                     r"`chmod 600 \S*laptop.key`"),
    "a CA others can write": (
        lambda c: os.chmod(c / "ca.pem", 0o666), r"ca.pem is writable by others \(mode 0666\): .* run "
                                                 r"`chmod go-w \S*ca.pem`"),
    "an expired certificate": (_expired, r"laptop.pem \(CN laptop\) expired on 2020-03-02 00:00 UTC"),
}


@pytest.mark.parametrize("fault", list(FAULTS))
def test_a_certificate_fault_zenoh_starts_with_is_refused_at_start_up(fault: str, certs: Path) -> None:
    make, message = FAULTS[fault]
    make(certs)
    # the fault: a connect-only router opens with it without a word (its links would never come up)
    unchecked = build_config("router", listen=[loopback(free_port())], connect=[f"tls/127.0.0.1:{free_port()}"],
                             tls=TlsFiles.from_folder(certs, "laptop"), require_certs=False)
    open_session(unchecked).close()
    # the fix: every router and service that uses certificates checks them first
    with pytest.raises(ZenohConfigError, match=message):
        build_config("router", connect=[f"tls/127.0.0.1:{free_port()}"], tls=TlsFiles.from_folder(certs, "laptop"))
    done = ovamos("router", "--certs", str(certs), "--cert", "laptop", "--listen", loopback(free_port()),
                  "--connect", f"tls/127.0.0.1:{free_port()}")
    assert done.returncode == 2
    assert re.search(message, done.stderr), done.stderr


def test_certs_init_makes_its_folder_private(tmp_path: Path) -> None:
    old = os.umask(0o022)
    try:
        (tmp_path / "plain").mkdir()  # what a folder gets under the usual umask, as `certs init` made it
        assert stat.S_IMODE((tmp_path / "plain").stat().st_mode) == 0o755
        assert ovamos("certs", "init", str(tmp_path / "new")).returncode == 0
        init_ca(tmp_path / "plain")
    finally:
        os.umask(old)
    for folder in ("new", "plain"):
        assert stat.S_IMODE((tmp_path / folder).stat().st_mode) == 0o700, folder


def test_expiry_is_logged_with_the_days_left_and_a_warning_when_near(certs: Path,
                                                                      caplog: pytest.LogCaptureFixture) -> None:
    issue(certs, "robot", force=True, days=10)
    with caplog.at_level(logging.INFO, logger="ovamos.router"):
        log_certificates([check_certificate(certs / "laptop.pem"), check_certificate(certs / "robot.pem")])
    laptop, robot = caplog.records
    assert laptop.levelno == logging.INFO and "(824 days left)" in laptop.getMessage()
    assert robot.levelno == logging.WARNING
    assert "it expires in 9 days, issue a new one (`ovamos certs issue DIR robot --force`)" in robot.getMessage()


def test_a_certificate_names_a_host_as_a_tls_client_checks_it() -> None:
    now = dt.datetime.now(dt.timezone.utc)
    info = CertInfo("x", "laptop", now, now, ("127.0.0.1", "laptop.local", "*.lan"), False)
    assert info.names("127.0.0.1") and info.names("LAPTOP.local.") and info.names("box.lan")
    assert not info.names("127.0.0.2") and not info.names("a.box.lan") and not info.names("lan")


class Routers:
    """``ovamos router`` processes, each with its output in a log file."""

    def __init__(self, root: Path) -> None:
        self.root = root
        self.procs: dict[str, subprocess.Popen] = {}

    def start(self, name: str, *args: str, port: int) -> None:
        log = (self.root / f"{name}.log").open("wb")
        self.procs[name] = subprocess.Popen([sys.executable, "-m", "ovamos.cli", "router", *args],
                                            stdout=log, stderr=subprocess.STDOUT, cwd=REPO)
        wait_for(lambda: port_open(port), 20, f"router {name} on port {port}")

    def log(self, name: str) -> str:
        return " ".join((self.root / f"{name}.log").read_text(errors="replace").split())

    def stop(self, name: str) -> None:
        proc = self.procs.pop(name)
        proc.terminate()
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


@pytest.fixture
def routers(tmp_path: Path) -> Iterator[Routers]:
    made = Routers(tmp_path)
    try:
        yield made
    finally:
        for name in list(made.procs):
            made.stop(name)


def test_a_laptop_certificate_for_another_host_is_named_on_both_sides(certs: Path, routers: Routers) -> None:
    issue(certs, "laptop", hosts=["laptop.local"], force=True)  # not the address the robot dials
    laptop_port, link_port, robot_port = free_port(), free_port(), free_port()
    link = f"tls/127.0.0.1:{link_port}"
    common = ("--certs", str(certs))
    routers.start("laptop", "--config", str(SECURE_LAPTOP), *common, "--cert", "laptop",
                  "--listen", loopback(laptop_port), "--listen", link, port=laptop_port)
    routers.start("robot", "--config", str(SECURE_ROBOT), *common, "--cert", "robot",
                  "--listen", loopback(robot_port), "--connect", link, port=robot_port)
    # the fault as Zenoh reports it: a bare alert, on the laptop only
    wait_for(lambda: "BadCertificate" in routers.log("laptop"), 20, "the laptop's BadCertificate")
    # ovamos: the robot says what is wrong and how to fix it; the laptop warned at start-up
    wait_for(lambda: "will not come up" in routers.log("robot"), 20, "the robot's error")
    assert (f"TLS link {link} will not come up: the peer at {link} (CN laptop) has a certificate that names only "
            f"laptop.local, not 127.0.0.1: this router refuses it and the peer logs BadCertificate; issue the "
            f"peer's certificate again with `ovamos certs issue DIR laptop --host 127.0.0.1 ... --force`"
            ) in routers.log("robot")
    assert ("WARNING ovamos.router: this router listens on tls/127.0.0.1 but its certificate "
            in routers.log("laptop")) and "names only laptop.local" in routers.log("laptop")
    # issued for the right host, the link comes up and each side logs the other's expiry
    routers.stop("robot")
    routers.stop("laptop")
    issue(certs, "laptop", hosts=["127.0.0.1"], force=True)
    (routers.root / "robot.log").unlink()
    routers.start("laptop", "--config", str(SECURE_LAPTOP), *common, "--cert", "laptop",
                  "--listen", loopback(laptop_port), "--listen", link, port=laptop_port)
    routers.start("robot", "--config", str(SECURE_ROBOT), *common, "--cert", "robot",
                  "--listen", loopback(robot_port), "--connect", link, port=robot_port)
    wait_for(lambda: f"TLS peer {link}: CN laptop" in routers.log("robot"), 20, "the robot's note of the laptop")
    assert "(824 days left)" in routers.log("robot") and "will not come up" not in routers.log("robot")
    assert "TLS certificate" in routers.log("laptop") and "days left" in routers.log("laptop")
    _linked(laptop_port, robot_port)


def _linked(laptop_port: int, robot_port: int) -> None:
    """The robot's odometry reaches a client of the laptop's router."""
    got: list[int] = []
    with zenoh.open(build_config("client", connect=[loopback(laptop_port)])) as laptop, \
            zenoh.open(build_config("client", connect=[loopback(robot_port)])) as robot:
        laptop.declare_subscriber("ovamos/robot1/odom", lambda s: got.append(1))

        def sent() -> bool:
            robot.put("ovamos/robot1/odom", b"{}")
            time.sleep(0.1)
            return bool(got)
        wait_for(sent, 20, "the robot's odometry on the laptop")


@pytest.mark.parametrize("plain", ["tcp/0.0.0.0:{port}", "tcp/[::]:{port}", "tcp/192.168.1.10:{port}",
                                   "tcp/laptop.local:{port}"])
def test_a_secure_router_refuses_a_plain_listener_off_loopback(plain: str, certs: Path) -> None:
    endpoint = plain.format(port=free_port())
    listen = ("--listen", loopback(free_port()), "--listen", endpoint, "--listen", f"tls/127.0.0.1:{free_port()}")
    # the fault: the config is accepted as it is (and Zenoh would listen there)
    build_config("router", file=SECURE_LAPTOP, listen=listen[1::2], tls=TlsFiles.from_folder(certs, "laptop"))
    done = ovamos("router", "--config", str(SECURE_LAPTOP), "--certs", str(certs), "--cert", "laptop", *listen)
    assert done.returncode == 2
    assert (f"listen endpoint {endpoint} is plain (no TLS) and not on loopback: on a router with a tls/ link, "
            f"anyone who reaches") in done.stderr


def test_plain_listeners_on_loopback_or_without_tls_are_left_alone(certs: Path) -> None:
    tls = TlsFiles.from_folder(certs, "laptop")
    for listen in (["tcp/127.0.0.1:7447", "tcp/localhost:7448", "tcp/[::1]:7449", "tls/127.0.0.1:7450"],
                   ["tls/0.0.0.0:7450", "unixsock-stream//tmp/zenoh.sock"]):
        check_plain_listeners(build_config("router", listen=listen, tls=tls))
    check_plain_listeners(build_config("router", listen=["tcp/0.0.0.0:7447"]))  # no TLS link: the plain profile
