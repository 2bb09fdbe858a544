"""Zenoh session configuration with this project's safe defaults.

Defaults follow what was measured for this deployment (../DESIGN.md section 4):
services are clients of a router on loopback, wait for it forever and reconnect
quickly after a router restart, and notice a hung peer within ~3 s. Multicast
scouting is always off: on a shared network it would make a robot join
strangers' Zenoh traffic, so a config file that turns it on is refused.

TLS (the link between the laptop's and the robot's routers): ``tls=`` a
:class:`TlsFiles` (a certificate folder made by ``ovamos certs`` and this host's
role) fills ``transport.link.tls`` for mutual authentication. Whatever the
source of a TLS setting (that argument or a config file), the certificates it
names are checked before Zenoh sees them: a missing or expired one is a
:class:`ZenohConfigError` with the date, not a link that silently never comes up.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Literal
from collections.abc import Sequence

import zenoh

from shared.certs import CA_CERT, CertError, check_certificate, check_key

Mode = Literal["client", "peer", "router"]
DEFAULT_PORT = 7447
DEFAULT_ENDPOINT = f"tcp/127.0.0.1:{DEFAULT_PORT}"
_DEFAULT_LISTEN = {"client": [], "peer": ["tcp/127.0.0.1:0"], "router": [DEFAULT_ENDPOINT]}
LEASE_MS = 3000
_ZENOH_DEFAULT_LEASE_MS = 10000
RETRY = {"period_init_ms": 100, "period_max_ms": 1000, "period_increase_factor": 2}


class ZenohConfigError(ValueError):
    """A Zenoh config file or override this project will not run with."""


class RouterUnreachableError(ZenohConfigError):
    """A session given an open timeout (the CLI's tools) found no router within it."""


@dataclass(frozen=True)
class TlsFiles:
    """This host's side of the mTLS link: the CA that signs every peer, and its own pair."""

    ca: Path
    cert: Path
    key: Path

    @classmethod
    def from_folder(cls, folder: str | Path, name: str) -> TlsFiles:
        """The files ``ovamos certs`` writes: ``ca.pem``, ``NAME.pem`` and ``NAME.key``."""
        folder = Path(folder).resolve()
        return cls(folder / CA_CERT, folder / f"{name}.pem", folder / f"{name}.key")

    def settings(self) -> dict[str, object]:
        """``transport.link.tls``: the same pair for accepting and opening links, both ends
        authenticated, and a link closed when a certificate on it expires."""
        return {"root_ca_certificate": str(self.ca),
                "listen_certificate": str(self.cert), "listen_private_key": str(self.key),
                "connect_certificate": str(self.cert), "connect_private_key": str(self.key),
                "enable_mtls": True, "close_link_on_expiration": True}


_TLS_CERTS = ("root_ca_certificate", "listen_certificate", "connect_certificate")
_TLS_KEYS = ("listen_private_key", "connect_private_key")


def check_tls(cfg: zenoh.Config) -> list[str]:
    """Check every certificate and key ``transport.link.tls`` names (existing, valid now);
    returns the certificates' descriptions. Raises :class:`ZenohConfigError`."""
    tls = _get(cfg, "transport/link/tls") or {}
    found = []
    try:
        for field in _TLS_CERTS:
            if tls.get(field) and (info := check_certificate(tls[field]).describe()) not in found:
                found.append(info)
        for field in _TLS_KEYS:
            if tls.get(field):
                check_key(tls[field])
    except CertError as exc:
        raise ZenohConfigError(str(exc)) from None
    return found


def uses_tls(cfg: zenoh.Config) -> bool:
    """Whether the config listens on or connects to a ``tls/`` endpoint."""
    return any(str(e).startswith("tls/") for kind in ("listen", "connect") for e in _endpoints(cfg, kind))


def _endpoints(cfg: zenoh.Config, kind: Literal["listen", "connect"]) -> list[object]:
    """The ``listen`` or ``connect`` endpoints: a list, or (Zenoh takes both) a list per mode."""
    value = _get(cfg, f"{kind}/endpoints")
    return [e for v in value.values() for e in v] if isinstance(value, dict) else list(value or [])


def _get(cfg: zenoh.Config, key: str) -> object:
    return json.loads(cfg.get_json(key))


def _set(cfg: zenoh.Config, key: str, value: object) -> None:
    cfg.insert_json5(key, json.dumps(value))


def build_config(mode: Mode | None = None, *, file: str | Path | None = None,
                 connect: Sequence[str] = (), listen: Sequence[str] = (),
                 tls: TlsFiles | None = None, require_certs: bool = True,
                 open_timeout_s: float | None = None) -> zenoh.Config:
    """A Zenoh config: ``file`` (json5) if given, our defaults, then explicit overrides.

    Without a file the result is a client of a router on ``tcp/127.0.0.1:7447``.
    ``connect`` / ``listen`` replace the file's endpoints, so one shipped file
    serves any port (tests use free ports). ``tls`` sets the TLS files (see
    :class:`TlsFiles`); the certificates named, from here or the file, are checked
    (``require_certs=False``: not, for a config only read, never opened).

    ``open_timeout_s``: opening the session fails (:class:`RouterUnreachableError`) when
    none of the connect endpoints answers within it. Services leave it None and wait for
    their router for ever (a profile starts them in any order); an operator's tool sets it,
    or it would hang without a word when no router is up. Once open, a session reconnects
    after a router restart either way (``connect.retry``).
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
    if open_timeout_s is not None:
        _set(cfg, "connect/timeout_ms", max(1, round(open_timeout_s * 1000)))
        _set(cfg, "connect/exit_on_failure", True)
    if _get(cfg, "connect/timeout_ms") is None:
        _set(cfg, "connect/timeout_ms", -1)
    if _get(cfg, "connect/exit_on_failure") is None:
        _set(cfg, "connect/exit_on_failure", False)
    if _get(cfg, "connect/retry") is None:
        _set(cfg, "connect/retry", RETRY)
    if _get(cfg, "transport/link/tx/lease") == _ZENOH_DEFAULT_LEASE_MS:
        _set(cfg, "transport/link/tx/lease", LEASE_MS)
    if tls is not None:
        for field, value in tls.settings().items():
            _set(cfg, f"transport/link/tls/{field}", value)
    if not require_certs:
        return cfg
    check_tls(cfg)
    if uses_tls(cfg) and not (_get(cfg, "transport/link/tls") or {}).get("root_ca_certificate"):
        raise ZenohConfigError("a tls/ endpoint needs certificates: give the folder made by "
                               "`ovamos certs` (--certs DIR --cert NAME)")
    return cfg


_STACK_HINT = "is the stack up? `ovamos up` / `ovamos demo --keep-running`"


def open_session(cfg: zenoh.Config) -> zenoh.Session:
    """Open a session; a bad endpoint or a taken port becomes one clear error, and no router
    within the open timeout (``build_config(open_timeout_s=...)``) a
    :class:`RouterUnreachableError` naming the endpoints tried."""
    try:
        return zenoh.open(cfg)
    except zenoh.ZError as exc:
        timeout_ms = _get(cfg, "connect/timeout_ms")
        if isinstance(timeout_ms, dict):  # Zenoh also takes one per mode
            timeout_ms = timeout_ms.get(_get(cfg, "mode"))
        if "Timeout" in str(exc) and isinstance(timeout_ms, int) and timeout_ms >= 0:
            tried = ", ".join(map(str, _endpoints(cfg, "connect")))
            raise RouterUnreachableError(f"no Zenoh router answered at {tried} within {timeout_ms / 1000:g} s "
                                         f"({_STACK_HINT})") from None
        endpoints = {k: _get(cfg, f"{k}/endpoints") for k in ("listen", "connect")}
        raise ZenohConfigError(f"cannot open a Zenoh {_get(cfg, 'mode')} session "
                               f"({endpoints}): {exc}") from None
