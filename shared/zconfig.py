"""Zenoh session configuration with this project's safe defaults.

Defaults follow what was measured for this deployment (../DESIGN.md section 4):
services are clients of a router on loopback, wait for it forever and reconnect
quickly after a router restart, and notice a hung peer within ~3 s. Multicast
scouting is always off: on a shared network it would make a robot join
strangers' Zenoh traffic, so a config file that turns it on is refused.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Literal
from collections.abc import Sequence

import zenoh

Mode = Literal["client", "peer", "router"]
DEFAULT_PORT = 7447
DEFAULT_ENDPOINT = f"tcp/127.0.0.1:{DEFAULT_PORT}"
_DEFAULT_LISTEN = {"client": [], "peer": ["tcp/127.0.0.1:0"], "router": [DEFAULT_ENDPOINT]}
LEASE_MS = 3000
_ZENOH_DEFAULT_LEASE_MS = 10000
RETRY = {"period_init_ms": 100, "period_max_ms": 1000, "period_increase_factor": 2}


class ZenohConfigError(ValueError):
    """A Zenoh config file or override this project will not run with."""


def _get(cfg: zenoh.Config, key: str) -> object:
    return json.loads(cfg.get_json(key))


def _set(cfg: zenoh.Config, key: str, value: object) -> None:
    cfg.insert_json5(key, json.dumps(value))


def build_config(mode: Mode | None = None, *, file: str | Path | None = None,
                 connect: Sequence[str] = (), listen: Sequence[str] = ()) -> zenoh.Config:
    """A Zenoh config: ``file`` (json5) if given, our defaults, then explicit overrides.

    Without a file the result is a client of a router on ``tcp/127.0.0.1:7447``.
    ``connect`` / ``listen`` replace the file's endpoints, so one shipped file
    serves any port (tests use free ports).
    """
    if file is not None:
        try:
            cfg = zenoh.Config.from_file(str(file))
        except zenoh.ZError as exc:
            raise ZenohConfigError(f"cannot load Zenoh config {file}: {exc}") from None
        if _get(cfg, "scouting/multicast/enabled") is True:
            raise ZenohConfigError(f"{file} enables multicast scouting; this project requires it "
                                   "disabled (set scouting.multicast.enabled: false)")
    else:
        cfg = zenoh.Config()
    file_mode = _get(cfg, "mode")
    mode = mode or file_mode or "client"
    if mode not in ("client", "peer", "router"):
        raise ZenohConfigError(f"unknown Zenoh mode {mode!r}")
    _set(cfg, "mode", mode)
    _set(cfg, "scouting/multicast/enabled", False)
    if connect:
        _set(cfg, "connect/endpoints", list(connect))
    if listen:
        _set(cfg, "listen/endpoints", list(listen))
    if mode == "client" and not _get(cfg, "connect/endpoints"):
        _set(cfg, "connect/endpoints", [DEFAULT_ENDPOINT])
    if not isinstance(_get(cfg, "listen/endpoints"), list):
        # Zenoh's default listens on every interface; ours stays on loopback.
        _set(cfg, "listen/endpoints", _DEFAULT_LISTEN[mode])
    if _get(cfg, "connect/timeout_ms") is None:
        _set(cfg, "connect/timeout_ms", -1)
    if _get(cfg, "connect/exit_on_failure") is None:
        _set(cfg, "connect/exit_on_failure", False)
    if _get(cfg, "connect/retry") is None:
        _set(cfg, "connect/retry", RETRY)
    if _get(cfg, "transport/link/tx/lease") == _ZENOH_DEFAULT_LEASE_MS:
        _set(cfg, "transport/link/tx/lease", LEASE_MS)
    return cfg


def open_session(cfg: zenoh.Config) -> zenoh.Session:
    """Open a session; a bad endpoint or a taken port becomes one clear error."""
    try:
        return zenoh.open(cfg)
    except zenoh.ZError as exc:
        endpoints = {k: _get(cfg, f"{k}/endpoints") for k in ("listen", "connect")}
        raise ZenohConfigError(f"cannot open a Zenoh {_get(cfg, 'mode')} session "
                               f"({endpoints}): {exc}") from None
