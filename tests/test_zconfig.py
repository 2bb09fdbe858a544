"""Zenoh configs: safe defaults, explicit overrides, and shipped files that stay on loopback.

Multicast scouting on a shared network would join strangers' Zenoh traffic and
a non-loopback listener would expose the robot, so both are checked on every
config this project builds or ships.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest
import zenoh

from ovamos.shared.bus.zconfig import DEFAULT_ENDPOINT, LEASE_MS, RETRY, ZenohConfigError, build_config

DEPLOY_DIR = Path(__file__).resolve().parents[1] / "deploy" / "zenoh"


def get(cfg: zenoh.Config, key: str) -> Any:
    return json.loads(cfg.get_json(key))


def write(tmp_path: Path, text: str, name: str = "cfg.json5") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def test_defaults_are_a_loopback_client() -> None:
    """No file, no flags: a client of the local router that waits and retries forever."""
    cfg = build_config()
    assert get(cfg, "mode") == "client"
    assert get(cfg, "connect/endpoints") == [DEFAULT_ENDPOINT] == ["tcp/127.0.0.1:7447"]
    assert get(cfg, "listen/endpoints") == []
    assert get(cfg, "scouting/multicast/enabled") is False
    assert get(cfg, "transport/link/tx/lease") == LEASE_MS == 3000
    assert get(cfg, "connect/timeout_ms") == -1
    assert get(cfg, "connect/exit_on_failure") is False
    assert get(cfg, "connect/retry") == RETRY
    assert get(cfg, "connect/retry") == {"period_init_ms": 100, "period_max_ms": 1000,
                                         "period_increase_factor": 2}


def test_router_mode_listens_on_loopback_by_default() -> None:
    cfg = build_config("router")
    assert get(cfg, "mode") == "router"
    assert get(cfg, "listen/endpoints") == ["tcp/127.0.0.1:7447"]
    assert get(cfg, "connect/endpoints") == []
    assert get(cfg, "scouting/multicast/enabled") is False


def test_peer_mode_listens_on_a_loopback_port() -> None:
    """Zenoh's own default would listen on every interface ('tcp/[::]:0')."""
    cfg = build_config("peer")
    assert get(cfg, "listen/endpoints") == ["tcp/127.0.0.1:0"]


def test_overrides_replace_endpoints() -> None:
    cfg = build_config(connect=["tcp/127.0.0.1:9000", "tcp/127.0.0.1:9001"], listen=["tcp/127.0.0.1:9002"])
    assert get(cfg, "connect/endpoints") == ["tcp/127.0.0.1:9000", "tcp/127.0.0.1:9001"]
    assert get(cfg, "listen/endpoints") == ["tcp/127.0.0.1:9002"]
    router = build_config("router", listen=["tcp/127.0.0.1:9100"])
    assert get(router, "listen/endpoints") == ["tcp/127.0.0.1:9100"]


def test_overrides_and_mode_win_over_the_file(tmp_path: Path) -> None:
    """One shipped file serves any port: flags replace the file's endpoints."""
    path = write(tmp_path, '{ mode: "client", connect: { endpoints: ["tcp/127.0.0.1:7448"], timeout_ms: 500 },'
                           ' transport: { link: { tx: { lease: 1234 } } } }')
    cfg = build_config(file=path)
    assert get(cfg, "connect/endpoints") == ["tcp/127.0.0.1:7448"]
    assert get(cfg, "connect/timeout_ms") == 500  # the file's choice is kept
    assert get(cfg, "transport/link/tx/lease") == 1234
    cfg = build_config("router", file=path, connect=["tcp/127.0.0.1:9000"], listen=["tcp/127.0.0.1:9001"])
    assert get(cfg, "mode") == "router"
    assert get(cfg, "connect/endpoints") == ["tcp/127.0.0.1:9000"]
    assert get(cfg, "listen/endpoints") == ["tcp/127.0.0.1:9001"]


def test_file_mode_is_used_when_none_is_given(tmp_path: Path) -> None:
    cfg = build_config(file=write(tmp_path, '{ mode: "router" }'))
    assert get(cfg, "mode") == "router"
    assert get(cfg, "listen/endpoints") == ["tcp/127.0.0.1:7447"]


