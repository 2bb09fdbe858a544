"""Structured logging: one line per event, human-readable or JSON for log shippers."""

from __future__ import annotations

import json
import logging
import sys
import time


class _JsonFormatter(logging.Formatter):
    def format(self, record: logging.LogRecord) -> str:
        entry = {"ts": round(record.created, 6), "level": record.levelname,
                 "logger": record.name, "msg": record.getMessage()}
        entry.update(getattr(record, "fields", {}))
        if record.exc_info:
            entry["exc"] = self.formatException(record.exc_info)
        return json.dumps(entry, default=str)


class _TextFormatter(logging.Formatter):
    def format(self, record: logging.LogRecord) -> str:
        stamp = time.strftime("%H:%M:%S", time.localtime(record.created))
        fields = " ".join(f"{k}={v}" for k, v in getattr(record, "fields", {}).items())
        line = f"{stamp}.{int(record.msecs):03d} {record.levelname:<7} {record.name}: {record.getMessage()}"
        if fields:
            line += f"  {fields}"
        if record.exc_info:
            line += "\n" + self.formatException(record.exc_info)
        return line


def setup_logging(*, json_lines: bool = False, level: str = "INFO") -> None:
    """Configure the root logger once per process (services log to stderr)."""
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(_JsonFormatter() if json_lines else _TextFormatter())
    root = logging.getLogger()
    root.handlers[:] = [handler]
    root.setLevel(level.upper())


def fields(**kwargs: object) -> dict[str, dict[str, object]]:
    """``log.info("msg", extra=fields(key=value))`` attaches structured fields."""
    return {"fields": kwargs}


def sampled(count: int) -> bool:
    """Whether the ``count``-th occurrence of a repeated problem is worth a log line.

    The first ten always are, then one in a thousand: a flood of garbage on a
    key must not flood the log, yet it must stay visible.
    """
    return count <= 10 or count % 1000 == 0
