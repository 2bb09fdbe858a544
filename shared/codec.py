"""Binary wire format for messages that carry arrays (RGB-D frames, map grids).

Layout of one payload::

    header  <4s B B H Q I I>  magic b"OVAM", wire version, flags, slack length,
                              stored body length, layout length, fields length
    padding                   zeros up to BODY_OFFSET
    body                      the raw array bytes, each array at an ALIGN-ed offset;
                              zlib-compressed as a whole when FLAG_ZLIB is set
    layout  UTF-8 JSON        {"kind", "v", "arrays": [[name, dtype, shape, offset]], "body"}
    fields  UTF-8 JSON        the message's scalar fields
    slack                     spaces (room for the fields to change size in a reused buffer)

Why this shape: JSON for the few scalar fields keeps them readable and
versionable with pydantic, while arrays travel as raw little-endian bytes so the
receiver gets ``numpy.frombuffer`` views without a copy. The body sits at a
fixed offset and the variable-length parts after it, so a producer can
:func:`loan` arrays that already live inside a payload buffer, fill them (a
renderer writes its pixels there) and publish with no copy before Zenoh's own.
The layout of a stream rarely changes, so both ends cache it: per message only
the fields are encoded and parsed.

Everything read from the wire is checked before use; any inconsistency raises
:class:`DecodeError`, the one error a subscriber has to catch.
"""

from __future__ import annotations

import functools
import json
import math
import struct
import weakref
import zlib
from collections.abc import Callable, Mapping
from typing import Any, NamedTuple

import numpy as np
from pydantic_core import from_json

MAGIC = b"OVAM"
WIRE_VERSION = 1
FLAG_ZLIB = 0x01
_KNOWN_FLAGS = FLAG_ZLIB
HEADER = struct.Struct("<4sBBHQII")
BODY_OFFSET = 64
ALIGN = 64
# Room for the fields to grow while a payload buffer is reused as is.
SLACK = 4096
# Explicit little-endian dtypes only: the wire format must not depend on the host.
ALLOWED_DTYPES = frozenset(np.dtype(d).str for d in (
    "|b1", "|u1", "|i1", "<u2", "<i2", "<u4", "<i4", "<u8", "<i8", "<f2", "<f4", "<f8"))
# Bounds a hostile header or a zip bomb cannot push us past.
MAX_META_BYTES = 1 << 20
# Layouts are cached; the cap bounds what a hostile peer can make the cache hold.
MAX_LAYOUT_BYTES = 1 << 14
# The codec's own ceiling on any body; each message type declares a tighter one (its largest
# honest arrays, see ``BinaryMessage.MAX_BODY_BYTES``) that :func:`unpack` checks before inflating.
MAX_BODY_BYTES = 1 << 30
MAX_NDIM = 8

Spec = tuple[tuple[int, ...], str]  # (shape, dtype str) of one array


class DecodeError(ValueError):
    """A payload that is not a valid message of the expected kind and version."""


class _Slot(NamedTuple):
    name: str
    dtype: np.dtype
    shape: tuple[int, ...]
    offset: int
    count: int


class _Layout(NamedTuple):
    kind: str
    version: int
    slots: tuple[_Slot, ...]
    body_size: int
    encoded: bytes


def _align(n: int) -> int:
    return (n + ALIGN - 1) // ALIGN * ALIGN


@functools.lru_cache(maxsize=256)
def _layout(kind: str, version: int, specs: tuple[tuple[str, tuple[int, ...], str], ...]) -> _Layout:
    """Where each array (name, shape, dtype) goes in the body, and that layout as JSON."""
    slots, offset = [], 0
    for name, shape, dtype in specs:
        count = math.prod(shape)
        slots.append(_Slot(name, np.dtype(dtype), shape, offset, count))
        offset = _align(offset + count * np.dtype(dtype).itemsize)
    table = [[s.name, s.dtype.str, list(s.shape), s.offset] for s in slots]
    encoded = json.dumps({"kind": kind, "v": version, "arrays": table, "body": offset},
                         separators=(",", ":")).encode()
    return _Layout(kind, version, tuple(slots), offset, encoded)


