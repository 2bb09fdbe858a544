"""Zenoh session configuration with this project's safe defaults.

Defaults follow what was measured for this deployment (docs/design.md, "Deployment and Zenoh"):
services are clients of a router on loopback, wait for it forever and reconnect
quickly after a router restart, and notice a hung peer within ~3 s. Multicast
scouting is always off: on a shared network it would make a robot join
strangers' Zenoh traffic, so a config file that turns it on is refused.

TLS (the link between the laptop's and the robot's routers): ``tls=`` a
:class:`TlsFiles` (a certificate folder made by ``ovamos certs`` and this host's
role) fills ``transport.link.tls`` for mutual authentication. Whatever the
source of a TLS setting (that argument or a config file), the certificates it
names are checked before Zenoh sees them (:func:`check_tls`: each key its
certificate's and its owner's alone, the CA writable by its owner only, all valid
now): a fault is a :class:`ZenohConfigError` saying what to do, not a link that
silently never comes up. A router with a ``tls/`` link keeps its plain listeners on
loopback (:func:`check_plain_listeners`).
"""

from __future__ import annotations

import ipaddress
import json
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import zenoh

from ovamos.shared.certs import CA_CERT, CertError, CertInfo, check_ca, check_certificate, check_key

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


#: ``transport.link.tls``'s (certificate, its key) pairs: for accepting links, and for opening them
_TLS_PAIRS = (("listen_certificate", "listen_private_key"), ("connect_certificate", "connect_private_key"))


def check_tls(cfg: zenoh.Config) -> list[CertInfo]:
    """Check every certificate and key ``transport.link.tls`` names: the CA (:func:`check_ca`),
    and each certificate valid now with its own key (:func:`check_key`); returns what was found,
    the CA first, each file once. Raises :class:`ZenohConfigError`."""
    tls = tls_settings(cfg)
    found: dict[str, CertInfo] = {}
    try:
        if tls.get("root_ca_certificate"):
            found[tls["root_ca_certificate"]] = check_ca(tls["root_ca_certificate"])
        for cert, key in _TLS_PAIRS:
            if tls.get(cert):
                found.setdefault(tls[cert], check_certificate(tls[cert]))
            if tls.get(key):
                check_key(tls[key], tls.get(cert))
    except CertError as exc:
        raise ZenohConfigError(str(exc)) from None
    return list(found.values())


def endpoint_host(endpoint: str) -> str | None:
    """The host of ``proto/host:port[#...]`` (an IPv6 address without its brackets); None for an
    endpoint without one (a unix socket)."""
    proto, sep, rest = endpoint.partition("/")
    address = rest.split("#", 1)[0].split("?", 1)[0]
    if not sep or proto.startswith("unix") or ":" not in address:
        return None
    host = address.rsplit(":", 1)[0]
    return host[1:-1] if host.startswith("[") and host.endswith("]") else host


def _on_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False  # a DNS name: it may resolve anywhere


def check_plain_listeners(cfg: zenoh.Config) -> None:
    """A router with a ``tls/`` link listens without TLS on loopback only: a plain listener on
    another address (``tcp/0.0.0.0``, the host's address on the robot network) would let anyone
    on that network in without a certificate, and the access control's ``local`` subject (the
    loopback interface) is the second line, not the first. Raises :class:`ZenohConfigError`."""
    if not uses_tls(cfg):
        return
    for endpoint in endpoints(cfg, "listen"):
        host = endpoint_host(endpoint)
        if not endpoint.startswith("tls/") and host is not None and not _on_loopback(host):
            raise ZenohConfigError(f"listen endpoint {endpoint} is plain (no TLS) and not on loopback: on a "
                                   f"router with a tls/ link, anyone who reaches {host} would get in without "
                                   f"a certificate; listen on tcp/127.0.0.1:PORT for this host's services and "
                                   f"put the other host's link on tls/")


def uses_tls(cfg: zenoh.Config) -> bool:
    """Whether the config listens on or connects to a ``tls/`` endpoint."""
    return any(e.startswith("tls/") for kind in ("listen", "connect") for e in endpoints(cfg, kind))


def endpoints(cfg: zenoh.Config, kind: Literal["listen", "connect"]) -> list[str]:
    """The ``listen`` or ``connect`` endpoints: a list, or (Zenoh takes both) a list per mode."""
    value = _get(cfg, f"{kind}/endpoints")
    return [str(e) for e in ([e for v in value.values() for e in v] if isinstance(value, dict) else value or [])]


def tls_settings(cfg: zenoh.Config) -> dict[str, Any]:
    """``transport.link.tls`` as set (empty without)."""
    value = _get(cfg, "transport/link/tls")
    return value if isinstance(value, dict) else {}


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
    if uses_tls(cfg) and not tls_settings(cfg).get("root_ca_certificate"):
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
            tried = ", ".join(endpoints(cfg, "connect"))
            raise RouterUnreachableError(f"no Zenoh router answered at {tried} within {timeout_ms / 1000:g} s "
                                         f"({_STACK_HINT})") from None
        configured = {k: _get(cfg, f"{k}/endpoints") for k in ("listen", "connect")}
        raise ZenohConfigError(f"cannot open a Zenoh {_get(cfg, 'mode')} session "
                               f"({configured}): {exc}") from None
