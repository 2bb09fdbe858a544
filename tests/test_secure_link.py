"""The pieces of the secure laptop-robot link that need no second host: certificates (``ovamos
certs``), TLS settings and their checks in Zenoh configs, the secure profiles' argv, and how a
router reads its access control's refusals from Zenoh's trace. The link itself, over two network
namespaces, is tests/test_netns_link.py."""

from __future__ import annotations

import datetime as dt
import json
import stat
from pathlib import Path

import pytest

from ovamos.profiles import PROFILE_DIR, ProfileError, load_profile, supervisor_for
from ovamos.shared.bus.acl import TraceParser
from ovamos.shared.bus.zconfig import TlsFiles, ZenohConfigError, build_config
from ovamos.shared.certs import CertError, check_certificate, init_ca, issue, list_certificates
from tests.polling import ovamos_unwrapped as ovamos

pytestmark = pytest.mark.system  # processes, routers, browsers or real-time devices: make test-all


@pytest.fixture
def certs(tmp_path: Path) -> Path:
    folder = tmp_path / "certs"
    init_ca(folder)
    issue(folder, "laptop", hosts=["127.0.0.1", "laptop.local"])
    issue(folder, "robot")
    return folder


def test_a_ca_and_certificates_with_private_keys_only_the_owner_reads(certs: Path) -> None:
    for key in ("ca.key", "laptop.key", "robot.key"):
        assert stat.S_IMODE((certs / key).stat().st_mode) == 0o600
    laptop = check_certificate(certs / "laptop.pem")
    assert laptop.common_name == "laptop" and laptop.hosts == ("127.0.0.1", "laptop.local")
    assert not laptop.is_ca and check_certificate(certs / "ca.pem").is_ca
    assert check_certificate(certs / "robot.pem").hosts == ("robot",)  # no --host: its name
    assert [i.common_name for i in list_certificates(certs)] == ["ovamos CA", "laptop", "robot"]


def test_certificate_errors_say_what_to_do(tmp_path: Path, certs: Path) -> None:
    with pytest.raises(CertError, match="a CA already exists in .*ca.pem, ca.key"):
        init_ca(certs)
    with pytest.raises(CertError, match=r"no CA in .*nowhere \(ca.pem, ca.key missing\): create one with "
                                        r"`ovamos certs init"):
        issue(tmp_path / "nowhere", "robot")
    with pytest.raises(CertError, match="robot.pem already exists: --force replaces it"):
        issue(certs, "robot")
    issue(certs, "robot", force=True)
    for bad in ("Robot", "ca", "../x", ""):
        with pytest.raises(CertError, match="certificate name"):
            issue(certs, bad)
    with pytest.raises(CertError, match="neither an IP address nor a DNS name"):
        issue(certs, "operator", hosts=["bad host"])


def test_an_expired_certificate_is_refused_at_start_up_with_its_date(certs: Path) -> None:
    issue(certs, "robot", force=True, days=1, valid_from=dt.datetime(2020, 3, 1, tzinfo=dt.timezone.utc))
    with pytest.raises(CertError, match=r"robot.pem \(CN robot\) expired on 2020-03-02 00:00 UTC"):
        check_certificate(certs / "robot.pem")
    with pytest.raises(ZenohConfigError, match="expired on 2020-03-02 00:00 UTC"):
        build_config("router", tls=TlsFiles.from_folder(certs, "robot"))
    done = ovamos("router", "--certs", str(certs), "--cert", "robot", "--listen", "tcp/127.0.0.1:0")
    assert done.returncode == 2 and "expired on 2020-03-02" in done.stderr
    done = ovamos("certs", "show", str(certs))
    assert done.returncode == 1 and "expired on 2020-03-02" in done.stdout


def test_the_cli_makes_a_ca_and_certificates(tmp_path: Path) -> None:
    folder = tmp_path / "c"
    assert ovamos("certs", "init", str(folder)).returncode == 0
    done = ovamos("certs", "init", str(folder))
    assert done.returncode == 2 and "already exists" in done.stderr
    done = ovamos("certs", "issue", str(folder), "laptop", "--host", "192.168.1.10")
    assert done.returncode == 0 and "CN laptop" in done.stdout and "192.168.1.10" in done.stdout
    done = ovamos("certs", "issue", str(tmp_path / "none"), "robot")
    assert done.returncode == 2 and "no CA in" in done.stderr


