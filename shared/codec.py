"""Binary wire format for messages that carry arrays (RGB-D frames, map grids).

Layout of one payload::

    header  <4s B B H Q I>  magic b"OVAM", wire version, flags, reserved,
                            stored body length, meta length
    padding                 zeros up to BODY_OFFSET
    body                    the raw array bytes, each array at an ALIGN-ed offset;
                            zlib-compressed as a whole when FLAG_ZLIB is set
    meta    UTF-8 JSON      {"kind", "v", "fields", "arrays": [[name, dtype, shape, offset]],
                            "body": inflated body length}, then spaces (slack)

Why this shape: JSON for the few scalar fields keeps them readable and
versionable with pydantic, while arrays travel as raw little-endian bytes so the
receiver gets ``numpy.frombuffer`` views without a copy. The body sits at a
fixed offset and the variable-length meta after it, so a producer can
:func:`loan` arrays that already live inside a payload buffer, fill them (a
renderer writes its pixels there) and publish with no copy before Zenoh's own.
Everything read from the wire is checked before use; any inconsistency raises
:class:`DecodeError`, the one error a subscriber has to catch.
"""

from __future__ import annotations

import json
import math
import struct
import zlib
from typing import Any, Mapping

import numpy as np

MAGIC = b"OVAM"
WIRE_VERSION = 1
FLAG_ZLIB = 0x01
_KNOWN_FLAGS = FLAG_ZLIB
HEADER = struct.Struct("<4sBBHQI")
BODY_OFFSET = 64
ALIGN = 64
# Room for the meta to grow or shrink while a payload buffer is reused as is;
# JSON ignores the trailing spaces that fill it.
META_SLACK = 4096
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


Table = list[list[Any]]  # [[name, dtype str, shape, offset]] in wire order


def _layout(arrays: Mapping[str, tuple[tuple[int, ...], str]]) -> tuple[Table, int]:
    """Offsets of arrays (name -> (shape, dtype)) in the body, and the body size."""
    table, offset = [], 0
    for name, (shape, dtype) in arrays.items():
        table.append([name, dtype, list(shape), offset])
        offset = _align(offset + math.prod(shape) * np.dtype(dtype).itemsize)
    return table, offset


def loan(arrays: Mapping[str, tuple[tuple[int, ...], str]]) -> dict[str, np.ndarray]:
    """Writable arrays (name -> (shape, dtype)) that live inside a fresh payload buffer.

    A message built from exactly these arrays, in this order, is packed without
    copying them. Filling them is the producer's job (they start zeroed).
    """
    table, body_size = _layout(arrays)
    buffer = bytearray(BODY_OFFSET + body_size + META_SLACK)
    return {name: np.frombuffer(buffer, dtype, math.prod(shape), BODY_OFFSET + off).reshape(shape)
            for name, dtype, shape, off in table}


def _address(obj: np.ndarray | bytearray) -> int:
    arr = obj if isinstance(obj, np.ndarray) else np.frombuffer(obj, np.uint8)
    return arr.ctypes.data


def _loaned_buffer(wired: Mapping[str, np.ndarray], table: Table) -> bytearray | None:
    """The buffer the arrays were loaned from, if they all sit at their wire offsets in it."""
    buffer = None
    for (_, _, _, off), arr in zip(table, wired.values()):
        base = arr.base
        while isinstance(base, np.ndarray):
            base = base.base
        base = base.obj if isinstance(base, memoryview) else base
        if not isinstance(base, bytearray) or (buffer is not None and base is not buffer):
            return None
        if _address(arr) != _address(base) + BODY_OFFSET + off:
            return None
        buffer = base
    return buffer


def _target(out: bytearray | None, total: int) -> bytearray:
    """``out`` when it can hold exactly ``total`` bytes (plus slack), else a new buffer."""
    if out is None:
        return bytearray(total)
    if not total <= len(out) <= total + META_SLACK:
        try:
            del out[total:]
            out.extend(bytes(max(0, total - len(out))))
        except BufferError:  # a loaned buffer whose arrays are still alive cannot resize
            return bytearray(total)
    return out


