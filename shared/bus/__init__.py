"""The Zenoh runtime of one service instance: typed publish/subscribe, counters, health.

A :class:`Bus` owns one Zenoh session and everything declared on it. It is the
only place where bytes become messages, so every service gets the same
guarantees for free: payloads are validated on receipt, a malformed one is
logged, counted and dropped, a handler that raises is logged and counted, and
neither ever reaches Zenoh's threads (which would swallow the exception).

Threads: Zenoh's callbacks only enqueue on the bus's :class:`~ovamos.shared.inbox.Inbox`;
handlers, query answers and request replies all run on one thread, the inbox's
taker (a service's main loop, see :func:`ovamos.shared.service.run_service`, or a
dispatcher thread of the bus for tools). A service's handlers therefore never
run concurrently with each other or with its tick, and need no locks. A
``keep=n`` subscription keeps only its newest ``n`` samples while the service
is busy, so a slow consumer drops stale frames (counted) instead of queueing
them without bound.
"""

from __future__ import annotations

import logging
import os
import socket
import threading
import time
from collections.abc import Callable
from typing import Any, Generic, Literal, Protocol, Self, TypeVar

import zenoh

from ovamos.shared import keys
from ovamos.shared.bus.shm import ShmPool
from ovamos.shared.bus.shm import enabled as shm_enabled
from ovamos.shared.bus.zconfig import open_session
from ovamos.shared.inbox import Inbox
from ovamos.shared.log import fields, sampled
from ovamos.shared.messages import CounterSet, DecodeError, ServiceStats

log = logging.getLogger("ovamos.bus")


class Codec(Protocol):
    """What the bus needs of a message type (JsonMessage and BinaryMessage both qualify)."""

    def to_bytes(self, out: bytearray | None = None) -> bytes | bytearray: ...

    @classmethod
    def from_bytes(cls, data: bytes) -> Self: ...


M = TypeVar("M", bound=Codec)


class Counters:
    """Per-key message counters, safe to bump from any thread.

    Plain integers, not :class:`CounterSet` models: every message bumps one on
    its hot path (in Zenoh's callback for a received frame), and a pydantic
    attribute write costs tens of microseconds there once a frame went through
    the caches; :meth:`snapshot` builds the models when someone asks.
    """

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._by_key: dict[str, dict[str, int]] = {}

    def bump(self, key: str, counter: str, n: int = 1) -> int:
        with self._lock:
            entry = self._by_key.get(key)
            if entry is None:
                entry = self._by_key[key] = dict.fromkeys(CounterSet.model_fields, 0)
            value = entry[counter] = entry[counter] + n
            return value

    def snapshot(self) -> dict[str, CounterSet]:
        with self._lock:
            return {k: CounterSet(**v) for k, v in self._by_key.items()}


class Publisher(Generic[M]):
    """Publishes messages of one type on one key."""

    def __init__(self, bus: BusCore, key: str, msg_type: type[M], *, block: bool = False) -> None:
        self.key, self.msg_type, self._bus = key, msg_type, bus
        self._put, self.undeclare = bus._publish(key, block)
        self._lock = threading.Lock()
        # The transport copies the payload during put(), so one buffer serves every message.
        self._buffer = bytearray()

    def put(self, msg: M) -> None:
        """Publish ``msg`` (thread-safe)."""
        if not isinstance(msg, self.msg_type):
            raise TypeError(f"{self.key} carries {self.msg_type.__name__}, got {type(msg).__name__}")
        with self._lock:
            self._put(msg.to_bytes(self._buffer))
        self._bus.counters.bump(self.key, "published")

    def put_bytes(self, payload: bytes) -> None:
        """Publish a payload already encoded as this key's message type, unchanged (a replayed
        recording goes back on the wire bit for bit; its subscribers validate it as usual)."""
        self._put(payload)
        self._bus.counters.bump(self.key, "published")


class Subscription:
    """A declaration (subscriber, queryable, liveliness token or watcher); ``undeclare()`` ends it,
    once: the bus undeclares everything again when it closes, and Zenoh refuses a second time."""

    def __init__(self, undeclare: Callable[[], None]) -> None:
        self._undeclare: Callable[[], None] | None = undeclare

    def undeclare(self) -> None:
        undeclare, self._undeclare = self._undeclare, None
        if undeclare is not None:
            undeclare()