def test_file_that_enables_multicast_is_refused(tmp_path: Path) -> None:
    path = write(tmp_path, '{ mode: "client", scouting: { multicast: { enabled: true } } }')
    with pytest.raises(ZenohConfigError, match="multicast"):
        build_config(file=path)


def test_file_that_leaves_multicast_unset_gets_it_disabled(tmp_path: Path) -> None:
    cfg = build_config(file=write(tmp_path, '{ mode: "peer" }'))
    assert get(cfg, "scouting/multicast/enabled") is False


def test_missing_file_is_a_config_error(tmp_path: Path) -> None:
    with pytest.raises(ZenohConfigError, match="nope.json5"):
        build_config(file=tmp_path / "nope.json5")


@pytest.mark.parametrize("text", [
    '{ mode: "client", bogus_field: 1 }',
    '{ mode: "client", connect: { endpoint: ["tcp/127.0.0.1:7447"] } }',
    '{ mode: "satellite" }',
    "{ this is not json5",
])
def test_invalid_file_is_a_config_error(tmp_path: Path, text: str) -> None:
    with pytest.raises(ZenohConfigError):
        build_config(file=write(tmp_path, text))


def test_unknown_mode_argument_is_a_config_error() -> None:
    with pytest.raises(ZenohConfigError, match="satellite"):
        build_config("satellite")


def _endpoints(cfg: zenoh.Config, which: str) -> list[str]:
    """Endpoints of listen/connect, flattening Zenoh's per-mode form ({"router": [...], ...})."""
    value = get(cfg, f"{which}/endpoints")
    if isinstance(value, dict):
        return [e for per_mode in value.values() for e in per_mode]
    assert isinstance(value, list), f"{which}/endpoints is {value!r}"
    return value


def _loopback_tcp(endpoint: str) -> bool:
    """tcp (or, for the secure routers' links, tls) on 127.0.0.1 with a port."""
    for prefix in ("tcp/127.0.0.1:", "tls/127.0.0.1:"):
        if endpoint.startswith(prefix) and endpoint[len(prefix):].isdigit():
            return True
    return False


def test_every_shipped_config_is_safe() -> None:
    """Each deploy/zenoh/*.json5 loads, keeps multicast off and stays on loopback (TCP; TLS for the
    secure routers' link, whose certificates come at run time: not checked here)."""
    files = sorted(DEPLOY_DIR.glob("*.json5"))
    assert files, f"no Zenoh configs shipped: {DEPLOY_DIR} has no *.json5 files"
    problems: list[str] = []
    for path in files:
        raw = zenoh.Config.from_file(str(path))
        if get(raw, "scouting/multicast/enabled") is not False:
            problems.append(f"{path.name}: does not set scouting.multicast.enabled: false explicitly")
        try:
            cfg = build_config(file=path, require_certs=False)
        except ZenohConfigError as exc:
            problems.append(f"{path.name}: {exc}")
            continue
        if "secure" in path.name and get(cfg, "access_control/enabled") is not True:
            problems.append(f"{path.name}: a secure router without access control")
        for subject in get(cfg, "access_control/subjects") or []:
            if "tcp" in (subject.get("link_protocols") or []) and subject.get("interfaces") != ["lo"]:
                problems.append(f"{path.name}: subject {subject['id']!r} lets plain TCP in from any interface")
        if get(cfg, "scouting/multicast/enabled") is not False:
            problems.append(f"{path.name}: multicast enabled after build_config")
        for which in ("listen", "connect"):
            for endpoint in _endpoints(cfg, which):
                if not _loopback_tcp(endpoint):
                    problems.append(f"{path.name}: {which} endpoint {endpoint!r} is not tcp/127.0.0.1")
        mode = get(cfg, "mode")
        if mode == "client" and not _endpoints(cfg, "connect"):
            problems.append(f"{path.name}: a client with nothing to connect to")
        if mode == "router" and not _endpoints(cfg, "listen"):
            problems.append(f"{path.name}: a router that listens nowhere")
    assert not problems, "\n".join(problems)
