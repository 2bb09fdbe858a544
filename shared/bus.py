"""The Zenoh runtime of one service instance: typed publish/subscribe, counters, health.

A :class:`Bus` owns one Zenoh session and everything declared on it. It is the
only place where bytes become messages, so every service gets the same
guarantees for free: payloads are validated on receipt, a malformed one is
logged, counted and dropped, a handler that raises is logged and counted, and
neither ever reaches Zenoh's threads (which would swallow the exception).

Threads: a plain subscription runs its handler on a Zenoh thread, one per
subscription; a ``latest_only`` subscription hands samples to its own worker
thread through a one-slot mailbox, so a slow consumer drops stale frames
(counted) instead of queueing them without bound. Handlers of different
subscriptions can run concurrently: services lock their shared state.
"""

from __future__ import annotations

import logging
import os
import threading
import time
from collections import defaultdict
from typing import Any, Generic, Protocol, Self, TypeVar
from collections.abc import Callable

import zenoh

from shared import keys
from shared.log import fields, sampled
from shared.messages import CounterSet, DecodeError, ServiceStats
from shared.zconfig import open_session

log = logging.getLogger("ovamos.bus")


class Codec(Protocol):
    """What the bus needs of a message type (JsonMessage and BinaryMessage both qualify)."""

    def to_bytes(self, out: bytearray | None = None) -> bytes | bytearray: ...

    @classmethod
    def from_bytes(cls, data: bytes) -> Self: ...


M = TypeVar("M", bound=Codec)