def _check_identity(robot_id: str, service: str, instance: str) -> None:
    keys.check_chunk(robot_id, "robot id")
    keys.check_chunk(service, "service name")
    keys.check_chunk(instance, "instance")


class BusCore:
    """Everything a service sees of its bus, whatever carries the bytes.

    Declarations are typed; every callback from the transport only enqueues on
    :attr:`inbox`, and the handlers run when the inbox's taker (the service's
    main loop, or a dispatcher thread) gets to them. Subclasses provide the
    transport: :class:`Bus` (Zenoh) and :class:`ovamos.shared.fake_bus.FakeBus`.
    """

    def __init__(self, robot_id: str, service: str, instance: str, inbox: Inbox | None = None) -> None:
        _check_identity(robot_id, service, instance)
        self.robot_id, self.service, self.instance = robot_id, service, instance
        self.counters = Counters()
        self.log = logging.getLogger(f"ovamos.{service}.{instance}")
        self.started = time.time()
        self.wall_clock: Callable[[], float] = time.time  # the clock its stats answer says (``now``)
        self.host = socket.gethostname()  # where it runs, for its stats answer
        self.inbox = inbox or Inbox()
        #: what ``ovamos status`` shows of the service: a snapshot its own thread refreshes
        #: (:func:`ovamos.shared.service.run_loop`), so answering a stats query reads no live state
        self.info: dict[str, Any] = {}
        self._declared: list[Any] = []  # keep references: a dropped declaration is undeclared
        self._closed = False

    # -- transport (subclasses) -----------------------------------------------------------
    def _publish(self, key: str, block: bool = False
                 ) -> tuple[Callable[[bytes | bytearray], None], Callable[[], None]]:
        """The put and undeclare functions of a publisher on ``key``; ``block``: a put waits
        while the transport is congested (a slow subscriber) instead of dropping."""
        raise NotImplementedError

    def _listen(self, key_expr: str, on_payload: Callable[[str, Callable[[], bytes]], None]
                ) -> Callable[[], None]:
        """Call ``on_payload(key, read_payload)`` per sample; return the undeclare function."""
        raise NotImplementedError

    def _listen_buffered(self, key_expr: str, on_payload: Callable[[str, Callable[[], bytes]], None],
                         backlog: int) -> Callable[[], None]:
        """:meth:`_listen`, with up to ``backlog`` samples held by the transport until taken
        (a transport without such a buffer delivers at once)."""
        return self._listen(key_expr, on_payload)

    def _answer(self, key: str, on_query: Callable[[Callable[[bytes | bytearray], None],
                                                    Callable[[], None]], None]) -> Callable[[], None]:
        """Call ``on_query(reply, finish)`` per query; return the undeclare function."""
        raise NotImplementedError

    def _ask(self, key: str, timeout_s: float, on_reply: Callable[[bytes], None],
             on_done: Callable[[], None]) -> None:
        raise NotImplementedError

    def _token(self, key: str) -> Callable[[], None]:
        """Declare a liveliness token; return the undeclare function."""
        raise NotImplementedError

    def _watch_tokens(self, key_expr: str, on_change: Callable[[str, bool], None]) -> Callable[[], None]:
        """Call ``on_change(key, alive)`` for the tokens under ``key_expr``, those already declared
        first; return the undeclare function."""
        raise NotImplementedError

    # -- declarations ---------------------------------------------------------------------
    def publisher(self, key: str, msg_type: type[M], *, block: bool = False) -> Publisher[M]:
        """A publisher of ``msg_type`` on ``key``. ``block=True`` is for tools that may go as slowly
        as their subscribers (a replay at full speed): a put waits while a subscriber's link is
        congested. Services never block: a stalled subscriber must not stall the robot."""
        pub = Publisher(self, key, msg_type, block=block)
        self._declared.append(pub)
        return pub

    def subscribe(self, key: str, msg_type: type[M], handler: Callable[[M], None], *,
                  keep: int = 0) -> Subscription:
        """Deliver valid ``msg_type`` messages on ``key`` to ``handler`` (on the inbox's taker).

        ``keep=n`` is for streams where only the newest samples matter (frames,
        maps): while the handler is busy, only the newest ``n`` samples wait,
        the others are dropped and counted.
        """
        return self.subscribe_keyed(key, msg_type, lambda _key, msg: handler(msg), keep=keep)

    def subscribe_keyed(self, key_expr: str, msg_type: type[M], handler: Callable[[str, M], None], *,
                        keep: int = 0) -> Subscription:
        """:meth:`subscribe`, for a key expression that may match many keys (``ovamos/*/sensors/rgbd``):
        ``handler(key, msg)`` gets each message with its key, and ``keep=n`` keeps the newest ``n``
        of each key (each robot's), not of all of them together."""
        def deliver(sample: tuple[str, Callable[[], bytes]]) -> None:
            key, read = sample
            msg = self.decode(key, msg_type, read())
            if msg is not None:
                handler(key, msg)

        return self._subscribe(key_expr, self._guard(deliver, key_expr), keep)

    def subscribe_raw(self, key_expr: str, handler: Callable[[str, bytes], None]) -> Subscription:
        """Deliver every payload under ``key_expr`` undecoded, with its key (monitoring tools)."""
        def on_payload(key: str, read: Callable[[], bytes]) -> None:
            self.counters.bump(key, "received")
            self.inbox.put(self._guard(lambda _: handler(key, read()), key_expr), None)

        sub = Subscription(self._listen(key_expr, on_payload))
        self._declared.append(sub)
        return sub

    def tap(self, key_expr: str, handler: Callable[[str, bytes], None], *, backlog: int = 16) -> Subscription:
        """Call ``handler(key, payload)`` for every sample under ``key_expr``, past the inbox
        (counted as received; exceptions counted as errors), on a thread of the subscription.

        For a recorder that bounds its own queue by bytes: the inbox bounds events by count,
        and 10,000 RGB-D frames are 20 GB. The handler must only enqueue, never block. Up to
        ``backlog`` samples wait in the transport while this process is busy (a thread holding
        the GIL while it compresses a chunk), where a callback would stall the link and make the
        router drop what it cannot queue.
        """
        guarded = self._guard(lambda sample: handler(*sample), key_expr)

        def on_payload(key: str, read: Callable[[], bytes]) -> None:
            self.counters.bump(key, "received")
            guarded((key, read()))

        sub = Subscription(self._listen_buffered(key_expr, on_payload, backlog))
        self._declared.append(sub)
        return sub

    def _subscribe(self, key_expr: str, deliver: Callable[[tuple[str, Callable[[], bytes]]], None], keep: int
                   ) -> Subscription:
        def on_payload(key: str, read: Callable[[], bytes]) -> None:
            self.counters.bump(key, "received")
            self.inbox.put(deliver, (key, read), channel=key, keep=keep,
                           on_drop=lambda: self.counters.bump(key, "dropped"))

        sub = Subscription(self._listen(key_expr, on_payload))
        self._declared.append(sub)
        return sub

    def queryable(self, key: str, answer: Callable[[], Codec]) -> None:
        """Answer queries on ``key`` with the message ``answer()`` returns (run by the inbox's taker)."""
        def respond(args: tuple[Callable[[bytes | bytearray], None], Callable[[], None]]) -> None:
            reply, finish = args
            try:
                reply(answer().to_bytes())
            finally:
                finish()

        def on_query(reply: Callable[[bytes | bytearray], None], finish: Callable[[], None]) -> None:
            self.inbox.put(self._guard(respond, key), (reply, finish))

        self._declared.append(Subscription(self._answer(key, on_query)))

    def request(self, key: str, msg_type: type[M], handler: Callable[[M | None], None],
                timeout_s: float = 1.0) -> None:
        """Ask the queryable(s) on ``key`` without waiting: ``handler`` gets the first valid
        answer, or None once every answer came in invalid or the timeout passed (once either
        way, on the inbox's taker)."""
        answered = False

        def on_reply(payload: bytes) -> None:
            nonlocal answered
            if not answered and (msg := self.decode(key, msg_type, payload)) is not None:
                answered = True
                handler(msg)

        def on_done(_: object) -> None:
            if not answered:
                handler(None)

        guarded_reply, guarded_done = self._guard(on_reply, key), self._guard(on_done, key)
        self._ask(key, timeout_s, lambda payload: self.inbox.put(guarded_reply, payload),
                  lambda: self.inbox.put(guarded_done, None))

    def watch_liveliness(self, key_expr: str, handler: Callable[[str, bool], None]) -> None:
        """``handler(key, alive)`` for every liveliness token under ``key_expr``, those already
        declared first (on the inbox's taker)."""
        def on_change(key: str, alive: bool) -> None:
            self.inbox.put(self._guard(lambda _: handler(key, alive), key_expr), None)

        self._declared.append(Subscription(self._watch_tokens(key_expr, on_change)))

    def serve_robot(self, robot_id: str) -> None:
        """Show this instance among ``robot_id``'s services too (its liveliness and its stats): a
        fleet-wide service (perception) runs under one id and serves several robots."""
        self.declare_token(keys.alive(robot_id, self.service, self.instance))
        self._answer_stats(keys.stats(robot_id, self.service, self.instance))

    def _answer_stats(self, key: str) -> None:
        """Answer stats queries on ``key`` (a transport may answer them off the inbox)."""
        self.queryable(key, self.stats)

    def declare_token(self, key: str) -> Subscription:
        """A liveliness token; ``undeclare()`` withdraws it (before the bus closes, if need be)."""
        handle = Subscription(self._token(key))
        self._declared.append(handle)
        return handle

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
                            counters=self.counters.snapshot(), info={**self.info, **self._transport_info()},
                            host=self.host, now=self.wall_clock())

    def _transport_info(self) -> dict[str, Any]:
        """What the transport adds to :meth:`stats`' info (a subclass's)."""
        return {}

    def close(self) -> None:
        """Undeclare everything and drop what is queued (idempotent)."""
        if self._closed:
            return
        self._closed = True
        for item in reversed(self._declared):
            item.undeclare()
        self._declared.clear()
        self.inbox.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class Bus(BusCore):
    """One service instance's Zenoh session, with its liveliness token and stats queryable
    (and its final stats, put on the same key when it closes).

    ``dispatch="thread"`` (tools, tests, embedding programs): a thread of the bus
    takes the inbox's events. ``"caller"``: the owner takes them
    (:func:`ovamos.shared.service.run_service` runs them between a service's ticks).
    ``shm``: large payloads go out through this shared-memory pool (:mod:`ovamos.shared.bus.shm`);
    :meth:`open` gives one when the session's config has shared memory on.
    """

    def __init__(self, session: zenoh.Session, robot_id: str, service: str, instance: str, *,
                 dispatch: Literal["thread", "caller"] = "thread", shm: ShmPool | None = None) -> None:
        super().__init__(robot_id, service, instance)
        self.session = session
        self.shm = shm
        self._dispatcher = (self.inbox.run_forever(f"bus:{service}/{instance}") if dispatch == "thread"
                            else None)
        self._stats_key = keys.stats(robot_id, service, instance)
        self._answer_stats(self._stats_key)
        self._alive = session.liveliness().declare_token(keys.alive(robot_id, service, instance))

    @classmethod
    def open(cls, cfg: zenoh.Config, robot_id: str, service: str, instance: str = "0", *,
             dispatch: Literal["thread", "caller"] = "thread") -> Bus:
        _check_identity(robot_id, service, instance)  # first: opening may wait for a router
        return cls(open_session(cfg), robot_id, service, instance, dispatch=dispatch,
                   shm=ShmPool() if shm_enabled(cfg) else None)

    def _publish(self, key: str, block: bool = False
                 ) -> tuple[Callable[[bytes | bytearray], None], Callable[[], None]]:
        congestion = zenoh.CongestionControl.BLOCK if block else zenoh.CongestionControl.DROP
        pub = self.session.declare_publisher(key, congestion_control=congestion)
        shm = self.shm
        if shm is None:
            return pub.put, pub.undeclare
        return (lambda payload: pub.put(shm.wrap(payload))), pub.undeclare

    def _listen(self, key_expr: str, on_payload: Callable[[str, Callable[[], bytes]], None]
                ) -> Callable[[], None]:
        def on_sample(sample: zenoh.Sample) -> None:
            on_payload(str(sample.key_expr), sample.payload.to_bytes)

        return self.session.declare_subscriber(key_expr, on_sample).undeclare

    def _listen_buffered(self, key_expr: str, on_payload: Callable[[str, Callable[[], bytes]], None],
                         backlog: int) -> Callable[[], None]:
        # Samples wait in Zenoh's own queue (no GIL needed to receive); one thread takes them.
        sub = self.session.declare_subscriber(key_expr, zenoh.handlers.FifoChannel(backlog))

        def take() -> None:
            for sample in sub:  # ends when the subscriber is undeclared
                on_payload(str(sample.key_expr), sample.payload.to_bytes)

        thread = threading.Thread(target=take, name=f"tap:{key_expr}", daemon=True)
        thread.start()

        def undeclare() -> None:
            sub.undeclare()
            thread.join(timeout=5)

        return undeclare

    def _answer(self, key: str, on_query: Callable[[Callable[[bytes | bytearray], None],
                                                    Callable[[], None]], None]) -> Callable[[], None]:
        def on_zenoh_query(query: zenoh.Query) -> None:
            # Kept alive until answered on the inbox's taker; drop() then ends the query.
            on_query(lambda payload: query.reply(key, bytes(payload)), query.drop)

        return self.session.declare_queryable(key, on_zenoh_query).undeclare

    def _ask(self, key: str, timeout_s: float, on_reply: Callable[[bytes], None],
             on_done: Callable[[], None]) -> None:
        def reply(r: zenoh.Reply) -> None:
            if r.ok is not None:
                on_reply(r.ok.payload.to_bytes())

        self.session.get(key, zenoh.handlers.Callback(reply, on_done), timeout=timeout_s)

    def _transport_info(self) -> dict[str, Any]:
        return {} if self.shm is None else self.shm.info()

    def _answer_stats(self, key: str) -> None:
        # Answered on Zenoh's thread, the one exception to enqueue-only: it reads only the
        # thread-safe counters and the info snapshot, so a service busy for seconds (a model on
        # a CPU) still shows up in `ovamos status` and the gateway's /health.
        self._declared.append(self.session.declare_queryable(
            key, lambda query: query.reply(key, self.stats().to_bytes())))

    def get(self, key: str, msg_type: type[M], timeout_s: float = 1.0) -> M | None:
        """Ask the queryable(s) on ``key`` and wait (HTTP handlers, tools; never a service's loop):
        the first valid answer, or None (none in time, or only malformed ones, counted)."""
        for reply in self.session.get(key, timeout=timeout_s):
            if reply.ok is not None:
                msg = self.decode(key, msg_type, reply.ok.payload.to_bytes())
                if msg is not None:
                    return msg
        return None

    def _token(self, key: str) -> Callable[[], None]:
        return self.session.liveliness().declare_token(key).undeclare

    def _watch_tokens(self, key_expr: str, on_change: Callable[[str, bool], None]) -> Callable[[], None]:
        def on_sample(sample: zenoh.Sample) -> None:
            on_change(str(sample.key_expr), sample.kind == zenoh.SampleKind.PUT)

        return self.session.liveliness().declare_subscriber(key_expr, on_sample, history=True).undeclare

    def close(self) -> None:
        """Undeclare everything and close the session (idempotent)."""
        if self._closed:
            return
        self._alive.undeclare()
        super().close()
        d = self._dispatcher
        if d is not None and d is not threading.current_thread():
            d.join(timeout=5)  # the handler it is running finishes before the session goes
        # The final counters, put once on the stats key: a process that is gone answers no
        # query, yet a recording is checked against what its publishers counted. Blocking, so a
        # queue still full of frames cannot drop the one message that says what was sent.
        self.session.put(self._stats_key, self.stats().to_bytes(), congestion_control=zenoh.CongestionControl.BLOCK)
        self.session.close()
