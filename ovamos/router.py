"""``ovamos router``: a Zenoh router (a Python session in router mode), with its access control
reported.

With ``access_control`` enabled (the secure profiles' routers), every message the
rules refuse is logged, sampled per sender and key, and counted per key in the
router's stats (:mod:`ovamos.shared.bus.acl` reads them from Zenoh's trace); the router then
answers ``ovamos status`` as service ``router`` with a liveliness token, like any
service. A TLS handshake Zenoh refused (no certificate, another CA) is logged too.

Before it opens, a router checks what would otherwise fail only on the other host: its
certificates (:func:`ovamos.shared.bus.zconfig.check_tls`, each logged with its days left, a warning
within :data:`~ovamos.shared.certs.EXPIRY_WARNING_DAYS`, an error when one expires while it runs),
that its plain listeners are on loopback (:func:`ovamos.shared.bus.zconfig.check_plain_listeners`), that
its certificate names the addresses its ``tls/`` listeners are reached at, and, once open, what
the peer at each ``tls/`` connect endpoint presents (:func:`check_peer`: another CA, expired,
or not naming the address this router dials, which the peer would otherwise only answer with
``BadCertificate`` in its own log). The robots' certificates are bound to their own keys
(:func:`ovamos.shared.bus.acl.bind_robots`).
"""

from __future__ import annotations

import datetime as dt
import json
import logging
import re
import socket
import ssl
import threading
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import zenoh
from cryptography import x509
from cryptography.exceptions import InvalidSignature

from ovamos.shared.bus import Bus
from ovamos.shared.bus.acl import AclConfigError, AclMonitor, Denial, bind_robots
from ovamos.shared.bus.zconfig import (
    ZenohConfigError,
    check_plain_listeners,
    check_tls,
    endpoint_host,
    endpoints,
    open_session,
    tls_settings,
)
from ovamos.shared.certs import EXPIRY_WARNING_DAYS, CertInfo, certificate_info, check_certificate
from ovamos.shared.log import fields, sampled

log = logging.getLogger("ovamos.router")
_AFTER_THREAD = re.compile(r"ThreadId\(\d+\)\s+(.*)$")
#: how often a tls/ peer that did not answer is tried again by :func:`check_peer`
PEER_RETRY_S = 5.0
_UNSPECIFIED = {"0.0.0.0", "::"}


class DenialLog:
    """Counts denials per key on the router's bus (``denied``) and per sender in its info."""

    def __init__(self) -> None:
        self.bus: Bus | None = None
        self.by_sender: Counter[str] = Counter()
        self.tls_refused = 0
        self._lock = threading.Lock()

    def on_denial(self, denial: Denial) -> None:
        what = denial.describe()
        with self._lock:
            self.by_sender[what] += 1
            n = self.by_sender[what]
            self._publish_info()
        if self.bus is not None:
            self.bus.counters.bump(denial.key, "denied")
        if sampled(n):
            level = logging.WARNING if denial.flow == "ingress" else logging.INFO
            log.log(level, "access control denied %s (%d so far)", what, n,
                    extra=fields(key=denial.key, cn=denial.common_name, message=denial.message,
                                 flow=denial.flow, count=n))

    def on_notice(self, level: str, text: str) -> None:
        if "zenoh_link_tls" in text:
            with self._lock:
                self.tls_refused += 1
                self._publish_info()
        log.log(logging.WARNING if level in ("WARN", "ERROR") else logging.INFO, "zenoh: %s", _notice(text))

    def _publish_info(self) -> None:
        if self.bus is not None:
            self.bus.info = {"access_control": {"denied": sum(self.by_sender.values()),
                                                "by": dict(self.by_sender.most_common(50)),
                                                "tls_refused": self.tls_refused}}


def _notice(text: str) -> str:
    """``zenoh_link_tls::unicast: invalid peer certificate: UnknownIssuer`` from a whole log line
    (without its time, thread, and the hint about file limits Zenoh adds to every link error)."""
    match = _AFTER_THREAD.search(text)
    text = match.group(1) if match else text
    return text.replace(" Hint: increase the system open file limit.", "").strip()


