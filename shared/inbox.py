"""One service's event queue: Zenoh's threads put, one thread takes (dora's node model).

Every callback Zenoh makes into a service (a sample, a query, a reply, a
liveliness change) only *enqueues* here; the service's own thread takes the
events one at a time and runs their handlers. So a service's core is only
ever touched by one thread and needs no locks, and nothing blocking (a model
call, a SQLite commit, a 40 ms planner decision) ever runs on Zenoh's
threads, where it would stall every other subscription of the session.

Events run in the order they arrived. Memory stays bounded. An ordinary
channel keeps every event up to ``limit`` in all (beyond it the oldest
ordinary event is dropped and counted); a ``keep=n`` channel (frames, maps)
keeps only its newest ``n``: an older one is dropped, and counted, when a
new one arrives before it was taken, and the survivors keep their own places
in the order (a frame never overtakes a task event that came before it).

The taker sleeps on a C queue (a wake-up token, sent only when it sleeps), not on
``threading.Condition``, whose wait and notify are Python code: on a cache gone
cold between frames the hand-off took ~60 us that way and takes ~35 us this way,
and a request/reply between two services pays it twice.
"""

from __future__ import annotations

import queue
import threading
import time
from collections import deque
from collections.abc import Callable
from typing import Any

__all__ = ["Inbox"]

Handler = Callable[[Any], None]
OnDrop = Callable[[], Any]


class _Latest:
    """The newest ``keep`` events of one channel, and how many places in the order it holds.

    Every arrival takes a place at the end of the order; a dropped event leaves
    its place behind, and a place is skipped when the channel has fewer events
    than places after it, so each survivor runs at (the place of) its arrival.
    """

    def __init__(self, keep: int) -> None:
        self.items: deque[tuple[Handler, Any, OnDrop | None]] = deque()
        self.keep = keep
        self.places = 0


class Inbox:
    """A thread-safe queue of (handler, argument) events with latest-only channels."""

    def __init__(self, limit: int = 10_000) -> None:
        self._lock = threading.Lock()
        self._wake: queue.SimpleQueue[None] = queue.SimpleQueue()
        self._taker_sleeps = False  # the taker waits on _wake: the next put sends it a token
        self._order: deque[tuple[Handler, Any, OnDrop | None] | _Latest] = deque()
        self._latest: dict[str, _Latest] = {}
        self._ordinary = 0
        self._limit = limit
        self._closed = False
        self.owner: int | None = None  # ident of the thread that takes events (set by run_until)

    def put(self, handler: Handler, arg: Any, *, channel: str | None = None, keep: int = 0,
            on_drop: OnDrop | None = None) -> None:
        """Enqueue ``handler(arg)``; never blocks, never runs the handler (any thread)."""
        dropped: OnDrop | None = None
        with self._lock:
            if self._closed:
                return
            if keep > 0:
                assert channel is not None, "a keep-latest event needs its channel"
                latest = self._latest.get(channel)
                if latest is None:
                    latest = self._latest[channel] = _Latest(keep)
                if len(latest.items) >= latest.keep:
                    dropped = latest.items.popleft()[2]
                latest.items.append((handler, arg, on_drop))
                if latest.places > 4 * latest.keep + 64:  # a stalled taker: forget the empty places
                    self._order = deque(e for e in self._order if e is not latest)
                    latest.places = 0
                    for _ in latest.items:
                        self._order.append(latest)
                        latest.places += 1
                else:
                    self._order.append(latest)
                    latest.places += 1
            else:
                if self._ordinary >= self._limit:
                    dropped = self._drop_oldest_ordinary()
                self._order.append((handler, arg, on_drop))
                self._ordinary += 1
            wake, self._taker_sleeps = self._taker_sleeps, False
        if wake:
            self._wake.put(None)
        if dropped is not None:
            dropped()

    def _drop_oldest_ordinary(self) -> OnDrop | None:
        for i, entry in enumerate(self._order):
            if not isinstance(entry, _Latest):
                del self._order[i]
                self._ordinary -= 1
                return entry[2]
        return None

    def _take(self) -> tuple[Handler, Any] | None:
        """The next event, or None when empty (caller holds the lock)."""
        while self._order:
            entry = self._order.popleft()
            if isinstance(entry, _Latest):
                entry.places -= 1
                if entry.places >= len(entry.items):
                    continue  # the place of a dropped event: its newer ones hold later places
                handler, arg, _ = entry.items.popleft()
                return handler, arg
            self._ordinary -= 1
            return entry[0], entry[1]
        return None

    def run_until(self, deadline: float, stop: threading.Event | None = None, *,
                  max_wait: float = 0.1) -> int:
        """Run events as they come until ``deadline`` (``time.monotonic()``), ``stop`` or close;
        return how many ran. Waits at most ``max_wait`` at a time, so ``stop`` is seen soon."""
        self.owner = threading.get_ident()
        ran = 0
        while True:
            with self._lock:
                event = self._take()
                if event is None:
                    remaining = deadline - time.monotonic()
                    if remaining <= 0 or self._closed or (stop is not None and stop.is_set()):
                        return ran
                    self._taker_sleeps = True
            if event is None:
                try:  # a token left by a put that raced a timed-out wait only makes one spare turn
                    self._wake.get(timeout=min(remaining, max_wait))
                except queue.Empty:
                    pass
                continue
            event[0](event[1])
            ran += 1
            if time.monotonic() >= deadline or (stop is not None and stop.is_set()):
                return ran

    def run_pending(self) -> int:
        """Run what is queued now, without waiting (tests and the fake bus pump with this)."""
        ran = 0
        while True:
            with self._lock:
                event = self._take()
            if event is None:
                return ran
            event[0](event[1])
            ran += 1

    def pending(self) -> int:
        with self._lock:
            return self._ordinary + sum(len(x.items) for x in self._latest.values())

    def close(self) -> None:
        """Drop what is queued and refuse new events; a waiting taker returns."""
        with self._lock:
            self._closed = True
            self._order.clear()
            self._latest.clear()
            self._ordinary = 0
        self._wake.put(None)

    @property
    def closed(self) -> bool:
        return self._closed

    def run_forever(self, name: str) -> threading.Thread:
        """Take events on a thread of its own until closed (a bus used outside a service loop)."""
        def loop() -> None:
            while not self._closed:
                self.run_until(time.monotonic() + 3600.0)

        thread = threading.Thread(target=loop, name=name, daemon=True)
        thread.start()
        return thread
