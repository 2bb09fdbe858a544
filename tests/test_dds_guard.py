"""The guard every DDS process of ours passes before rclpy is imported (shared/dds.py): refused in
this machine's own network namespace, allowed only in a loopback-only one with the loopback Fast
DDS profile. Nothing here loads DDS."""

from __future__ import annotations

import json
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from ovamos.shared.dds import LOOPBACK_PROFILE, PROFILE_VARS, DdsNetworkError, check_loopback_only, loopback_env

REPO = Path(__file__).resolve().parent.parent


def test_the_shipped_profile_passes_in_a_loopback_only_namespace() -> None:
    check_loopback_only(loopback_env({}), interfaces=["lo"])
    env = loopback_env({"ROS_STATIC_PEERS": "10.0.0.7", "HOME": "/root"})
    assert "ROS_STATIC_PEERS" not in env and env["HOME"] == "/root"
    assert {env[v] for v in PROFILE_VARS} == {str(LOOPBACK_PROFILE)} and env["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "LOCALHOST"


def test_another_interface_is_refused_by_name() -> None:
    with pytest.raises(DdsNetworkError, match=r"has eth0, lo, not only lo.*python -m ovamos.shared.dds"):
        check_loopback_only(loopback_env({}), interfaces=["lo", "eth0"])


def test_this_hosts_own_namespace_is_refused() -> None:
    names = sorted(name for _, name in socket.if_nameindex())
    if names == ["lo"]:
        pytest.skip("this test already runs in a loopback-only namespace")
    with pytest.raises(DdsNetworkError, match="not only lo"):
        check_loopback_only(loopback_env({}))


@pytest.mark.parametrize("env,message", [
    ({"FASTDDS_DEFAULT_PROFILES_FILE": "p", "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"},
     "FASTRTPS_DEFAULT_PROFILES_FILE is not set"),
    ({**loopback_env({}), "ROS_AUTOMATIC_DISCOVERY_RANGE": "SUBNET"}, "is 'SUBNET', not 'LOCALHOST'"),
    ({**loopback_env({}), "ROS_DISCOVERY_SERVER": "10.0.0.2:11811"}, "ROS_DISCOVERY_SERVER is set"),
])
def test_an_environment_that_widens_discovery_is_refused(env: dict[str, str], message: str) -> None:
    with pytest.raises(DdsNetworkError, match=message):
        check_loopback_only(env, interfaces=["lo"])


@pytest.mark.parametrize("change,message", [
    (lambda x: x.replace("<address>127.0.0.1</address></interfaceWhiteList>",
                         "<address>192.168.1.5</address></interfaceWhiteList>"), "not only 127.0.0.1"),
    (lambda x: x.replace("<defaultUnicastLocatorList>", "<defaultMulticastLocatorList><locator><udpv4>"
                         "<address>127.0.0.1</address></udpv4></locator></defaultMulticastLocatorList>"
                         "<defaultUnicastLocatorList>"), "multicast"),
    (lambda x: x.replace("<useBuiltinTransports>false</useBuiltinTransports>", ""), "built-in transports"),
    (lambda x: x[: len(x) // 2], "cannot be read as a profile"),
])
def test_a_profile_that_could_reach_beyond_loopback_is_refused(tmp_path: Path, change, message: str) -> None:
    profile = tmp_path / "profile.xml"
    profile.write_text(change(LOOPBACK_PROFILE.read_text()))
    with pytest.raises(DdsNetworkError, match=message):
        check_loopback_only(loopback_env({}, profile), interfaces=["lo"])


def _unshare_reason() -> str | None:
    try:
        done = subprocess.run(["unshare", "--net", "--mount", "true"], capture_output=True, text=True, timeout=30)
    except (OSError, subprocess.SubprocessError) as exc:
        return f"cannot run unshare: {exc}"
    return None if done.returncode == 0 else f"unshare --net --mount refused (root is needed): {done.stderr.strip()}"


def test_the_runner_gives_a_command_a_loopback_only_namespace_that_passes_the_guard() -> None:
    if (reason := _unshare_reason()) is not None:
        pytest.skip(reason)
    probe = ("import json, os, socket; from ovamos.shared.dds import check_loopback_only; check_loopback_only(); "
             "print(json.dumps({'links': sorted(n for _, n in socket.if_nameindex()), "
             "'shm': os.listdir('/dev/shm'), 'range': os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE']}))")
    done = subprocess.run([sys.executable, "-m", "ovamos.shared.dds", "--", sys.executable, "-c", probe], cwd=REPO,
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    inside = json.loads(done.stdout)
    assert inside == {"links": ["lo"], "shm": [], "range": "LOCALHOST"}  # a private, empty /dev/shm
    # a 127.0.0.1 socket works in there (the lo the runner brought up)
    echo = ("import socket; s = socket.socket(); s.bind(('127.0.0.1', 0)); s.listen(); "
            "c = socket.create_connection(s.getsockname()); print('connected')")
    done = subprocess.run([sys.executable, "-m", "ovamos.shared.dds", "--", sys.executable, "-c", echo], cwd=REPO,
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 0 and done.stdout.strip() == "connected", done.stderr