def _wire_array(name: str, arr: np.ndarray) -> np.ndarray:
    if type(arr) is np.ndarray and arr.dtype.str in ALLOWED_DTYPES and arr.flags.c_contiguous:
        return arr  # as it goes on the wire (the common case: checked first, it is a hot path)
    arr = np.asarray(arr)
    if arr.dtype.byteorder == ">":
        arr = arr.astype(arr.dtype.newbyteorder("<"))
    if arr.dtype.str not in ALLOWED_DTYPES:
        raise TypeError(f"array {name!r}: dtype {arr.dtype} cannot be sent; "
                        f"allowed: {sorted(ALLOWED_DTYPES)}")
    return np.ascontiguousarray(arr)


#: id(array) -> (weak reference to it, its buffer, its offset in the buffer) for every loaned array
#: alive: how :func:`pack` knows a loan without asking numpy where the memory is (which costs tens
#: of microseconds a frame once 2 MB went through the caches)
_LOANS: dict[int, tuple[weakref.ref[np.ndarray], bytearray, int]] = {}


def _forget_loan(key: int) -> Callable[[weakref.ref[np.ndarray]], None]:
    return lambda _ref: _LOANS.pop(key, None)


def _spec_layout(arrays: Mapping[str, Spec]) -> _Layout:
    """The layout of arrays named -> (shape, dtype), in this order."""
    return _layout("", 0, tuple((n, tuple(shape), np.dtype(d).str) for n, (shape, d) in arrays.items()))


def body_size(arrays: Mapping[str, Spec]) -> int:
    """Body bytes of a payload with these arrays (name -> (shape, dtype)), padding included: what
    a message type's largest honest arrays take, from which its decode limit is derived."""
    return _spec_layout(arrays).body_size


def loan(arrays: Mapping[str, Spec]) -> dict[str, np.ndarray]:
    """Writable arrays (name -> (shape, dtype)) that live inside a fresh payload buffer.

    A message built from exactly these arrays, in this order, is packed without
    copying them: its payload *is* the loan's buffer, so encoding a second
    message from the same loan rewrites the first payload. Publishing is safe
    (Zenoh copies during ``put``); a payload kept for later needs ``bytes(...)``.
    Filling the arrays is the producer's job (they start zeroed).
    """
    layout = _spec_layout(arrays)
    buffer = bytearray(BODY_OFFSET + layout.body_size + SLACK)
    loaned = {}
    for s in layout.slots:
        arr = np.frombuffer(buffer, s.dtype, s.count, BODY_OFFSET + s.offset).reshape(s.shape)
        _LOANS[id(arr)] = (weakref.ref(arr, _forget_loan(id(arr))), buffer, BODY_OFFSET + s.offset)
        loaned[s.name] = arr
    return loaned


def _loaned_buffer(arrays: list[np.ndarray], layout: _Layout) -> bytearray | None:
    """The buffer the arrays were loaned from, if they are all from one loan and each sits at its
    wire offset (an array keeps its memory for life, and the buffer cannot move while it is alive)."""
    buffer = None
    for slot, arr in zip(layout.slots, arrays):
        entry = _LOANS.get(id(arr))
        if entry is None or entry[0]() is not arr or entry[2] != BODY_OFFSET + slot.offset \
                or (buffer is not None and entry[1] is not buffer):
            return None
        buffer = entry[1]
    return buffer


def _target(out: bytearray | None, size: int) -> bytearray:
    """``out`` when it can hold ``size`` bytes plus at most SLACK, else a buffer that can."""
    if out is None:
        return bytearray(size)
    if not size <= len(out) <= size + SLACK:
        try:
            del out[size:]
            out.extend(bytes(size - len(out)))
        except BufferError:  # a loaned buffer whose arrays are alive cannot be resized
            return bytearray(size)
    return out


