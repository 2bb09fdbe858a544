"""A router's access control: each robot's certificate bound to its own keys, and what the rules
refused, each denial logged (sampled) and counted.

Robots' identities (:func:`bind_robots`): the laptop's router config names one subject,
``robot``, and the rules a robot gets over ``ovamos/*/...`` keys. At start-up it becomes one
subject per robot, certificate CN ``robot-<id>`` (``ovamos certs issue DIR robot-<id>``; the one
robot of a single-robot deployment may keep CN ``robot``), whose rules name that robot's keys
(``ovamos/<id>/...``) for what it asserts and what it is sent: its puts, liveliness tokens,
queryables, replies and subscriptions in, the puts out. A stolen robot key therefore cannot
publish another robot's frames or odometry, nor read its commands. The laptop's own interest
(its subscriptions and queries out, a robot's queries in) keeps ``ovamos/*``: ``ovamos status``
and a perception serving every robot ask with wildcards, and asking grants nothing.

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
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import zenoh

log = logging.getLogger("ovamos.acl")

#: the subject of a laptop router's config that stands for every robot (see :func:`bind_robots`)
ROBOT_SUBJECT = "robot"
#: how the rules of :data:`ROBOT_SUBJECT` name any robot's keys
_ANY_ROBOT = "ovamos/*/"
#: (flow, message) of a robot's rules bound to its own keys: what it asserts, and what it is sent
_BOUND = frozenset({("ingress", m) for m in ("put", "delete", "declare_subscriber", "liveliness_token",
                                             "declare_queryable", "reply")} | {("egress", "put"), ("egress", "delete")})


class AclConfigError(ValueError):
    """An access-control config this project cannot bind to its robots."""


def robot_common_names(robot: str, *, only: bool) -> list[str]:
    """The certificate CNs that speak for ``robot``: ``robot-<id>``, and for the ``only`` robot of a
    single-robot deployment also plain ``robot`` (the name its certificates always had)."""
    return [f"{ROBOT_SUBJECT}-{robot}", *([ROBOT_SUBJECT] if only else [])]


def _bind_rule(rule: dict[str, Any], robot: str) -> list[dict[str, Any]]:
    """``rule`` for one robot: split per flow into the part bound to ``ovamos/<robot>/`` (its
    messages in :data:`_BOUND`) and the part that keeps its keys."""
    out = []
    for flow in rule["flows"]:
        bound = [m for m in rule["messages"] if (flow, m) in _BOUND]
        free = [m for m in rule["messages"] if (flow, m) not in _BOUND]
        for messages, tag in ((bound, "own"), (free, "any")):
            if not messages:
                continue
            keys = rule["key_exprs"]
            if tag == "own":
                wrong = [k for k in keys if not k.startswith(_ANY_ROBOT)]
                if wrong:
                    raise AclConfigError(f"access control rule {rule['id']!r} of subject {ROBOT_SUBJECT!r} names "
                                         f"{', '.join(wrong)}: a robot's keys are {_ANY_ROBOT}..., bound to each "
                                         f"robot's own at start-up")
                keys = [f"ovamos/{robot}/{k[len(_ANY_ROBOT):]}" for k in keys]
            out.append({**rule, "id": f"{rule['id']}/{flow}/{tag}/{robot}", "flows": [flow],
                        "messages": messages, "key_exprs": keys})
    return out


def bind_robots(acl: dict[str, Any], robots: Sequence[str]) -> dict[str, Any]:
    """``access_control`` with its :data:`ROBOT_SUBJECT` replaced by one subject per robot, each
    allowed its policies' rules on its own keys only (the module docstring says which); unchanged
    without that subject (a robot's router, where every robot-side peer is this one robot)."""
    if not acl.get("enabled"):
        return acl
    template = next((s for s in acl.get("subjects") or [] if s["id"] == ROBOT_SUBJECT), None)
    if template is None:
        return acl
    if not robots:
        raise AclConfigError(f"access control subject {ROBOT_SUBJECT!r} needs the robots it stands for")
    all_rules, all_policies = acl.get("rules") or [], acl.get("policies") or []
    rules = {r["id"]: r for r in all_rules}
    policies = [p for p in all_policies if ROBOT_SUBJECT in p["subjects"]]
    if any(p["subjects"] != [ROBOT_SUBJECT] for p in policies):
        raise AclConfigError(f"access control subject {ROBOT_SUBJECT!r} must have policies of its own")
    subjects = [s for s in acl["subjects"] if s["id"] != ROBOT_SUBJECT]
    kept = [p for p in all_policies if p not in policies]
    bound_rules = []
    for robot in robots:
        subject = f"{ROBOT_SUBJECT}-{robot}"
        subjects.append({**template, "id": subject,
                         "cert_common_names": robot_common_names(robot, only=len(robots) == 1)})
        for policy in policies:
            own = [b for rule_id in policy["rules"] for b in _bind_rule(rules[rule_id], robot)]
            bound_rules += own
            kept.append({**policy, "id": f"{policy.get('id', ROBOT_SUBJECT)} ({robot})", "subjects": [subject],
                         "rules": [r["id"] for r in own]})
    used = {r for p in kept for r in p["rules"]}
    return {**acl, "subjects": subjects, "policies": kept,
            "rules": [r for r in all_rules if r["id"] in used] + bound_rules}

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
