"""Writing a file so that a reader (or a restart after a crash) never sees half of it."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

__all__ = ["write_atomic"]


def write_atomic(path: str | os.PathLike[str], data: bytes | bytearray | memoryview,
                 mode: int | None = None) -> Path:
    """Write ``data`` to a temporary file beside ``path``, flush it to the disk, then rename
    it over ``path``; returns the path.

    The rename is atomic, and the data is on the disk before it (``fsync``): a crash
    leaves the old file or the new one, never a torn or empty one. ``mode`` sets the
    file's permissions (``mkstemp`` makes it readable by its owner only). The folder
    must exist (``OSError`` otherwise); the temporary file is removed on any failure.
    """
    target = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        if mode is not None:
            os.chmod(tmp, mode)
        os.replace(tmp, target)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return target
