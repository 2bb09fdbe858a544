"""Large payloads through Zenoh shared memory between processes on one host.

A publisher with a :class:`ShmPool` writes each large payload (an RGB-D frame)
into a buffer of its own shared-memory provider and puts that buffer: a
subscriber on the same host, and the router between them, pass a reference to
it instead of the bytes. Zenoh decides per link: a subscriber on another host,
or one whose session has shared memory off, gets the bytes over the network as
before, so nothing here knows where its subscribers are.

Why a provider of our own when Zenoh 1.x already moves payloads over 3 KB
through its own pool (``transport.shared_memory.transport_optimization``)? That
path copies the payload twice before it is shared (Python bytes into Zenoh's
buffer, then into the pool); ours copies it once, straight from the encoder's
buffer. The pool is sized for a few 640x480 frames in flight; when it is full
(subscribers still hold their buffers, a recorder's backlog) a put falls back
to the normal path (counted), never blocks and never fails.

The Python API has no writable view of a shared buffer (no buffer protocol on
``ZShmMut``), so a frame cannot be encoded in place: one copy remains.
"""

from __future__ import annotations

import logging

import zenoh
import zenoh.shm

log = logging.getLogger("ovamos.shm")

#: bytes of shared memory per publishing process: ten 640x480 RGB-D frames (2.15 MB each)
POOL_BYTES = 24 << 20
#: payloads from this size go through the pool; smaller ones are cheaper to copy
MIN_PAYLOAD_BYTES = 64 << 10


def enabled(cfg: zenoh.Config) -> bool:
    """Whether a session opened with ``cfg`` takes shared-memory buffers (Zenoh's own setting,
    ``transport.shared_memory.enabled``; on by default in Zenoh 1.x)."""
    return cfg.get_json("transport/shared_memory/enabled") == "true"


class ShmPool:
    """A shared-memory provider, created on the first large payload (a process that publishes only
    small messages never maps any memory). Thread-safe as Zenoh's provider is."""

    def __init__(self, size: int = POOL_BYTES, min_payload: int = MIN_PAYLOAD_BYTES) -> None:
        self.size, self.min_payload = size, min_payload
        self._provider: zenoh.shm.ShmProvider | None = None
        self._broken = False
        #: payloads that went through shared memory, and large ones that could not (pool full)
        self.shared = self.fallbacks = 0

    def wrap(self, payload: bytes | bytearray) -> bytes | bytearray | zenoh.shm.ZShmMut:
        """``payload`` in a shared buffer when it is large and the pool has room, else itself."""
        if len(payload) < self.min_payload or self._broken:
            return payload
        provider = self._provider or self._open()
        if provider is None:
            return payload
        try:
            buf = provider.alloc(len(payload))
        except zenoh.ZError:
            # Buffers the subscribers have released are reclaimed only by a collection: a few us
            # when done here, where Zenoh's GarbageCollect policy took ~250 us an allocation.
            provider.garbage_collect()
            try:
                buf = provider.alloc(len(payload))
            except zenoh.ZError:
                self.fallbacks += 1
                return payload
        buf[:] = payload
        self.shared += 1
        return buf

    def _open(self) -> zenoh.shm.ShmProvider | None:
        try:
            self._provider = zenoh.shm.ShmProvider.default_backend(self.size)
        except zenoh.ZError as exc:  # no /dev/shm, or too small: the network path still works
            self._broken = True
            log.warning("shared memory unavailable (%s): frames take the normal path", exc)
        return self._provider

    def info(self) -> dict[str, int]:
        return {"shm_shared": self.shared, "shm_fallbacks": self.fallbacks}
