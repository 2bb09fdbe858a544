"""Binary wire format for messages that carry arrays (RGB-D frames, map grids).

Layout of one payload::

    header  <4s B B H I>  magic b"OVAM", wire version, flags, reserved, meta length
    meta    UTF-8 JSON    {"kind", "v", "fields", "arrays": [[name, dtype, shape, offset]], "body"}
    padding               up to a multiple of ALIGN from the payload start
    body                  the raw array bytes, each array at an ALIGN-ed offset;
                          zlib-compressed as a whole when FLAG_ZLIB is set

Why this shape: JSON for the few scalar fields keeps them readable and
versionable with pydantic, while arrays travel as raw little-endian bytes so the
receiver gets ``numpy.frombuffer`` views without a copy. Offsets are aligned so
those views are aligned for every dtype. Everything read from the wire is
checked before use; any inconsistency raises :class:`DecodeError`, the one
error a subscriber has to catch.
"""

from __future__ import annotations

import json
import struct
import zlib
from typing import Any, Mapping

import numpy as np

MAGIC = b"OVAM"
WIRE_VERSION = 1
FLAG_ZLIB = 0x01
_KNOWN_FLAGS = FLAG_ZLIB
HEADER = struct.Struct("<4sBBHI")
ALIGN = 64
# Explicit little-endian dtypes only: the wire format must not depend on the host.
ALLOWED_DTYPES = frozenset(np.dtype(d).str for d in (
    "|b1", "|u1", "|i1", "<u2", "<i2", "<u4", "<i4", "<u8", "<i8", "<f2", "<f4", "<f8"))
# Bounds a hostile meta or a zip bomb cannot push us past.
MAX_META_BYTES = 1 << 20
MAX_BODY_BYTES = 1 << 30


class DecodeError(ValueError):
    """A payload that is not a valid message of the expected kind and version."""


def _align(n: int) -> int:
    return (n + ALIGN - 1) // ALIGN * ALIGN


def _wire_array(name: str, arr: np.ndarray) -> np.ndarray:
    arr = np.asarray(arr)
    if arr.dtype.byteorder == ">":
        arr = arr.astype(arr.dtype.newbyteorder("<"))
    if arr.dtype.str not in ALLOWED_DTYPES:
        raise TypeError(f"array {name!r}: dtype {arr.dtype} cannot be sent; "
                        f"allowed: {sorted(ALLOWED_DTYPES)}")
    return np.ascontiguousarray(arr)


def pack(kind: str, version: int, fields: Mapping[str, Any], arrays: Mapping[str, np.ndarray],
         *, compress_level: int | None = None) -> bytearray:
    """Encode scalar ``fields`` and named ``arrays`` into one payload."""
    wired = {name: _wire_array(name, a) for name, a in arrays.items()}
    table, offset = [], 0
    for name, arr in wired.items():
        table.append([name, arr.dtype.str, list(arr.shape), offset])
        offset = _align(offset + arr.nbytes)
    body_size = offset
    meta = json.dumps({"kind": kind, "v": version, "fields": fields, "arrays": table,
                       "body": body_size}, separators=(",", ":")).encode()
    body_start = _align(HEADER.size + len(meta))
    flags = 0 if compress_level is None else FLAG_ZLIB

    if compress_level is None:
        out = bytearray(body_start + body_size)
        body = np.frombuffer(out, np.uint8, body_size, body_start)
    else:
        scratch = bytearray(body_size)
        body = np.frombuffer(scratch, np.uint8)
    for (_, _, _, off), arr in zip(table, wired.values()):
        body[off:off + arr.nbytes] = arr.reshape(-1).view(np.uint8)
    if compress_level is not None:
        compressed = zlib.compress(scratch, compress_level)
        out = bytearray(body_start + len(compressed))
        out[body_start:] = compressed
    HEADER.pack_into(out, 0, MAGIC, WIRE_VERSION, flags, 0, len(meta))
    out[HEADER.size:HEADER.size + len(meta)] = meta
    return out