def test_tls_settings_for_mutual_authentication(certs: Path) -> None:
    cfg = build_config("router", listen=["tls/127.0.0.1:0"], tls=TlsFiles.from_folder(certs, "laptop"))
    tls = json.loads(cfg.get_json("transport/link/tls"))
    assert tls["enable_mtls"] is True and tls["close_link_on_expiration"] is True
    assert tls["root_ca_certificate"] == str(certs / "ca.pem")
    assert tls["listen_certificate"] == tls["connect_certificate"] == str(certs / "laptop.pem")
    assert tls["listen_private_key"] == tls["connect_private_key"] == str(certs / "laptop.key")
    with pytest.raises(ZenohConfigError, match="a tls/ endpoint needs certificates"):
        build_config("router", listen=["tls/127.0.0.1:0"])
    with pytest.raises(ZenohConfigError, match="nobody.pem does not exist"):
        build_config("router", tls=TlsFiles.from_folder(certs, "nobody"))


def test_secure_profiles_link_over_tls_with_this_hosts_certificate(certs: Path, tmp_path: Path) -> None:
    sup = supervisor_for("laptop-secure", certs=certs, listen_link="192.168.1.10:7450", log_dir=tmp_path,
                         check_configs=False)
    router = sup.status()[0]
    argv = next(c.entry.argv for c in sup._children if c.entry.name == router.name)
    assert argv[argv.index("--certs") + 1] == str(certs.resolve()) and argv[argv.index("--cert") + 1] == "laptop"
    listen = [argv[i + 1] for i, a in enumerate(argv) if a == "--listen"]
    assert listen == ["tcp/127.0.0.1:7447", "tls/192.168.1.10:7450"]  # the services' port stays on loopback
    robot = supervisor_for("robot-secure", certs=certs, connect_laptop="192.168.1.10:7450", log_dir=tmp_path,
                           check_configs=False)
    argv = robot._children[0].entry.argv
    assert argv[argv.index("--connect") + 1] == "tls/192.168.1.10:7450"
    assert robot._children[0].entry.ready == ("127.0.0.1", 7448)
    with pytest.raises(ProfileError, match=r"robot-secure.toml: router: .*operator.pem does not exist"):
        profile = PROFILE_DIR / "robot-secure.toml"
        text = profile.read_text().replace('cert = "robot"', 'cert = "operator"')
        copy = tmp_path / "robot-secure.toml"
        copy.write_text(text.replace('"../', f'"{PROFILE_DIR.parent}/'))
        supervisor_for(copy, certs=certs, log_dir=tmp_path, check_configs=False)
    plain = supervisor_for("laptop", listen_link="192.168.1.10:7447", log_dir=tmp_path, check_configs=False)
    argv = plain._children[0].entry.argv  # the robot's link in plain TCP, the services' on loopback
    assert [argv[i + 1] for i, a in enumerate(argv) if a == "--listen"] == ["tcp/127.0.0.1:7447",
                                                                             "tcp/192.168.1.10:7447"]
    assert load_profile(PROFILE_DIR / "laptop.toml").secure is False


def _line(thread: int, text: str) -> str:
    return (f"\x1b[2m2026-12-01T14:00:59.903025Z\x1b[0m \x1b[35mTRACE\x1b[0m rx-0 ThreadId({thread}) "
            f"\x1b[2mzenoh::net::routing::interceptor{text}")


def test_a_refusal_is_the_last_unauthorized_verdict_before_the_interceptor_drops_the_message() -> None:
    parser = TraceParser()
    verdict = ("::access_control\x1b[0m\x1b[2m:\x1b[0m 2a29 on Interface(lo)+CertCommonName({cn})+Transport(Tls)+"
               "2a29 is {v}authorized to Put (ingress) on ovamos/robot1/{key}")
    # allowed by a later subject: no denial
    assert parser.feed(_line(9, verdict.format(cn="robot", v="un", key="odom"))) is None
    assert parser.feed(_line(9, verdict.format(cn="robot", v="", key="odom"))) is None
    # refused, then dropped, on another thread in between
    assert parser.feed(_line(11, verdict.format(cn="operator", v="un", key="plan/command"))) is None
    assert parser.feed(_line(9, verdict.format(cn="robot", v="", key="odom"))) is None
    denial = parser.feed(_line(11, "\x1b[0m\x1b[2m:\x1b[0m Msg intercepted!"))
    assert denial is not None and denial.describe() == \
        "Put (ingress) on ovamos/robot1/plan/command from CN operator"
    assert parser.feed("a line from something else") is None