def _write_arrays(body: np.ndarray, layout: _Layout, arrays: list[np.ndarray]) -> None:
    for slot, arr in zip(layout.slots, arrays):
        end = slot.offset + arr.nbytes
        body[slot.offset:end] = arr.reshape(-1).view(np.uint8)
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
    if not isinstance(fields, bytes):
        fields = json.dumps(fields, separators=(",", ":")).encode()
    wired = [_wire_array(name, a) for name, a in arrays.items()]
    layout = _layout(kind, version, tuple((n, a.shape, a.dtype.str) for n, a in zip(arrays, wired)))
    meta_size = len(layout.encoded) + len(fields)
    if compress_level is None:
        loaned = _loaned_buffer(wired, layout)
        stored = layout.body_size
        buf = _target(loaned if loaned is not None else out, BODY_OFFSET + stored + meta_size)
        if buf is not loaned:
            _write_arrays(np.frombuffer(buf, np.uint8, stored, BODY_OFFSET), layout, wired)
    else:
        scratch = bytearray(layout.body_size)
        _write_arrays(np.frombuffer(scratch, np.uint8), layout, wired)
        compressed = zlib.compress(scratch, compress_level)
        stored = len(compressed)
        buf = _target(out, BODY_OFFSET + stored + meta_size)
        buf[BODY_OFFSET:BODY_OFFSET + stored] = compressed
    flags = 0 if compress_level is None else FLAG_ZLIB
    meta_start = BODY_OFFSET + stored
    slack = len(buf) - meta_start - meta_size
    buf[:BODY_OFFSET] = bytes(BODY_OFFSET)
    HEADER.pack_into(buf, 0, MAGIC, WIRE_VERSION, flags, slack, stored, len(layout.encoded), len(fields))
    buf[meta_start:] = layout.encoded + fields + b" " * slack
    return buf


def _is_count(value: Any) -> bool:
    """A JSON integer in [0, MAX_BODY_BYTES] (JSON floats, inf and bools are not)."""
    return type(value) is int and 0 <= value <= MAX_BODY_BYTES


@functools.lru_cache(maxsize=256)
def _parse_layout(encoded: bytes) -> _Layout:
    """A layout read from the wire, checked once per distinct layout (cached)."""
    try:
        meta = json.loads(encoded)
        kind, version, table, body_size = meta["kind"], meta["v"], meta["arrays"], meta["body"]
    except (ValueError, KeyError, TypeError, RecursionError) as exc:
        raise DecodeError(f"layout is not valid: {type(exc).__name__}: {exc}") from None
    if not isinstance(kind, str) or type(version) is not int or not isinstance(table, list):
        raise DecodeError("layout kind/v/arrays have the wrong types")
    if not _is_count(body_size):
        raise DecodeError(f"body size {body_size!r} is not an integer within bounds")
    slots, names, end = [], set(), 0
    for entry in table:
        if not (isinstance(entry, list) and len(entry) == 4 and isinstance(entry[0], str)
                and isinstance(entry[1], str) and isinstance(entry[2], list)
                and len(entry[2]) <= MAX_NDIM and all(map(_is_count, entry[2]))
                and _is_count(entry[3])):
            raise DecodeError(f"bad array table entry {str(entry)[:200]}")
        name, dtype_str, shape, offset = entry[0], entry[1], tuple(entry[2]), entry[3]
        try:
            dtype = np.dtype(dtype_str)
        except (TypeError, ValueError):
            raise DecodeError(f"array {name!r}: unknown dtype {dtype_str!r}") from None
        if name in names or dtype.str not in ALLOWED_DTYPES:
            raise DecodeError(f"array {name!r}: duplicate, or dtype {dtype_str!r} not allowed")
        if offset < end or offset % ALIGN:
            raise DecodeError(f"array {name!r}: offset {offset} overlaps or is not aligned")
        count = math.prod(shape)
        end = offset + count * dtype.itemsize
        if end > body_size:
            raise DecodeError(f"array {name!r} needs body bytes up to {end}, body holds {body_size}")
        names.add(name)
        slots.append(_Slot(name, dtype, shape, offset, count))
    return _Layout(kind, version, tuple(slots), body_size, encoded)


