"""Reading a recording's raw channels back, in order and with their original timing.

The file is read with the ``mcap`` library: through its index when the recording was closed
(messages in log-time order), else record by record from the start (a recorder killed with
SIGKILL left no index; its writer thread logged in arrival order). A file that ends in the
middle of a chunk yields every message before the break and then reports where it stopped;
a file that is not MCAP at all raises :class:`RecordingError`.
"""

from __future__ import annotations

import logging
import time
from collections import Counter
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import BinaryIO

from mcap.reader import NonSeekingReader, make_reader
from mcap.records import Channel

from ovamos.record.channels import RawChannel, UnknownKeyError, from_metadata, recorded_ports

__all__ = ["RecordingError", "RawMessage", "ReadReport", "read_raw", "paced"]

log = logging.getLogger("ovamos.replay")


class RecordingError(ValueError):
    """A file that cannot be read as a recording at all."""


@dataclass(frozen=True)
class RawMessage:
    channel: RawChannel
    payload: bytes
    log_time: int  # Unix nanoseconds, when the recorder received it


@dataclass
class ReadReport:
    """What reading a recording found besides its messages."""

    read: Counter[str] = field(default_factory=Counter)       # raw messages yielded, by key name
    skipped_channels: list[str] = field(default_factory=list)  # channels this version cannot replay
    truncated: str = ""                                        # why reading stopped early, if it did


def _reader_messages(stream: BinaryIO) -> Iterator[tuple[Channel, bytes, int]]:
    try:
        summary = make_reader(stream).get_summary()
    except Exception:  # no summary or a damaged one: read record by record below
        summary = None
    stream.seek(0)
    if summary is not None and summary.chunk_indexes:
        source = make_reader(stream).iter_messages(log_time_order=True)
    else:
        source = NonSeekingReader(stream).iter_messages(log_time_order=False)
    for _, channel, message in source:
        yield channel, message.data, message.log_time


def read_raw(path: Path, names: Sequence[str] | None = None, report: ReadReport | None = None
             ) -> Iterator[RawMessage]:
    """The raw messages of ``path`` (of the keys in ``names``; all when None), in order.

    Channels of keys this version does not publish, or of other message versions, are skipped
    and listed in ``report``; a truncated or damaged file ends the iteration with
    ``report.truncated`` saying where. Raises :class:`RecordingError` when ``path`` is not an
    MCAP file (or cannot be opened), and :class:`UnknownKeyError` for an unknown name in ``names``.
    """
    report = report if report is not None else ReadReport()
    ports = recorded_ports()
    if names:
        unknown = sorted(set(names) - set(ports))
        if unknown:
            raise UnknownKeyError(f"unknown key(s) {', '.join(unknown)}; known: {', '.join(sorted(ports))}")
    channels: dict[int, RawChannel | None] = {}
    try:
        stream = open(path, "rb")
    except OSError as exc:
        raise RecordingError(f"cannot open {path}: {exc.strerror}") from None
    with stream:
        messages = _reader_messages(stream)
        count = 0
        while True:
            try:
                channel, data, log_time = next(messages)
            except StopIteration:
                return
            except Exception as exc:  # the reader's errors on a damaged file are of many types
                # (McapError, struct.error, EOFError, a decompressor's): all mean "cannot read on"
                if count == 0 and not channels:
                    raise RecordingError(f"{path} is not a readable MCAP recording: {exc}") from None
                report.truncated = (f"stopped after {count} messages of the file (views included): "
                                    f"{type(exc).__name__}: {exc}")
                log.warning("%s: %s", path, report.truncated)
                return
            if channel.id not in channels:
                channels[channel.id] = _raw_channel(channel, ports, report)
            raw = channels[channel.id]
            count += 1
            if raw is None or (names and raw.name not in names):
                continue
            report.read[raw.name] += 1
            yield RawMessage(raw, data, log_time)


def _raw_channel(channel: Channel, ports: dict[str, type], report: ReadReport) -> RawChannel | None:
    try:
        return from_metadata(channel.metadata, ports)
    except UnknownKeyError as exc:
        report.skipped_channels.append(f"{channel.topic}: {exc}")
        log.warning("skipping channel %s: %s", channel.topic, exc)
        return None


def paced(messages: Iterator[RawMessage], rate: float | None, *,
          clock: Callable[[], float] = time.monotonic, sleep: Callable[[float], None] = time.sleep,
          stopped: Callable[[], bool] = lambda: False) -> Iterator[RawMessage]:
    """``messages`` at their recorded pace times ``rate`` (None: as fast as they are taken);
    ends early once ``stopped()``."""
    start: tuple[float, int] | None = None
    for msg in messages:
        if stopped():
            return
        if rate is not None:
            if start is None:
                start = (clock(), msg.log_time)
            due = start[0] + (msg.log_time - start[1]) / 1e9 / rate
            while (wait := due - clock()) > 0 and not stopped():
                sleep(min(wait, 0.1))
        yield msg
