"""An MCAP recorder with bounded memory: payloads in from any thread, one writer thread out.

:meth:`Recorder.offer` never blocks: it queues the payload unless the queue already holds
``budget_bytes``, in which case the payload is dropped and counted (a recorder that cannot
keep up, on a disk slower than the camera, loses frames instead of the robot's memory). The
writer thread logs each payload unchanged on its key's raw channel, hands it to the views
(:class:`~ovamos.record.views.ViewPump`, which may skip frames, never the raw channels) and
finishes a chunk every ``flush_s``: a recorder killed with SIGKILL leaves a file whose
complete chunks a reader still yields (at most ``flush_s`` of messages are lost), while a
closed one gets its summary and index.

``split_bytes`` starts a new file (``run.mcap``, ``run.1.mcap``, ``run.2.mcap``, ...) once
the current one holds that many bytes, so a long run can be copied and opened in parts.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import Counter, deque
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import foxglove
from foxglove.mcap import MCAPCompression, MCAPWriteOptions

from ovamos.record.channels import RawChannel
from ovamos.record.views import ViewPump

__all__ = ["RecorderConfig", "Recorder", "RecordingExistsError", "part_path"]

log = logging.getLogger("ovamos.recorder")

Compression = Literal["zstd", "lz4", "none"]
_COMPRESSION = {"zstd": MCAPCompression.Zstd, "lz4": MCAPCompression.Lz4, "none": None}


class RecordingExistsError(FileExistsError):
    """The output file is there already and overwriting was not asked for."""


@dataclass(frozen=True)
class RecorderConfig:
    """How a recording is written (``ovamos record``'s options)."""

    budget_bytes: int = 256 << 20      # queued payloads beyond this are dropped (and counted)
    flush_s: float = 1.0               # finish the open chunk this often (lost on SIGKILL at most)
    chunk_bytes: int = 4 << 20         # target uncompressed chunk size
    compression: Compression = "zstd"
    compression_level: int = 1         # zstd's fastest: 640x480 RGB-D at 30 Hz on two cores
    split_bytes: int | None = None     # start a new file past this size
    views: bool = True                 # also write the Foxglove view channels
    overwrite: bool = False


def part_path(path: Path, part: int) -> Path:
    """The ``part``-th file of a split recording (the first is ``path`` itself)."""
    return path if part == 0 else path.with_name(f"{path.stem}.{part}{path.suffix}")


@dataclass
class _Queue:
    """FIFO of (name, payload, ns) bounded by the bytes it holds."""

    budget: int
    items: deque[tuple[str, bytes, int]] = field(default_factory=deque)
    held: int = 0
    closed: bool = False
    cond: threading.Condition = field(default_factory=threading.Condition)


class Recorder:
    """Writes the raw channels of ``ports`` (key name -> message type) of ``robot_id`` to ``path``."""

    def __init__(self, path: Path, ports: Mapping[str, type], robot_id: str,
                 config: RecorderConfig = RecorderConfig()) -> None:
        self.path, self.config = Path(path), config
        for part in (0, 1) if config.split_bytes else (0,):  # parts are numbered from 1 on, in order
            if part_path(self.path, part).exists() and not config.overwrite:
                raise RecordingExistsError(f"{part_path(self.path, part)} exists (overwrite it with --overwrite)")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.context = foxglove.Context()
        self._raw = {name: RawChannel(name, message, robot_id).open(self.context)
                     for name, message in ports.items()}
        self.views = ViewPump(self.context, ports) if config.views else None
        self.files: list[Path] = []
        self._writer = self._open(0)
        self._queue = _Queue(config.budget_bytes)
        self._lock = threading.Lock()
        self.written: Counter[str] = Counter()
        self.dropped: Counter[str] = Counter()
        self.bytes_written = 0
        self.failed = ""  # why the writer stopped early (a full disk), if it did
        self._closing = False
        self._thread = threading.Thread(target=self._run, name="recorder", daemon=True)
        self._thread.start()

    def _open(self, part: int) -> foxglove.mcap.MCAPWriter:
        path = part_path(self.path, part)
        c = self.config
        options = MCAPWriteOptions(compression=_COMPRESSION[c.compression], chunk_size=c.chunk_bytes,
                                   compression_level=c.compression_level, profile="ovamos")
        writer = foxglove.open_mcap(path, allow_overwrite=c.overwrite, context=self.context,
                                    writer_options=options)
        self.files.append(path)
        return writer

    # -- any thread ----------------------------------------------------------------------------
    def offer(self, name: str, payload: bytes, ns: int | None = None) -> bool:
        """Queue ``payload`` of key ``name`` (received at ``ns``, Unix nanoseconds; now if None).
        False when it was dropped: the queue is full, the key is not recorded, or we are closed."""
        q = self._queue
        with q.cond:
            if q.closed or name not in self._raw or q.held + len(payload) > q.budget:
                accepted = False
            else:
                q.items.append((name, payload, time.time_ns() if ns is None else ns))
                q.held += len(payload)
                q.cond.notify()
                accepted = True
        if not accepted:
            with self._lock:
                self.dropped[name] += 1
        return accepted

    def stats(self) -> dict[str, object]:
        with self._lock:
            out: dict[str, object] = {"written": dict(self.written), "dropped": dict(self.dropped),
                                      "bytes": self.bytes_written, "files": [str(p) for p in self.files],
                                      "failed": self.failed}
        with self._queue.cond:
            out["queued_bytes"] = self._queue.held
        if self.views is not None:
            out["views"] = dict(self.views.counters)
        return out

    # -- the writer thread ---------------------------------------------------------------------
    def _take(self, timeout: float) -> tuple[str, bytes, int] | None:
        q = self._queue
        with q.cond:
            if not q.items and not q.closed:
                q.cond.wait(timeout)
            if not q.items:
                return None
            item = q.items.popleft()
            q.held -= len(item[1])
            return item

    def _run(self) -> None:
        try:
            self._write_until_closed()
        except Exception as exc:  # a full disk, a split file that cannot be created: stop taking
            with self._queue.cond:
                self._queue.closed = True
                self._queue.items.clear()
                self._queue.held = 0
            self.failed = f"{type(exc).__name__}: {exc}"
            log.exception("the recording stopped: %s", self.failed)

    def _write_until_closed(self) -> None:
        next_flush = time.monotonic() + self.config.flush_s
        while True:
            item = self._take(max(0.0, next_flush - time.monotonic()))
            if item is not None:
                name, payload, ns = item
                self._raw[name].log(payload, log_time=ns)
                if self.views is not None:
                    self.views.offer(name, payload, ns)
                with self._lock:
                    self.written[name] += 1
                    self.bytes_written += len(payload)
            elif self._queue.closed:
                return
            if time.monotonic() >= next_flush:
                self._writer.flush()
                self._maybe_split()
                next_flush = time.monotonic() + self.config.flush_s

    def _maybe_split(self) -> None:
        limit = self.config.split_bytes
        if limit is not None and self.files[-1].stat().st_size >= limit:
            self._writer.close()
            self._writer = self._open(len(self.files))

    def close(self) -> None:
        """Write what is queued, the views' last drawings, and finish the file (idempotent)."""
        if self._closing:
            return
        self._closing = True
        with self._queue.cond:
            self._queue.closed = True
            self._queue.cond.notify_all()
        self._thread.join()
        if self.views is not None:
            self.views.close()
        try:
            self._writer.close()
        except Exception as exc:  # a full disk: the chunks written so far stay readable
            self.failed = self.failed or f"{type(exc).__name__}: {exc}"
            log.exception("finishing %s failed", self.files[-1])