def log_certificates(certs: Sequence[CertInfo]) -> None:
    """Each certificate with its days left: a warning when it expires soon."""
    for cert in certs:
        days = cert.days_left()
        soon = days < EXPIRY_WARNING_DAYS
        log.log(logging.WARNING if soon else logging.INFO, "TLS certificate %s%s", cert.describe(),
                f": it expires in {days} days, issue a new one (`ovamos certs issue DIR {cert.common_name} --force`)"
                if soon and not cert.is_ca else "", extra=fields(cn=cert.common_name, days_left=days))


def check_listen_names(cfg: zenoh.Config) -> list[str]:
    """Warnings for ``tls/`` listeners at an address this router's certificate does not name: a peer
    dialling it refuses the certificate, and only the peer's log would say so."""
    path = tls_settings(cfg).get("listen_certificate")
    if not path:
        return []
    cert = check_certificate(path)
    hosts = [h for e in endpoints(cfg, "listen") if e.startswith("tls/")
             if (h := endpoint_host(e)) is not None and h not in _UNSPECIFIED]
    return [f"this router listens on tls/{host} but its certificate {cert.path} (CN {cert.common_name}) names "
            f"only {', '.join(cert.hosts) or 'nothing'}: a peer connecting to {host} will refuse it; issue it "
            f"again with that host: `ovamos certs issue DIR {cert.common_name} --host {host} ... --force`"
            for host in hosts if not cert.names(host)]


@dataclass(frozen=True)
class PeerCheck:
    """What :func:`check_peer` found at a ``tls/`` endpoint."""

    reached: bool
    problem: str = ""                # "" when the link can come up
    cert: CertInfo | None = None     # what the peer presented


def check_peer(endpoint: str, tls: dict[str, Any], timeout_s: float = 3.0) -> PeerCheck:
    """Open a TLS connection to ``endpoint`` with this router's certificate and judge the peer's as
    Zenoh's link would, with the reason: Zenoh itself says only "invalid peer certificate" here
    and ``BadCertificate`` on the peer."""
    host = endpoint_host(endpoint)
    assert host is not None
    port = int(endpoint.split("#", 1)[0].rsplit(":", 1)[1])
    context = ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT)
    context.check_hostname, context.verify_mode = False, ssl.CERT_NONE  # judged below, with the reasons
    context.load_cert_chain(tls["connect_certificate"], tls["connect_private_key"])
    try:
        with socket.create_connection((host, port), timeout=timeout_s) as raw, \
                context.wrap_socket(raw, server_hostname=host) as conn:
            der = conn.getpeercert(binary_form=True)
            refused = _refused(conn)
    except ssl.SSLError as exc:
        return PeerCheck(True, f"the peer at {endpoint} refused the TLS handshake: {exc}")
    except OSError:
        return PeerCheck(False)
    if der is None:
        return PeerCheck(True, f"the peer at {endpoint} presented no certificate")
    cert = x509.load_der_x509_certificate(der)
    peer = certificate_info(cert, endpoint)
    ca = x509.load_pem_x509_certificate(Path(tls["root_ca_certificate"]).read_bytes())
    who = f"the peer at {endpoint} (CN {peer.common_name})"
    try:
        cert.verify_directly_issued_by(ca)
    except (ValueError, TypeError, InvalidSignature):
        return PeerCheck(True, f"{who} has a certificate of another CA than this router's", peer)
    if peer.days_left() < 0:
        return PeerCheck(True, f"{who} has a certificate that expired on {peer.not_after:%Y-%m-%d}: it needs "
                               f"a new one (`ovamos certs issue DIR {peer.common_name} --force`)", peer)
    if not peer.names(host):
        return PeerCheck(True, f"{who} has a certificate that names only {', '.join(peer.hosts) or 'nothing'}, "
                               f"not {host}: this router refuses it and the peer logs BadCertificate; issue "
                               f"the peer's certificate again with `ovamos certs issue DIR {peer.common_name} "
                               f"--host {host} ... --force`, or connect to a host it names", peer)
    if refused:
        return PeerCheck(True, f"{who} refused this router's certificate: {refused}", peer)
    return PeerCheck(True, "", peer)


