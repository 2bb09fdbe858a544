"""What a router's access control refused: each denial logged (sampled) and counted.

Zenoh's access control drops a message its rules do not allow without telling
anyone but its own trace log, which goes to the process's standard output. A
router with ``access_control`` enabled (``ovamos router``) therefore turns on
exactly that trace target, reads its own standard output through a pipe
(:class:`AclMonitor`), and for every message the interceptor dropped reports a
:class:`Denial`: who sent it (the certificate's common name), what it was
(``put``, ``declare_subscriber``, ...), the direction and the key. Every other
line is passed through unchanged, and Zenoh's warnings (a TLS handshake refused:
no certificate, another CA) are logged through Python's logging.

How a denial is recognised, from the trace (zenoh 1.10): for each message the
interceptor logs one ``... is authorized to`` / ``... is unauthorized to`` line
per subject it tries, then ``Msg intercepted!`` when the message is dropped,
all on the thread that routes it. The last refusal on a thread before its
``Msg intercepted!`` is the denial. For a TLS peer whose certificate matches no
other subject to be named in those lines, the shipped configs give every TLS
link a catch-all subject (``any-tls``) with no permissions.
"""

from __future__ import annotations

import logging
import os
import re
import threading
from collections.abc import Callable
from dataclasses import dataclass

import zenoh

log = logging.getLogger("ovamos.acl")

#: the trace target whose lines say what the access control allowed and refused
TRACE_TARGET = "zenoh::net::routing::interceptor"
_ANSI = re.compile(r"\x1b\[[0-9;]*m")
_THREAD = re.compile(r"ThreadId\((\d+)\)")
_VERDICT = re.compile(r"access_control: (?P<zid>[0-9a-f]+) on (?P<props>\S+) is (?P<verdict>un)?authorized "
                      r"to (?P<message>.+?) \((?P<flow>ingress|egress)\) on (?P<key>\S+)\s*$")
_CN = re.compile(r"CertCommonName\(([^)]*)\)")
_PROTO = re.compile(r"Transport\((\w+)\)")
_LEVEL = re.compile(r"\b(TRACE|DEBUG|INFO|WARN|ERROR)\b")


@dataclass(frozen=True)
class Denial:
    """One message the access control dropped."""

    common_name: str     # the sender's (ingress) or receiver's (egress) certificate CN; "" without one
    protocol: str        # the link's: tls, tcp, ...
    message: str         # as Zenoh names it: Put, Declare/Undeclare Subscriber, ...
    flow: str            # ingress (it came from that peer) or egress (it was not sent to it)
    key: str

    def describe(self) -> str:
        who = f"CN {self.common_name}" if self.common_name else f"a {self.protocol or 'peer'} link without a CN"
        direction = "from" if self.flow == "ingress" else "to"
        return f"{self.message} ({self.flow}) on {self.key} {direction} {who}"


class TraceParser:
    """Turns Zenoh's log lines into denials (see the module docstring); not thread-safe."""

    def __init__(self) -> None:
        self._refused: dict[str, Denial] = {}

    def feed(self, line: str) -> Denial | None:
        """The denial this line completes, if any."""
        line = _ANSI.sub("", line)
        if TRACE_TARGET not in line:
            return None
        thread = _THREAD.search(line)
        tid = thread.group(1) if thread else ""
        verdict = _VERDICT.search(line)
        if verdict is not None:
            if verdict.group("verdict"):
                props = verdict.group("props")
                cn, proto = _CN.search(props), _PROTO.search(props)
                self._refused[tid] = Denial(cn.group(1) if cn else "", proto.group(1).lower() if proto else "",
                                            verdict.group("message"), verdict.group("flow"), verdict.group("key"))
            else:
                self._refused.pop(tid, None)  # a later subject allowed it
            return None
        if line.rstrip().endswith("Msg intercepted!"):
            return self._refused.pop(tid, None) or Denial("", "", "message", "", "?")
        return None


def is_zenoh_notice(line: str) -> str | None:
    """The level of a Zenoh log line worth a person's attention (INFO and up, not the trace)."""
    clean = _ANSI.sub("", line)
    match = _LEVEL.search(clean[:80])
    if match is None or match.group(1) in ("TRACE", "DEBUG"):
        return None
    return match.group(1)


class AclMonitor:
    """Read this process's standard output (where Zenoh logs) and report denials.

    :meth:`start` must run before the router's session opens (it turns Zenoh's
    logging on). ``on_denial`` and ``on_notice(level, text)`` run on the monitor's
    thread; other output goes on to the original standard output.
    """

    def __init__(self, on_denial: Callable[[Denial], None],
                 on_notice: Callable[[str, str], None] | None = None) -> None:
        self.on_denial, self.on_notice = on_denial, on_notice
        self.parser = TraceParser()
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        read_fd, write_fd = os.pipe()
        self._out = os.fdopen(os.dup(1), "w", buffering=1, errors="replace")
        os.dup2(write_fd, 1)
        os.close(write_fd)
        self._thread = threading.Thread(target=self._run, args=(read_fd,), name="acl-monitor", daemon=True)
        self._thread.start()
        directives = f"warn,{TRACE_TARGET}=trace"
        user = os.environ.get("RUST_LOG")
        os.environ["RUST_LOG"] = f"{user},{TRACE_TARGET}=trace" if user else directives
        zenoh.try_init_log_from_env()

    def _run(self, fd: int) -> None:
        with os.fdopen(fd, "r", errors="replace") as lines:
            for line in lines:
                try:
                    self._line(line)
                except Exception:  # never stop reading: Zenoh would block on a full pipe
                    log.exception("could not handle a Zenoh log line")

    def _line(self, line: str) -> None:
        denial = self.parser.feed(line)
        if denial is not None:
            self.on_denial(denial)
            return
        level = is_zenoh_notice(line) if "zenoh" in line else None
        if level is not None:  # a warning, or the access control's own notes (a peer matching no subject)
            if self.on_notice is not None:
                self.on_notice(level, _ANSI.sub("", line).strip())
        elif TRACE_TARGET not in line:  # the verdicts are thousands a minute: only refusals matter
            self._out.write(line)