def _write_arrays(body: np.ndarray, table: Table, wired: Mapping[str, np.ndarray]) -> None:
    for (_, _, _, off), arr in zip(table, wired.values()):
        end = off + arr.nbytes
        body[off:end] = arr.reshape(-1).view(np.uint8)
        body[end:_align(end)] = 0  # padding: a reused buffer must not leak old bytes


def pack(kind: str, version: int, fields: Mapping[str, Any] | bytes, arrays: Mapping[str, np.ndarray],
         *, compress_level: int | None = None, out: bytearray | None = None) -> bytearray:
    """Encode scalar ``fields`` and named ``arrays`` into one payload.

    ``fields`` may come already JSON-encoded (pydantic's ``model_dump_json``
    is several times faster than :func:`json.dumps`, and this is a hot path).
    Arrays from :func:`loan` are not copied: their buffer becomes the payload.
    Otherwise ``out`` (the previous payload of a stream) is reused when given,
    which saves allocating and page-faulting megabytes per message.
    """
    wired = {name: _wire_array(name, a) for name, a in arrays.items()}
    table, body_size = _layout({n: (a.shape, a.dtype.str) for n, a in wired.items()})
    if not isinstance(fields, bytes):
        fields = json.dumps(fields, separators=(",", ":")).encode()
    meta = b'{"kind":%s,"v":%d,"fields":%s,"arrays":%s,"body":%d}' % (
        json.dumps(kind).encode(), version, fields, json.dumps(table, separators=(",", ":")).encode(),
        body_size)
    if compress_level is None:
        loaned = _loaned_buffer(wired, table)
        stored = body_size
        buf = _target(loaned if loaned is not None else out, BODY_OFFSET + stored + len(meta))
        if buf is not loaned:
            _write_arrays(np.frombuffer(buf, np.uint8, body_size, BODY_OFFSET), table, wired)
    else:
        scratch = bytearray(body_size)
        _write_arrays(np.frombuffer(scratch, np.uint8), table, wired)
        compressed = zlib.compress(scratch, compress_level)
        stored = len(compressed)
        buf = _target(out, BODY_OFFSET + stored + len(meta))
        buf[BODY_OFFSET:BODY_OFFSET + stored] = compressed
    flags = 0 if compress_level is None else FLAG_ZLIB
    buf[:BODY_OFFSET] = bytes(BODY_OFFSET)
    HEADER.pack_into(buf, 0, MAGIC, WIRE_VERSION, flags, 0, stored, len(buf) - BODY_OFFSET - stored)
    meta_start = BODY_OFFSET + stored
    buf[meta_start:meta_start + len(meta)] = meta
    buf[meta_start + len(meta):] = b" " * (len(buf) - meta_start - len(meta))
    return buf


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
    count = math.prod(shape)
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
    if len(data) < BODY_OFFSET:
        raise DecodeError(f"payload of {len(data)} bytes is shorter than the header")
    magic, wire, flags, _, stored, meta_len = HEADER.unpack_from(data, 0)
    if magic != MAGIC:
        raise DecodeError(f"bad magic {bytes(magic)!r}: not an ovamos binary message")
    if wire != WIRE_VERSION:
        raise DecodeError(f"wire version {wire} is not supported (this build reads {WIRE_VERSION})")
    if flags & ~_KNOWN_FLAGS:
        raise DecodeError(f"unknown flags 0x{flags:02x}")
    if meta_len > MAX_META_BYTES or BODY_OFFSET + stored + meta_len != len(data):
        raise DecodeError(f"header declares {stored} body + {meta_len} meta bytes, "
                          f"payload holds {len(data) - BODY_OFFSET}")
    meta_start = BODY_OFFSET + stored
    try:
        meta = json.loads(bytes(data[meta_start:]))
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

    body: bytes | memoryview = data[BODY_OFFSET:meta_start]
    if flags & FLAG_ZLIB:
        body = _decompress(body, body_size)
    elif stored != body_size:
        raise DecodeError(f"body holds {stored} bytes, meta declares {body_size}")

    arrays: dict[str, np.ndarray] = {}
    end = 0
    for entry in table:
        name, view, end = _array_view(body, entry, end)
        if name in arrays:
            raise DecodeError(f"array {name!r} appears twice")
        arrays[name] = view
    return fields, arrays