def _refused(conn: ssl.SSLSocket) -> str:
    """With TLS 1.3 the server judges the client's certificate after the handshake: its alert, if it
    sends one at once; "" when it waits for the session to begin (Zenoh's accepted link)."""
    conn.settimeout(0.5)
    try:
        conn.recv(1)
    except ssl.SSLError as exc:
        return str(exc)
    except OSError:  # the timeout: nothing said
        pass
    return ""


def watch_peers(cfg: zenoh.Config, stop: threading.Event) -> None:
    """:func:`check_peer` each ``tls/`` connect endpoint until it answers (every
    :data:`PEER_RETRY_S`), then log what it presented: its expiry, or the problem, loudly."""
    tls = tls_settings(cfg)
    todo = [e for e in endpoints(cfg, "connect") if e.startswith("tls/") and endpoint_host(e) is not None]
    while todo and not stop.is_set():
        for endpoint in list(todo):
            found = check_peer(endpoint, tls)
            if not found.reached:
                continue
            todo.remove(endpoint)
            if found.problem:
                log.error("TLS link %s will not come up: %s", endpoint, found.problem,
                          extra=fields(endpoint=endpoint))
            elif found.cert is not None:
                log.info("TLS peer %s", found.cert.describe(),
                         extra=fields(endpoint=endpoint, cn=found.cert.common_name, days_left=found.cert.days_left()))
        if todo:
            stop.wait(PEER_RETRY_S)


def _hold(stop: threading.Event, certs: Sequence[CertInfo]) -> None:
    """Wait for ``stop``; an error when one of ``certs`` expires meanwhile (Zenoh closes the links
    that use it, and without this line the holder's log would not say why)."""
    pending = sorted(certs, key=lambda c: c.not_after)
    while True:
        left = (pending[0].not_after - dt.datetime.now(dt.timezone.utc)).total_seconds() if pending else None
        if stop.wait(None if left is None else max(0.0, left)):
            return
        cert = pending.pop(0)
        log.error("TLS certificate %s has expired: the links that use it are closed; issue a new one "
                  "(`ovamos certs issue DIR %s --force`) and restart", cert.path, cert.common_name,
                  extra=fields(cn=cert.common_name))


def run_router(cfg: zenoh.Config, *, robot_id: str, name: str, stop: threading.Event,
               robots: Sequence[str] = (), on_open: Callable[[], None] = lambda: None) -> None:
    """Check the config (see the module docstring), open the router session and hold it until
    ``stop`` is set. ``robots``: the robots a laptop router's access control binds (default: the
    one robot ``robot_id``)."""
    check_plain_listeners(cfg)
    certs = check_tls(cfg)
    acl = json.loads(cfg.get_json("access_control"))
    try:
        bound = bind_robots(acl, list(robots) or [robot_id])
    except AclConfigError as exc:
        raise ZenohConfigError(str(exc)) from None
    if bound is not acl:
        cfg.insert_json5("access_control", json.dumps(bound))
    denials: DenialLog | None = None
    if acl.get("enabled"):
        denials = DenialLog()
        AclMonitor(denials.on_denial, denials.on_notice).start()
    session = open_session(cfg)
    on_open()
    bus = None
    if denials is not None:
        bus = denials.bus = Bus(session, robot_id, "router", name)
        denials._publish_info()
    log_certificates(certs)
    for warning in check_listen_names(cfg):
        log.warning("%s", warning)
    threading.Thread(target=watch_peers, args=(cfg, stop), name="tls-peers", daemon=True).start()
    log.info("router %s listening on %s%s", session.zid(), cfg.get_json("listen/endpoints"),
             ", access control on (default: %s)" % acl.get("default_permission") if denials else "")
    try:
        _hold(stop, certs)
    finally:
        if bus is not None:
            bus.close()  # closes the session too
        else:
            session.close()
