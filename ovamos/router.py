"""``ovamos router``: a Zenoh router (a Python session in router mode), with its access control
reported.

With ``access_control`` enabled (the secure profiles' routers), every message the
rules refuse is logged, sampled per sender and key, and counted per key in the
router's stats (:mod:`shared.acl` reads them from Zenoh's trace); the router then
answers ``ovamos status`` as service ``router`` with a liveliness token, like any
service. A TLS handshake Zenoh refused (no certificate, another CA) is logged too.
"""

from __future__ import annotations

import json
import logging
import re
import threading
from collections import Counter
from collections.abc import Callable

import zenoh

from shared.acl import AclMonitor, Denial
from shared.bus import Bus
from shared.log import fields, sampled
from shared.zconfig import check_tls, open_session

log = logging.getLogger("ovamos.router")
_AFTER_THREAD = re.compile(r"ThreadId\(\d+\)\s+(.*)$")


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


def run_router(cfg: zenoh.Config, *, robot_id: str, name: str, stop: threading.Event,
               on_open: Callable[[], None] = lambda: None) -> None:
    """Open the router session and hold it until ``stop`` is set."""
    acl = json.loads(cfg.get_json("access_control"))
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
    for cert in check_tls(cfg):
        log.info("TLS certificate %s", cert)
    log.info("router %s listening on %s%s", session.zid(), cfg.get_json("listen/endpoints"),
             ", access control on (default: %s)" % acl.get("default_permission") if denials else "")
    try:
        stop.wait()
    finally:
        if bus is not None:
            bus.close()  # closes the session too
        else:
            session.close()
