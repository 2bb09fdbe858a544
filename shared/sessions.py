"""Following the driver's odometry session on evidence, not on one message.

A message's ``odom_session`` is no proof: any process on the laptop, anyone on the plain link, a
stolen robot certificate or a recording replayed onto the live robot id can send one message of a
made-up session (``20991231T235959Z-ffffff``, ``""``). A consumer that followed it at once would
drop every real message afterwards as "of a session left behind" until restarted. So a session
becomes the current one only on the evidence of a restarted driver (:class:`SessionSwitch`): a
sustained stream of it (``messages`` messages, each ordered after the one before, spanning at
least ``min_span_s``) while the current session has gone quiet (nothing for ``quiet_s``). A forged
message, or a forged stream while the real driver still talks, is counted and ignored; a real
restart (the old session silent, the new one streaming) switches within about
``max(quiet_s, min_span_s)``. With no current session yet the first one seen is taken at once
(nothing can be lost, and a wrong one goes quiet and is replaced by the real stream). A session
left is never followed again: a driver never reuses one, so its messages are late or replayed.

Times are the consumer's own monotonic clock at receipt: stamps in messages are the sender's word.
"""

from __future__ import annotations

import logging
import math
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass

from pydantic import Field

from ovamos.shared.config import StrictModel
from ovamos.shared.log import sampled

__all__ = ["SessionSwitch", "SessionFollower", "Evidence"]


class SessionSwitch(StrictModel):
    """When a consumer follows a new odometry session (see :mod:`ovamos.shared.sessions`)."""

    messages: int = Field(
        default=5, ge=1,
        description="messages of the new session needed, each ordered after the one before (odometry "
                    "and frames: a higher seq; driver states: a later stamp); a message out of order "
                    "starts the count again, one repeated adds nothing")
    min_span_s: float = Field(
        default=0.1, ge=0,
        description="the first and last of those messages arrive at least this far apart (receipt time): "
                    "a burst is not a stream")
    quiet_s: float = Field(
        default=0.5, ge=0,
        description="the current session has sent nothing for at least this long (receipt time): a "
                    "driver that still talks has not restarted")


@dataclass
class Evidence:
    """A candidate session's stream so far (and, at a switch, what it was switched on)."""

    session: str
    messages: int
    first_at: float
    last_at: float
    last_order: float
    quiet_for: float = 0.0

    def describe(self) -> str:
        if math.isinf(self.quiet_for):
            return "its first message, with no session followed (a start, or the source back after it was gone)"
        return (f"{self.messages} messages in order over {self.last_at - self.first_at:.2f} s, "
                f"the session before quiet for {self.quiet_for:.2f} s")


class SessionFollower:
    """The current session of one driver, changed only on evidence (the module's rule).

    ``observe`` every message (``stream``: which of the consumer's inputs it came on; each stream
    has its own order, e.g. odometry seq and frame seq); it says whether the message is of the
    current session (after a switch it may have just become so). Messages of any other session are
    counted in ``stray`` by stream, the latest switch's evidence is in ``switched_on``.
    """

    def __init__(self, rule: SessionSwitch, current: str | None = None,
                 clock: Callable[[], float] = time.monotonic) -> None:
        """``current``: a session known before any message (a held checkpoint's), taken as quiet."""
        self.rule, self.current, self._clock = rule, current, clock
        self._current_at = -math.inf              # receipt of the current session's newest message
        self._candidates: dict[str, Evidence] = {}  # by stream
        self.stray: Counter[str] = Counter()       # messages of a session not followed, by stream
        self.switches = 0
        self.switched_on: Evidence | None = None
        self.left: set[str] = set()                # sessions that were current
        self._reconnected_from: str | None = None  # the session before a reconnection

    def observe(self, stream: str, session: str, order: float) -> bool:
        """Whether a message (``order``: its seq or stamp) is of the current session, after
        taking it as evidence for a switch."""
        now = self._clock()
        if self.current is None:
            self._switch(Evidence(session, 1, now, now, order, math.inf))
        if session == self.current:
            self._current_at = now
            self._candidates.pop(stream, None)  # the current session talks: no stream of another
            return True
        ev = self._candidates.get(stream)
        if session in self.left:
            self.stray[stream] += 1
            return False
        if ev is not None and ev.session == session and order == ev.last_order:
            self.stray[stream] += 1  # the same message again (a re-published frame): no evidence
            return False
        if ev is None or ev.session != session or order < ev.last_order:
            ev = self._candidates[stream] = Evidence(session, 0, now, now, order)
        ev.messages, ev.last_at, ev.last_order = ev.messages + 1, now, order
        ev.quiet_for = now - self._current_at
        if (ev.messages >= self.rule.messages and ev.last_at - ev.first_at >= self.rule.min_span_s
                and ev.quiet_for >= self.rule.quiet_s):
            self._switch(ev)
            self._current_at = now
            return True
        self.stray[stream] += 1
        return False

    def admit(self, stream: str, session: str, order: float, log: logging.Logger) -> bool:
        """:meth:`observe`, saying in ``log`` (sampled) what it ignored: the one warning every
        consumer that logs its strays gives."""
        if self.observe(stream, session, order):
            return True
        if sampled(self.stray[stream]):
            log.warning("ignored %s %s of odometry session %r: the driver's is %r and no sustained stream of %r "
                        "says it restarted (%d such so far)", stream.replace("_", " "), order, session,
                        self.current, session, self.stray[stream])
        return False

    def reconnected(self) -> None:
        """The driver's source was gone (its liveliness lost) and is back: the next message's
        session is taken at once, as at the start, since a restarted driver is expected. The
        session before is not left: a driver that only lost its link goes on with it."""
        if self.current is not None:
            self._current_at, self._candidates = -math.inf, {}
            self.current, self._reconnected_from = None, self.current

    def _switch(self, ev: Evidence) -> None:
        left = self.current if self.current is not None else self._reconnected_from
        if left is not None and left != ev.session:
            self.left.add(left)
        self._reconnected_from = None
        self.current, self.switched_on = ev.session, ev
        self.switches += 1
        self._candidates.clear()

    def info(self) -> dict[str, object]:
        """For a service's info: the session, strays counted, the candidates' streams."""
        return {"session": self.current, "stray": dict(self.stray), "switches": self.switches,
                "candidates": {s: {"session": e.session, "messages": e.messages}
                               for s, e in self._candidates.items()}}