def _decompress(data: memoryview, size: int) -> bytes:
    """The body inflated, never past ``size`` + 1 bytes: a stream that would inflate further (its
    declared size lies) stops there and is refused, so memory is bounded by what was checked."""
    inflater = zlib.decompressobj()
    try:
        body = inflater.decompress(data, size + 1)  # max_length 0 would mean "no limit"
    except zlib.error as exc:
        raise DecodeError(f"compressed body is corrupt: {exc}") from None
    if len(body) > size:
        raise DecodeError(f"compressed body inflates past the declared {size} bytes")
    if len(body) != size or not inflater.eof or inflater.unused_data:
        raise DecodeError(f"compressed body does not inflate to the declared {size} bytes")
    return body


def unpack(payload: bytes | bytearray | memoryview, kind: str, version: int,
           max_body: int = MAX_BODY_BYTES) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """Decode a payload of the given kind and version into (fields, arrays).

    ``max_body`` is the most body bytes a message of this kind may declare (its largest honest
    arrays): a larger one is refused before anything is parsed or inflated, so a small
    compressed payload cannot make the receiver allocate more than that.

    Arrays are views into ``payload`` (read-only when it is ``bytes``), so the
    payload must stay alive as long as they do; numpy's views keep it referenced.
    """
    data = memoryview(payload)
    if len(data) < BODY_OFFSET:
        raise DecodeError(f"payload of {len(data)} bytes is shorter than the header")
    magic, wire, flags, slack, stored, layout_len, fields_len = HEADER.unpack_from(data, 0)
    if magic != MAGIC:
        raise DecodeError(f"bad magic {bytes(magic)!r}: not an ovamos binary message")
    if wire != WIRE_VERSION:
        raise DecodeError(f"wire version {wire} is not supported (this build reads {WIRE_VERSION})")
    if flags & ~_KNOWN_FLAGS:
        raise DecodeError(f"unknown flags 0x{flags:02x}")
    if layout_len + fields_len > MAX_META_BYTES or \
            BODY_OFFSET + stored + layout_len + fields_len + slack != len(data):
        raise DecodeError(f"header declares {stored} + {layout_len} + {fields_len} + {slack} bytes "
                          f"after the header, payload holds {len(data) - BODY_OFFSET}")
    meta_start = BODY_OFFSET + stored
    if layout_len > MAX_LAYOUT_BYTES:
        raise DecodeError(f"layout of {layout_len} bytes exceeds {MAX_LAYOUT_BYTES}")
    layout = _parse_layout(bytes(data[meta_start:meta_start + layout_len]))
    if layout.kind != kind:
        raise DecodeError(f"expected a {kind!r} message, got {layout.kind!r}")
    if layout.version != version:
        raise DecodeError(f"{kind} version {layout.version!r} is not supported (expected {version})")
    if layout.body_size > max_body:
        raise DecodeError(f"{kind} body of {layout.body_size} bytes exceeds the {max_body} bytes "
                          f"a {kind} message may declare")
    try:
        # pydantic's Rust parser: the fields are parsed per message (the layout once, cached), and
        # json.loads' Python layers cost twice as much, more on a cold cache between frames.
        fields = from_json(bytes(data[meta_start + layout_len:meta_start + layout_len + fields_len]))
    except ValueError as exc:
        raise DecodeError(f"fields are not valid JSON: {exc}") from None
    if not isinstance(fields, dict):
        raise DecodeError("fields must be a JSON object")

    body: bytes | memoryview = data[BODY_OFFSET:meta_start]
    if flags & FLAG_ZLIB:
        body = _decompress(body, layout.body_size)
    elif stored != layout.body_size:
        raise DecodeError(f"body holds {stored} bytes, layout declares {layout.body_size}")
    arrays = {s.name: np.frombuffer(body, s.dtype, s.count, s.offset).reshape(s.shape)
              for s in layout.slots}
    return fields, arrays