class Counters:
    """Per-key message counters, safe to bump from any thread."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._by_key: dict[str, CounterSet] = defaultdict(CounterSet)

    def bump(self, key: str, counter: str, n: int = 1) -> int:
        with self._lock:
            entry = self._by_key[key]
            value = getattr(entry, counter) + n
            setattr(entry, counter, value)
            return value

    def snapshot(self) -> dict[str, CounterSet]:
        with self._lock:
            return {k: v.model_copy() for k, v in self._by_key.items()}


class Publisher(Generic[M]):
    """Publishes messages of one type on one key."""

    def __init__(self, bus: Bus, key: str, msg_type: type[M], **options: Any) -> None:
        self.key, self.msg_type, self._bus = key, msg_type, bus
        self._pub = bus.session.declare_publisher(key, **options)
        self._lock = threading.Lock()
        # Zenoh copies the payload during put(), so one buffer serves every message.
        self._buffer = bytearray()

    def put(self, msg: M) -> None:
        """Publish ``msg`` (thread-safe)."""
        if not isinstance(msg, self.msg_type):
            raise TypeError(f"{self.key} carries {self.msg_type.__name__}, got {type(msg).__name__}")
        with self._lock:
            self._pub.put(msg.to_bytes(self._buffer))
        self._bus.counters.bump(self.key, "published")

    def undeclare(self) -> None:
        self._pub.undeclare()


class _Mailbox:
    """Latest-only hand-off from Zenoh's thread to a worker thread.

    Zenoh's ``RingChannel(1)`` gives the same bounded memory but cannot say how
    many samples it overwrote; this one counts them as ``dropped``.
    """

    def __init__(self, name: str, deliver: Callable[[zenoh.Sample], None],
                 on_drop: Callable[[], Any]) -> None:
        self._cond = threading.Condition()
        self._slot: zenoh.Sample | None = None
        self._closed = False
        self._deliver, self._on_drop = deliver, on_drop
        self._thread = threading.Thread(target=self._loop, name=name, daemon=True)
        self._thread.start()

    def offer(self, sample: zenoh.Sample) -> None:
        with self._cond:
            if self._slot is not None:
                self._on_drop()
            self._slot = sample
            self._cond.notify()

    def _loop(self) -> None:
        while True:
            with self._cond:
                while self._slot is None and not self._closed:
                    self._cond.wait()
                if self._closed:
                    return
                sample, self._slot = self._slot, None
            self._deliver(sample)

    def close(self) -> None:
        with self._cond:
            self._closed = True
            self._cond.notify()
        if threading.current_thread() is not self._thread:
            self._thread.join(timeout=5)


class Subscription:
    """A declared subscriber; ``undeclare()`` stops delivery."""

    def __init__(self, sub: zenoh.Subscriber, mailbox: _Mailbox | None) -> None:
        self._sub, self._mailbox = sub, mailbox

    def undeclare(self) -> None:
        self._sub.undeclare()
        if self._mailbox is not None:
            self._mailbox.close()


def _check_identity(robot_id: str, service: str, instance: str) -> None:
    keys.check_chunk(robot_id, "robot id")
    keys.check_chunk(service, "service name")
    keys.check_chunk(instance, "instance")


class Bus:
    """One service instance's Zenoh session, with its liveliness token and stats queryable."""

    def __init__(self, session: zenoh.Session, robot_id: str, service: str, instance: str,
                 info: Callable[[], dict[str, Any]] | None = None) -> None:
        _check_identity(robot_id, service, instance)
        self.session = session
        self.robot_id, self.service, self.instance = robot_id, service, instance
        self.counters = Counters()
        self.log = logging.getLogger(f"ovamos.{service}.{instance}")
        self.started = time.time()
        self._info = info or dict
        self._declared: list[Any] = []  # keep references: a dropped declaration is undeclared
        self._closed = False
        self.queryable(keys.stats(robot_id, service, instance), lambda _query: self.stats())
        self._token = session.liveliness().declare_token(keys.alive(robot_id, service, instance))

    @classmethod
    def open(cls, cfg: zenoh.Config, robot_id: str, service: str, instance: str = "0",
             info: Callable[[], dict[str, Any]] | None = None) -> Bus:
        _check_identity(robot_id, service, instance)  # first: opening may wait for a router
        return cls(open_session(cfg), robot_id, service, instance, info)

    # -- declarations ---------------------------------------------------------------------
    def publisher(self, key: str, msg_type: type[M], **options: Any) -> Publisher[M]:
        pub = Publisher(self, key, msg_type, **options)
        self._declared.append(pub)
        return pub

    def subscribe(self, key: str, msg_type: type[M], handler: Callable[[M], None], *,
                  latest_only: bool = False) -> Subscription:
        """Deliver valid ``msg_type`` messages on ``key`` to ``handler``.

        ``latest_only`` is for streams where only the newest sample matters
        (frames, maps): the handler runs on a worker thread and samples that
        arrive while it is busy replace each other.
        """
        def deliver(sample: zenoh.Sample) -> None:
            msg = self.decode(key, msg_type, sample.payload.to_bytes())
            if msg is not None:
                handler(msg)

        return self._declare_subscriber(key, self._guard(deliver, key), latest_only)

    def subscribe_raw(self, key_expr: str, handler: Callable[[str, bytes], None]) -> Subscription:
        """Deliver every payload under ``key_expr`` undecoded, with its key (monitoring tools)."""
        def deliver(sample: zenoh.Sample) -> None:
            handler(str(sample.key_expr), sample.payload.to_bytes())

        return self._declare_subscriber(key_expr, self._guard(deliver, key_expr), False)

    def queryable(self, key: str, answer: Callable[[zenoh.Query], Codec]) -> None:
        """Answer queries on ``key`` with the message ``answer`` returns."""
        def reply(query: zenoh.Query) -> None:
            query.reply(key, answer(query).to_bytes())

        self._declared.append(self.session.declare_queryable(key, self._guard(reply, key)))

    def get(self, key: str, msg_type: type[M], timeout_s: float = 1.0) -> M | None:
        """Ask the queryable(s) on ``key``; the first valid answer, or None (none answered in
        time, or only malformed answers, which are counted)."""
        for reply in self.session.get(key, timeout=timeout_s):
            if reply.ok is not None:
                msg = self.decode(key, msg_type, reply.ok.payload.to_bytes())
                if msg is not None:
                    return msg
        return None

    def _declare_subscriber(self, key_expr: str, deliver: Callable[[zenoh.Sample], None],
                            latest_only: bool) -> Subscription:
        def count(sample: zenoh.Sample) -> None:
            self.counters.bump(str(sample.key_expr), "received")

        if latest_only:
            mailbox = _Mailbox(f"sub:{key_expr}", deliver,
                               lambda: self.counters.bump(key_expr, "dropped"))

            def on_sample(sample: zenoh.Sample) -> None:
                count(sample)
                mailbox.offer(sample)
        else:
            mailbox = None

            def on_sample(sample: zenoh.Sample) -> None:
                count(sample)
                deliver(sample)
        sub = Subscription(self.session.declare_subscriber(key_expr, on_sample), mailbox)
        self._declared.append(sub)
        return sub

    # -- errors ---------------------------------------------------------------------------
    def _guard(self, fn: Callable[[Any], None], key: str) -> Callable[[Any], None]:
        """Wrap a callback so an exception is logged and counted, never lost in Zenoh."""
        def guarded(arg: Any) -> None:
            try:
                fn(arg)
            except Exception:
                self.record_failure(key)
        return guarded

    def record_failure(self, key: str) -> None:
        """Count, and log (sampled), the exception being handled: call it in an except block."""
        n = self.counters.bump(key, "errors")
        if sampled(n):
            self.log.exception("%s: handler failed", key, extra=fields(key=key, count=n))

    def decode(self, key: str, msg_type: type[M], payload: bytes) -> M | None:
        """The message in ``payload``, or None (logged and counted) when it is malformed."""
        try:
            return msg_type.from_bytes(payload)
        except DecodeError as exc:
            n = self.counters.bump(key, "malformed")
            if sampled(n):
                self.log.warning("dropped malformed message: %s", exc, extra=fields(key=key, count=n))
            return None

    # -- health ---------------------------------------------------------------------------
    def stats(self) -> ServiceStats:
        return ServiceStats(robot_id=self.robot_id, service=self.service, instance=self.instance,
                            pid=os.getpid(), started=self.started,
                            counters=self.counters.snapshot(), info=self._info())

    def close(self) -> None:
        """Undeclare everything and close the session (idempotent)."""
        if self._closed:
            return
        self._closed = True
        self._token.undeclare()
        for item in reversed(self._declared):
            item.undeclare()
        self._declared.clear()
        self.session.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