def _decompress(data: memoryview, size: int) -> bytes:
    inflater = zlib.decompressobj()
    try:
        body = inflater.decompress(data, size)
    except zlib.error as exc:
        raise DecodeError(f"compressed body is corrupt: {exc}") from None
    if len(body) != size or not inflater.eof or inflater.unconsumed_tail:
        raise DecodeError(f"compressed body does not inflate to the declared {size} bytes")
    return body


def _array_view(body: bytes | memoryview, entry: Any, end_of_previous: int) -> tuple[str, np.ndarray, int]:
    try:
        name, dtype_str, shape, offset = entry
        dtype = np.dtype(dtype_str)
        shape = tuple(int(s) for s in shape)
        offset = int(offset)
    except (TypeError, ValueError) as exc:
        raise DecodeError(f"bad array table entry {entry!r}: {exc}") from None
    if not isinstance(name, str) or dtype.str not in ALLOWED_DTYPES:
        raise DecodeError(f"array {name!r}: dtype {dtype_str!r} is not allowed")
    if any(s < 0 for s in shape) or offset < end_of_previous or offset % ALIGN:
        raise DecodeError(f"array {name!r}: bad shape {shape} or offset {offset}")
    count = int(np.prod(shape, dtype=np.int64))
    end = offset + count * dtype.itemsize
    if end > len(body):
        raise DecodeError(f"array {name!r} needs bytes up to {end}, body holds {len(body)}")
    view = np.frombuffer(body, dtype, count, offset).reshape(shape)
    return name, view, end


def unpack(payload: bytes | bytearray | memoryview, kind: str, version: int
           ) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """Decode a payload of the given kind and version into (fields, arrays).

    Arrays are views into ``payload`` (read-only when it is ``bytes``), so the
    payload must stay alive as long as they do; numpy's views keep it referenced.
    """
    data = memoryview(payload)
    if len(data) < HEADER.size:
        raise DecodeError(f"payload of {len(data)} bytes is shorter than the header")
    magic, wire, flags, _, meta_len = HEADER.unpack_from(data, 0)
    if magic != MAGIC:
        raise DecodeError(f"bad magic {bytes(magic)!r}: not an ovamos binary message")
    if wire != WIRE_VERSION:
        raise DecodeError(f"wire version {wire} is not supported (this build reads {WIRE_VERSION})")
    if flags & ~_KNOWN_FLAGS:
        raise DecodeError(f"unknown flags 0x{flags:02x}")
    if meta_len > MAX_META_BYTES or HEADER.size + meta_len > len(data):
        raise DecodeError(f"meta length {meta_len} exceeds the payload")
    try:
        meta = json.loads(bytes(data[HEADER.size:HEADER.size + meta_len]))
        msg_kind, msg_version = meta["kind"], meta["v"]
        fields, table, body_size = meta["fields"], meta["arrays"], int(meta["body"])
    except (ValueError, KeyError, TypeError) as exc:
        raise DecodeError(f"meta is not valid: {exc}") from None
    if msg_kind != kind:
        raise DecodeError(f"expected a {kind!r} message, got {msg_kind!r}")
    if msg_version != version:
        raise DecodeError(f"{kind} version {msg_version!r} is not supported (expected {version})")
    if not isinstance(fields, dict) or not isinstance(table, list) or not 0 <= body_size <= MAX_BODY_BYTES:
        raise DecodeError("meta fields/arrays/body have the wrong types")

    body_start = _align(HEADER.size + meta_len)
    if body_start > len(data):
        raise DecodeError("payload truncated before the body")
    body: bytes | memoryview = data[body_start:]
    if flags & FLAG_ZLIB:
        body = _decompress(body, body_size)
    elif len(body) != body_size:
        raise DecodeError(f"body holds {len(body)} bytes, meta declares {body_size}")

    arrays: dict[str, np.ndarray] = {}
    end = 0
    for entry in table:
        name, view, end = _array_view(body, entry, end)
        if name in arrays:
            raise DecodeError(f"array {name!r} appears twice")
        arrays[name] = view
    return fields, arrays
