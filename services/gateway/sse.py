"""Task progress as Server-Sent Events, fed from whichever thread changed the task.

Changes happen on the TaskManager's owner thread (the bus's inbox taker); the
streams live in the event loop. :class:`TaskWatchers` crosses over with
``loop.call_soon_threadsafe`` (Zenoh has no asyncio API); its lock guards only
the table of streams and is never held across I/O, so the loop taking it never
waits for a commit. A stream reads its task's state now through
``asyncio.to_thread``. Each stream keeps
only the newest state of its task: every event is a complete snapshot, so a
slow client skips intermediate progress but never misses the final state, and
memory stays bounded whatever the client does.
"""

from __future__ import annotations

import asyncio
import threading
from collections import defaultdict
from collections.abc import AsyncIterator, Callable, Iterator
from contextlib import contextmanager

from ovamos.services.gateway.models import TaskView

_CLOSED = object()  # offered to every stream when the gateway shuts down


class _Watch:
    """One stream's mailbox; touched only from the event loop."""

    def __init__(self) -> None:
        self._latest: object | None = None
        self._ready = asyncio.Event()

    def offer(self, item: object) -> None:
        if self._latest is not _CLOSED:
            self._latest = item
        self._ready.set()

    async def next(self, timeout: float) -> object | None:
        """The newest item, or None after ``timeout`` seconds without one."""
        try:
            await asyncio.wait_for(self._ready.wait(), timeout)
        except TimeoutError:
            return None
        self._ready.clear()
        item = self._latest
        if item is not _CLOSED:  # closed stays closed
            self._latest = None
        return item


class TaskWatchers:
    """Fan-out of task views to the streams watching them."""

    def __init__(self, loop: asyncio.AbstractEventLoop) -> None:
        self._loop = loop
        self._lock = threading.Lock()
        self._watches: dict[str, set[_Watch]] = defaultdict(set)

    def watched(self, task_id: str) -> bool:
        """Whether anyone watches ``task_id`` (callers skip building views nobody reads)."""
        with self._lock:
            return bool(self._watches.get(task_id))

    def publish(self, view: TaskView) -> None:
        """Hand ``view`` to its task's streams (any thread)."""
        with self._lock:
            watches = list(self._watches.get(view.id, ()))
        for watch in watches:
            self._loop.call_soon_threadsafe(watch.offer, view)

    def close(self) -> None:
        """End every stream (gateway shutdown: open streams must not hold it up)."""
        with self._lock:
            watches = [w for ws in self._watches.values() for w in ws]
        for watch in watches:
            self._loop.call_soon_threadsafe(watch.offer, _CLOSED)

    @contextmanager
    def watch(self, task_id: str) -> Iterator[_Watch]:
        watch = _Watch()
        with self._lock:
            self._watches[task_id].add(watch)
        try:
            yield watch
        finally:
            with self._lock:
                self._watches[task_id].discard(watch)
                if not self._watches[task_id]:
                    del self._watches[task_id]


def format_event(view: TaskView) -> bytes:
    """One SSE ``task`` event carrying the task's JSON (single line, as SSE data must be)."""
    return f"event: task\ndata: {view.model_dump_json()}\n\n".encode()


async def task_stream(watchers: TaskWatchers, task_id: str, current: Callable[[], TaskView | None],
                      heartbeat_s: float) -> AsyncIterator[bytes]:
    """The task's state now, then each change, ending after the final state.

    The watch is registered before the current state is read, so no change can
    fall between the two. A comment line every ``heartbeat_s`` of silence lets
    proxies and clients tell a quiet search from a dead connection.
    """
    with watchers.watch(task_id) as watch:
        view = await asyncio.to_thread(current)
        if view is None:
            return
        yield format_event(view)
        while not view.final:
            item = await watch.next(heartbeat_s)
            if item is _CLOSED:
                return
            if item is None:
                yield b": keep-alive\n\n"
                continue
            assert isinstance(item, TaskView)
            view = item
            yield format_event(view)
