"""Wire-format tests for ovamos.shared.codec and the messages built on it.

The codec is the one place where bytes from the network meet numpy, so these
tests pin three promises: what a producer sends is what a consumer gets, bit
for bit; arrays arrive as zero-copy read-only views; and anything malformed
surfaces as :class:`DecodeError`, the only exception a subscriber catches.
"""

from __future__ import annotations

import json
import zlib
from collections.abc import Callable
from typing import Any, NamedTuple

import numpy as np
import pytest
from hypothesis import HealthCheck, assume, example, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp
from pydantic import ValidationError

from ovamos.shared import codec
from ovamos.shared.codec import BODY_OFFSET, FLAG_ZLIB, HEADER, MAGIC, WIRE_VERSION, DecodeError, loan, pack, unpack
from ovamos.shared.messages import CounterSet, Intrinsics, MapSnapshot, ObjectInstance, RgbdFrame, ServiceStats

SETTINGS = settings(max_examples=50, deadline=None,
                    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])

# ---------------------------------------------------------------------------------------------
# Strategies
# ---------------------------------------------------------------------------------------------

finite = st.floats(allow_nan=False, allow_infinity=False)
positive = st.floats(min_value=1e-6, max_value=1e6, allow_nan=False, allow_infinity=False)
small_text = st.text(max_size=12)
finite_depth = st.floats(width=32, allow_nan=False, allow_infinity=False)  # a frame's float depth is finite


@st.composite
def rgbd_frames(draw: st.DrawFn, max_side: int = 32) -> RgbdFrame:
    """Any valid RgbdFrame with a small image, every optional part exercised."""
    h = draw(st.integers(1, max_side))
    w = draw(st.integers(1, max_side))
    depth_dtype = draw(st.sampled_from([np.dtype("<f4"), np.dtype("<u2")]))
    with_ids = draw(st.booleans())
    return RgbdFrame(
        seq=draw(st.integers(0, 2**63 - 1)),
        stamp=draw(finite),
        intrinsics=Intrinsics(fx=draw(positive), fy=draw(positive), cx=draw(finite), cy=draw(finite)),
        camera_pose=tuple(draw(st.lists(finite, min_size=16, max_size=16))),
        depth_scale=draw(positive),
        rgb=draw(hnp.arrays(np.uint8, (h, w, 3))),
        depth=draw(hnp.arrays(depth_dtype, (h, w), elements=finite_depth if depth_dtype.kind == "f" else None)),
        instance_ids=draw(hnp.arrays(np.dtype("<i4"), (h, w))) if with_ids else None,
    )


objects = st.builds(ObjectInstance, label=small_text, x=finite, y=finite, z=finite, score=finite,
                    hits=st.integers(0, 10**6), confirmed=st.booleans())


@st.composite
def map_snapshots(draw: st.DrawFn) -> MapSnapshot:
    """Any valid MapSnapshot: empty grids and empty frontier lists included."""
    h = draw(st.integers(0, 24))
    w = draw(st.integers(0, 24))
    layers = tuple(draw(st.lists(small_text, max_size=3)))
    n = draw(st.integers(0, 6))
    return MapSnapshot(
        seq=draw(st.integers(-1, 2**31)),
        stamp=draw(finite),
        resolution=draw(positive),
        origin=(draw(finite), draw(finite)),
        layers=layers,
        objects=tuple(draw(st.lists(objects, max_size=3))),
        obstacle=draw(hnp.arrays(np.bool_, (h, w))),
        explored=draw(hnp.arrays(np.bool_, (h, w))),
        counts=draw(hnp.arrays(np.dtype("<u2"), (len(layers), h, w))),
        values=draw(hnp.arrays(np.dtype("<f4"), (len(layers), h, w))),
        frontiers=draw(hnp.arrays(np.dtype("<f8"), (n, 2))),
        confidence=draw(st.none() | hnp.arrays(np.dtype("<f4"), (len(layers), h, w))),
    )


messages = st.one_of(rgbd_frames(max_side=8), map_snapshots())


def service_stats(**overrides: Any) -> ServiceStats:
    base: dict[str, Any] = dict(robot_id="r1", service="mapping", instance="i0", pid=42, started=1.5,
                                counters={"rgbd": CounterSet(received=3, dropped=1)},
                                info={"frames": 7, "nested": {"a": [1, 2.5, None]}})
    base.update(overrides)
    return ServiceStats(**base)


# ---------------------------------------------------------------------------------------------
# Helpers
# ---------------------------------------------------------------------------------------------


def assert_same_array(got: np.ndarray | None, want: np.ndarray | None) -> None:
    """Same dtype, shape and bits (NaN payloads and -0.0 included)."""
    if want is None:
        assert got is None
        return
    assert got is not None
    assert got.dtype == want.dtype and got.shape == want.shape
    assert np.array_equal(got, want, equal_nan=got.dtype.kind == "f")
    assert got.tobytes() == want.tobytes()


def assert_same_message(got: RgbdFrame | MapSnapshot, want: RgbdFrame | MapSnapshot) -> None:
    assert type(got) is type(want)
    arrays = set(type(want).ARRAYS)
    assert got.model_dump(exclude=arrays) == want.model_dump(exclude=arrays)
    # JSON text tells -0.0 from 0.0 and shows every float digit: exact, not just ==.
    assert got.model_dump_json(exclude=arrays) == want.model_dump_json(exclude=arrays)
    for name in arrays:
        assert_same_array(getattr(got, name), getattr(want, name))


class Parts(NamedTuple):
    """A payload taken apart (see the layout in ovamos.shared.codec's docstring)."""

    flags: int
    body: bytes
    layout: bytes
    fields: bytes


def split(payload: bytes | bytearray) -> Parts:
    _, _, flags, _, stored, layout_len, fields_len = HEADER.unpack_from(payload, 0)
    start = BODY_OFFSET + stored
    return Parts(flags, bytes(payload[BODY_OFFSET:start]), bytes(payload[start:start + layout_len]),
                 bytes(payload[start + layout_len:start + layout_len + fields_len]))


def assemble(flags: int, body: bytes, layout: bytes, fields: bytes = b"{}", *, slack: int = 0,
             magic: bytes = MAGIC, wire: int = WIRE_VERSION) -> bytes:
    """A payload with a consistent header around the given parts."""
    buf = bytearray(BODY_OFFSET)
    HEADER.pack_into(buf, 0, magic, wire, flags, slack, len(body), len(layout), len(fields))
    return bytes(buf) + body + layout + fields + b" " * slack


def with_meta(payload: bytes | bytearray, edit: Callable[[dict[str, Any]], None]) -> bytes:
    """The payload after ``edit`` changed its meta, header fixed up to match.

    ``edit`` sees the layout's keys (kind, v, arrays, body) plus ``fields``.
    """
    parts = split(payload)
    meta = {**json.loads(parts.layout), "fields": json.loads(parts.fields)}
    edit(meta)
    fields = meta.pop("fields", {})
    return assemble(parts.flags, parts.body, json.dumps(meta).encode(), json.dumps(fields).encode())


def sample_frame(h: int = 4, w: int = 5, *, ids: bool = True) -> RgbdFrame:
    rng = np.random.default_rng(1)
    return RgbdFrame(seq=3, stamp=12.5, intrinsics=Intrinsics(fx=10, fy=11, cx=2, cy=1.5),
                     rgb=rng.integers(0, 256, (h, w, 3), dtype=np.uint8),
                     depth=rng.random((h, w), dtype=np.float32),
                     instance_ids=rng.integers(-5, 5, (h, w), dtype=np.int32) if ids else None)


def sample_map(n: int = 6) -> MapSnapshot:
    rng = np.random.default_rng(2)
    return MapSnapshot(seq=4, stamp=2.0, resolution=0.05, origin=(-1.0, 2.0), layers=("chair", "bed"),
                       objects=(ObjectInstance(label="chair", x=1, y=2, score=0.9, hits=3),),
                       obstacle=rng.random((n, n)) > 0.5, explored=rng.random((n, n)) > 0.3,
                       counts=rng.integers(0, 9, (2, n, n), dtype=np.uint16),
                       values=rng.random((2, n, n), dtype=np.float32),
                       frontiers=rng.random((3, 2)))


RGBD_FIELDS = {"seq": 0, "stamp": 0.0, "intrinsics": {"fx": 1.0, "fy": 1.0, "cx": 0.0, "cy": 0.0}}

# ---------------------------------------------------------------------------------------------
# Round trips
# ---------------------------------------------------------------------------------------------


@SETTINGS
@given(rgbd_frames())
def test_rgbd_frame_round_trip_is_exact(frame: RgbdFrame) -> None:
    """Every field and every pixel survives encoding unchanged (floats bit-exact)."""
    decoded = RgbdFrame.from_bytes(bytes(frame.to_bytes()))
    assert_same_message(decoded, frame)
    assert decoded.camera_pose == frame.camera_pose


@SETTINGS
@given(map_snapshots())
def test_map_snapshot_round_trip_is_exact(snapshot: MapSnapshot) -> None:
    """Grids, layers, frontiers and objects survive the compressed encoding unchanged."""
    payload = bytes(snapshot.to_bytes())
    assert payload[5] & FLAG_ZLIB, "maps are meant to travel compressed"
    decoded = MapSnapshot.from_bytes(payload)
    assert_same_message(decoded, snapshot)
    assert decoded.objects == snapshot.objects
    assert decoded.layers == snapshot.layers


@SETTINGS
@given(messages)
def test_decodes_from_bytes_bytearray_and_memoryview(msg: RgbdFrame | MapSnapshot) -> None:
    """Zenoh hands payloads over in different buffer types; all decode the same."""
    payload = msg.to_bytes()
    for data in (bytes(payload), bytearray(payload), memoryview(bytes(payload))):
        assert_same_message(type(msg).from_bytes(data), msg)


@SETTINGS
@given(rgbd_frames(max_side=8), rgbd_frames(max_side=8))
def test_reused_out_buffer_gives_the_second_message(first: RgbdFrame, second: RgbdFrame) -> None:
    """A stream reusing its previous payload as ``out`` must not leak the old message."""
    buf = first.to_bytes()
    again = second.to_bytes(out=buf)
    assert_same_message(RgbdFrame.from_bytes(bytes(again)), second)


@SETTINGS
@given(messages, messages)
def test_reused_buffer_holds_exactly_the_fresh_encoding(first: RgbdFrame | MapSnapshot,
                                                        second: RgbdFrame | MapSnapshot) -> None:
    """Nothing of the old payload survives in a reused one (padding included): no leaks."""
    buf = first.to_bytes()
    buf[BODY_OFFSET:] = b"\xff" * (len(buf) - BODY_OFFSET)  # old bytes, easy to spot
    reused = bytes(second.to_bytes(out=buf))
    fresh = bytes(second.to_bytes())
    slack = HEADER.unpack_from(reused, 0)[3]
    assert reused[BODY_OFFSET:len(reused) - slack] == fresh[BODY_OFFSET:]
    assert reused[len(reused) - slack:] == b" " * slack
    assert reused[:BODY_OFFSET].rstrip(b"\x00") != b""  # a header is there
    assert bytes(reused[HEADER.size:BODY_OFFSET]) == bytes(BODY_OFFSET - HEADER.size)


def test_loaned_arrays_are_published_without_a_copy() -> None:
    """Arrays from RgbdFrame.loan become the payload itself, and decode to what was written."""
    arrays = RgbdFrame.loan(6, 7, depth_dtype="<u2", instance_ids=True)
    arrays["rgb"][:] = 200
    arrays["depth"][:] = np.arange(7, dtype=np.uint16)
    arrays["instance_ids"][2, 3] = -9
    frame = RgbdFrame(seq=1, stamp=0.5, intrinsics=Intrinsics(fx=1, fy=1, cx=0, cy=0), **arrays)
    payload = frame.to_bytes()
    assert np.shares_memory(np.frombuffer(payload, np.uint8), arrays["rgb"])
    assert_same_message(RgbdFrame.from_bytes(bytes(payload)), frame)


def test_arrays_that_are_not_one_loan_in_place_are_copied() -> None:
    """Only a loan's own arrays, all from one loan and each at its wire offset, are the payload:
    arrays from two loans, a view of a loaned array, or loaned arrays in another order are
    copied into a payload of their own, and every one decodes to what was written."""
    first, second = loan({"a": ((4,), "<f4"), "b": ((3,), "|u1")}), loan({"a": ((4,), "<f4"), "b": ((3,), "|u1")})
    for arrays in (first, second):
        arrays["a"][:] = np.arange(4)
        arrays["b"][:] = 7
    cases = {"one loan": (first, True), "two loans": ({"a": first["a"], "b": second["b"]}, False),
             "a view": ({"a": first["a"][:], "b": first["b"]}, False),
             "another order": ({"b": first["b"], "a": first["a"]}, False)}
    for case, (arrays, in_place) in cases.items():
        payload = pack("k", 1, {}, arrays)
        assert np.shares_memory(np.frombuffer(payload, np.uint8), first["a"]) is in_place, case
        _, got = unpack(bytes(payload), "k", 1)
        for name, arr in arrays.items():
            assert_same_array(got[name], arr)


def test_a_loan_is_forgotten_when_its_arrays_die() -> None:
    """The loan registry holds no array alive and does not grow with the frames of a stream."""
    before = len(codec._LOANS)
    for _ in range(50):
        arrays = RgbdFrame.loan(4, 5)
        assert len(codec._LOANS) == before + 2
        del arrays
    assert len(codec._LOANS) == before


def test_big_endian_arrays_go_out_little_endian() -> None:
    """The wire is host-independent: a '>f4' array is sent as '<f4' with the same values."""
    arr = np.arange(6, dtype=">f4").reshape(2, 3)
    _, arrays = unpack(bytes(pack("k", 1, {}, {"a": arr})), "k", 1)
    assert arrays["a"].dtype.str == "<f4"
    assert np.array_equal(arrays["a"], arr)


def test_unpack_returns_the_fields_and_arrays_it_was_given() -> None:
    """The low-level API, as services without a message class would use it."""
    fields = {"x": 1, "s": "é", "l": [1.5, None]}
    arrays = {"a": np.arange(5, dtype=np.int64), "b": np.zeros((0, 3), np.float32),
              "c": np.array([True, False])}
    for level in (None, 6):
        got_fields, got_arrays = unpack(bytes(pack("k", 3, fields, arrays, compress_level=level)), "k", 3)
        assert got_fields == fields
        assert list(got_arrays) == list(arrays)
        for name, arr in arrays.items():
            assert_same_array(got_arrays[name], arr)


def test_pack_refuses_arrays_the_wire_cannot_carry() -> None:
    """Object and complex arrays cannot be sent as raw bytes; the producer hears of it."""
    for arr in (np.array([object()], dtype=object), np.zeros(2, np.complex64)):
        with pytest.raises(TypeError):
            pack("k", 1, {}, {"a": arr})


# ---------------------------------------------------------------------------------------------
# Zero-copy, read-only views
# ---------------------------------------------------------------------------------------------


@SETTINGS
@given(rgbd_frames())
def test_decoded_frame_arrays_are_read_only_views_of_the_payload(frame: RgbdFrame) -> None:
    """A subscriber gets views into the received bytes: no copy, and no way to corrupt them."""
    payload = bytes(frame.to_bytes())
    whole = np.frombuffer(payload, np.uint8)
    decoded = RgbdFrame.from_bytes(payload)
    for name in RgbdFrame.ARRAYS:
        arr = getattr(decoded, name)
        if arr is None:
            continue
        assert not arr.flags.writeable
        assert not arr.flags.owndata
        assert np.shares_memory(arr, whole), f"{name} was copied out of the payload"
        with pytest.raises(ValueError):
            arr.flat[0] = 0


@SETTINGS
@given(map_snapshots())
def test_decoded_map_arrays_are_read_only(snapshot: MapSnapshot) -> None:
    """Compressed maps inflate once; the arrays are read-only views of that one buffer."""
    decoded = MapSnapshot.from_bytes(bytes(snapshot.to_bytes()))
    bases = set()
    for name in MapSnapshot.ARRAYS:
        arr = getattr(decoded, name)
        if arr is None:
            assert getattr(snapshot, name) is None
            continue
        assert not arr.flags.writeable
        assert not arr.flags.owndata
        base = arr
        while isinstance(base, np.ndarray) and base.base is not None:
            base = base.base
        bases.add(id(base.obj) if isinstance(base, memoryview) else id(base))
    assert len(bases) == 1, "each array was copied separately"


# ---------------------------------------------------------------------------------------------
# Malformed payloads: DecodeError and nothing else
# ---------------------------------------------------------------------------------------------


@SETTINGS
@given(messages, st.data())
def test_every_truncation_is_rejected(msg: RgbdFrame | MapSnapshot, data: st.DataObject) -> None:
    """A payload cut short anywhere (lost fragment, short read) is never half-decoded."""
    payload = bytes(msg.to_bytes())
    cut = data.draw(st.integers(0, len(payload) - 1), label="cut")
    with pytest.raises(DecodeError):
        type(msg).from_bytes(payload[:cut])


@SETTINGS
@given(messages, st.binary(min_size=1, max_size=64))
def test_trailing_bytes_are_rejected(msg: RgbdFrame | MapSnapshot, extra: bytes) -> None:
    """The header's lengths must account for the whole payload."""
    with pytest.raises(DecodeError):
        type(msg).from_bytes(bytes(msg.to_bytes()) + extra)


@SETTINGS
@given(messages, st.binary(min_size=4, max_size=4))
def test_wrong_magic_is_rejected(msg: RgbdFrame | MapSnapshot, magic: bytes) -> None:
    assume(magic != MAGIC)
    payload = bytearray(msg.to_bytes())
    payload[:4] = magic
    with pytest.raises(DecodeError, match="magic"):
        type(msg).from_bytes(bytes(payload))


@SETTINGS
@given(messages, st.integers(0, 255))
def test_wrong_wire_version_is_rejected(msg: RgbdFrame | MapSnapshot, wire: int) -> None:
    assume(wire != WIRE_VERSION)
    payload = bytearray(msg.to_bytes())
    payload[4] = wire
    with pytest.raises(DecodeError, match="wire version"):
        type(msg).from_bytes(bytes(payload))


@SETTINGS
@given(messages, st.integers(0, 255))
def test_unknown_flags_are_rejected(msg: RgbdFrame | MapSnapshot, extra_flags: int) -> None:
    """A flag this build does not know could change the meaning of the body."""
    assume(extra_flags & ~FLAG_ZLIB)
    payload = bytearray(msg.to_bytes())
    payload[5] |= extra_flags
    with pytest.raises(DecodeError, match="flags"):
        type(msg).from_bytes(bytes(payload))


def test_wrong_message_kind_is_rejected() -> None:
    """A frame published on a map key (or vice versa) is refused, not misread."""
    with pytest.raises(DecodeError, match="rgbd"):
        MapSnapshot.from_bytes(bytes(sample_frame().to_bytes()))
    with pytest.raises(DecodeError, match="map"):
        RgbdFrame.from_bytes(bytes(sample_map().to_bytes()))


@pytest.mark.parametrize("version", [0, 2, 99])
def test_wrong_message_version_is_rejected(version: int) -> None:
    frame = sample_frame()
    arrays = {n: getattr(frame, n) for n in RgbdFrame.ARRAYS}
    payload = bytes(pack(RgbdFrame.KIND, version, frame.model_dump(mode="json", exclude=set(arrays)),
                         arrays))
    with pytest.raises(DecodeError, match="version"):
        RgbdFrame.from_bytes(payload)
    # The same payload with the right version decodes: the version alone made it fail.
    good = bytes(pack(RgbdFrame.KIND, RgbdFrame.VERSION,
                      frame.model_dump(mode="json", exclude=set(arrays)), arrays))
    assert_same_message(RgbdFrame.from_bytes(good), frame)


@pytest.mark.parametrize("dtype", ["|O", ">f4", ">u2", "<c8", "|V4", "<M8[s]", "not-a-dtype", 5, None])
def test_disallowed_dtype_in_array_table_is_rejected(dtype: Any) -> None:
    """Only explicit little-endian plain dtypes may come off the wire (no objects, no host order)."""
    def edit(meta: dict[str, Any]) -> None:
        meta["arrays"][1][1] = dtype  # the depth entry

    payload = with_meta(sample_frame().to_bytes(), edit)
    with pytest.raises(DecodeError):
        unpack(payload, RgbdFrame.KIND, RgbdFrame.VERSION)  # the codec itself refuses it
    with pytest.raises(DecodeError):
        RgbdFrame.from_bytes(payload)


def test_inconsistent_shapes_are_rejected() -> None:
    """rgb 4x4x3 with depth 5x5 packs fine at the codec level but is not a valid frame."""
    payload = bytes(pack(RgbdFrame.KIND, RgbdFrame.VERSION, RGBD_FIELDS,
                         {"rgb": np.zeros((4, 4, 3), np.uint8), "depth": np.zeros((5, 5), np.float32)}))
    with pytest.raises(DecodeError, match="rgb"):
        RgbdFrame.from_bytes(payload)


@pytest.mark.parametrize("arrays", [
    {"rgb": np.zeros((4, 4, 3), np.float32), "depth": np.zeros((4, 4), np.float32)},
    {"rgb": np.zeros((4, 4), np.uint8), "depth": np.zeros((4, 4), np.float32)},
    {"rgb": np.zeros((4, 4, 3), np.uint8), "depth": np.zeros((4, 4), np.float64)},
    {"rgb": np.zeros((4, 4, 3), np.uint8)},
    {"rgb": np.zeros((4, 4, 3), np.uint8), "depth": np.zeros((4, 4), np.float32),
     "surprise": np.zeros(1, np.uint8)},
], ids=["rgb-float", "rgb-2d", "depth-f8", "no-depth", "extra-array"])
def test_arrays_a_frame_does_not_accept_are_rejected(arrays: dict[str, np.ndarray]) -> None:
    """Decoding re-checks what the producer-side validation would have checked."""
    with pytest.raises(DecodeError):
        RgbdFrame.from_bytes(bytes(pack(RgbdFrame.KIND, RgbdFrame.VERSION, RGBD_FIELDS, arrays)))


Edit = Callable[[dict[str, Any]], None]

_BAD_LAYOUTS: dict[str, Edit] = {
    "misaligned-offset": lambda m: m["arrays"][1].__setitem__(3, m["arrays"][1][3] + 1),
    "overlapping-offset": lambda m: m["arrays"][1].__setitem__(3, 0),
    # On the last array: an earlier one would trip the overlap check instead.
    "offset-past-body": lambda m: m["arrays"][-1].__setitem__(3, 10**6),
    "last-array-one-item-too-long":  # instance_ids, 4 bytes an item, reaching 4 bytes past the body
        lambda m: m["arrays"][-1].__setitem__(2, [(m["body"] - m["arrays"][-1][3]) // 4 + 1]),
    "negative-dimension": lambda m: m["arrays"][1].__setitem__(2, [4, -5]),
    "shape-past-body": lambda m: m["arrays"][-1].__setitem__(2, [40, 50]),
    "duplicate-name": lambda m: m["arrays"][1].__setitem__(0, "rgb"),
    "short-entry": lambda m: m["arrays"].__setitem__(1, ["depth", "<f4"]),
    "table-not-a-list": lambda m: m.__setitem__("arrays", {"rgb": 1}),
    "body-size-lies": lambda m: m.__setitem__("body", m["body"] + 64),
    "negative-body-size": lambda m: m.__setitem__("body", -1),
    "fields-not-an-object": lambda m: m.__setitem__("fields", [1, 2]),
    "no-kind": lambda m: m.pop("kind"),
    "no-version": lambda m: m.pop("v"),
    "kind-not-a-string": lambda m: m.__setitem__("kind", ["rgbd"]),
}
_BAD_FIELDS: dict[str, Edit] = {
    "unknown-field": lambda m: m["fields"].__setitem__("bogus", 1),
    "missing-field": lambda m: m["fields"].pop("intrinsics"),
    "negative-seq": lambda m: m["fields"].__setitem__("seq", -1),
    "short-pose": lambda m: m["fields"].__setitem__("camera_pose", [1.0] * 15),
}


@pytest.mark.parametrize("edit", list(_BAD_LAYOUTS.values()), ids=list(_BAD_LAYOUTS))
def test_tampered_layout_is_rejected_by_the_codec(edit: Edit) -> None:
    """Each inconsistency a corrupt or hostile layout could carry is caught before use."""
    payload = with_meta(sample_frame().to_bytes(), edit)
    with pytest.raises(DecodeError):
        unpack(payload, RgbdFrame.KIND, RgbdFrame.VERSION)
    with pytest.raises(DecodeError):
        RgbdFrame.from_bytes(payload)


@pytest.mark.parametrize("edit", list(_BAD_FIELDS.values()), ids=list(_BAD_FIELDS))
def test_tampered_fields_are_rejected_by_the_message(edit: Edit) -> None:
    with pytest.raises(DecodeError):
        RgbdFrame.from_bytes(with_meta(sample_frame().to_bytes(), edit))


def test_absent_array_smuggled_in_as_a_field_is_rejected() -> None:
    payload = with_meta(sample_frame(ids=False).to_bytes(),
                        lambda m: m["fields"].__setitem__("instance_ids", [[1]]))
    with pytest.raises(DecodeError, match="instance_ids"):
        RgbdFrame.from_bytes(payload)


def test_field_named_like_an_array_is_rejected() -> None:
    """Unknown or clashing input is rejected, never silently ignored (extra='forbid' spirit)."""
    payload = with_meta(sample_frame().to_bytes(), lambda m: m["fields"].__setitem__("rgb", [[[0, 0, 0]]]))
    with pytest.raises(DecodeError):
        RgbdFrame.from_bytes(payload)


def test_untampered_meta_round_trips_through_the_helpers() -> None:
    """with_meta with a no-op edit gives a valid payload: the edits above are what fail."""
    frame = sample_frame()
    assert_same_message(RgbdFrame.from_bytes(with_meta(frame.to_bytes(), lambda m: None)), frame)


def test_meta_that_is_not_json_is_rejected() -> None:
    parts = split(sample_frame().to_bytes())
    for junk in (b"{not json", b"\xff\xfe\x00", b"[1, 2]", b'"text"', b"", b"null", b"{}"):
        with pytest.raises(DecodeError):
            RgbdFrame.from_bytes(assemble(parts.flags, parts.body, junk, parts.fields))
        with pytest.raises(DecodeError):
            RgbdFrame.from_bytes(assemble(parts.flags, parts.body, parts.layout, junk))
    # The untouched parts reassemble into a valid payload: only the junk made them fail.
    RgbdFrame.from_bytes(assemble(parts.flags, parts.body, parts.layout, parts.fields))


def test_slack_after_the_fields_is_accepted() -> None:
    """Reused buffers carry spaces after the fields; the header says how many."""
    frame = sample_frame()
    parts = split(frame.to_bytes())
    payload = assemble(parts.flags, parts.body, parts.layout, parts.fields, slack=100)
    assert_same_message(RgbdFrame.from_bytes(payload), frame)
    with pytest.raises(DecodeError):  # slack the header does not declare
        RgbdFrame.from_bytes(assemble(parts.flags, parts.body, parts.layout, parts.fields) + b" ")


def test_corrupted_compressed_body_is_rejected() -> None:
    """A map whose zlib stream is damaged is refused, never decoded into wrong cells."""
    snapshot = sample_map()
    flags, body, layout, fields = split(snapshot.to_bytes())
    size = json.loads(layout)["body"]
    assert flags & FLAG_ZLIB
    bad_bodies = [
        bytes(len(body)),                                    # zeroed
        bytes(b ^ 0xFF for b in body),                       # every bit flipped
        body[:2] + bytes(b ^ 0x55 for b in body[2:-4]) + body[-4:],  # deflate data scrambled
        bytes([body[0] ^ 0x01]) + body[1:],                  # zlib header check fails
        body[:-4] + bytes(b ^ 0xA5 for b in body[-4:]),      # adler32 mismatch
        body[: len(body) // 2],                              # stream ends early
        zlib.compress(b"\x00" * (size + 1)),                 # inflates to one byte too many
        zlib.compress(b"\x00" * (size - 1)),                 # one byte too few
    ]
    for bad in bad_bodies:
        with pytest.raises(DecodeError):
            MapSnapshot.from_bytes(assemble(flags, bad, layout, fields))
    assert_same_message(MapSnapshot.from_bytes(assemble(flags, body, layout, fields)), snapshot)


def test_single_bit_flips_in_a_compressed_body_never_yield_different_data() -> None:
    """Deflate has a few don't-care bits, so a flip may decode; but then to the same map."""
    snapshot = sample_map(4)
    flags, body, layout, fields = split(snapshot.to_bytes())
    rejected = 0
    for i in range(len(body)):
        for bit in range(8):
            bad = bytearray(body)
            bad[i] ^= 1 << bit
            try:
                decoded = MapSnapshot.from_bytes(assemble(flags, bytes(bad), layout, fields))
            except DecodeError:
                rejected += 1
                continue
            assert_same_message(decoded, snapshot)
    assert rejected > 0.9 * 8 * len(body)


@SETTINGS
@given(st.binary(max_size=512))
@example(b"")
@example(MAGIC)
@example(MAGIC + bytes([WIRE_VERSION]) + bytes(200))
def test_random_bytes_are_rejected(garbage: bytes) -> None:
    for cls in (RgbdFrame, MapSnapshot):
        with pytest.raises(DecodeError):
            cls.from_bytes(garbage)


@SETTINGS
@given(st.binary(max_size=300), st.sampled_from([0, FLAG_ZLIB]), st.binary(max_size=200),
       st.binary(max_size=200))
def test_random_parts_behind_a_valid_header_are_rejected(body: bytes, flags: int, layout: bytes,
                                                         fields: bytes) -> None:
    """Garbage that gets past the header checks still ends in DecodeError."""
    for cls in (RgbdFrame, MapSnapshot):
        with pytest.raises(DecodeError):
            cls.from_bytes(assemble(flags, body, layout, fields))


json_scalars = st.one_of(st.none(), st.booleans(), st.integers(-3, 200), finite, st.text(max_size=6),
                         st.sampled_from(["|u1", "<f4", "<u2", "<i4", "|b1", "<f8", ">f4", "|O"]))
json_values = st.recursive(json_scalars, lambda inner: st.one_of(
    st.lists(inner, max_size=4), st.dictionaries(st.text(max_size=4), inner, max_size=4)), max_leaves=12)


@SETTINGS
@given(st.data())
def test_fuzzed_meta_decodes_to_a_valid_message_or_raises_decode_error(data: st.DataObject) -> None:
    """Meta values of every JSON type in every slot: the only failure mode is DecodeError."""
    parts = split(sample_frame(2, 2).to_bytes())
    meta = {**json.loads(parts.layout), "fields": json.loads(parts.fields)}
    slot = data.draw(st.sampled_from(["kind", "v", "fields", "arrays", "body", "entry", "field",
                                      "name", "dtype", "shape", "offset"]), label="slot")
    value = data.draw(json_values, label="value")
    if slot in ("kind", "v", "fields", "arrays", "body"):
        meta[slot] = value
    elif slot == "entry":
        meta["arrays"][data.draw(st.integers(0, 2))] = value
    elif slot == "field":
        meta["fields"][data.draw(st.sampled_from(list(meta["fields"]) + ["x"]))] = value
    else:
        meta["arrays"][data.draw(st.integers(0, 2))][["name", "dtype", "shape", "offset"].index(slot)] = value
    try:
        fields = json.dumps(meta.pop("fields")).encode()
        decoded = RgbdFrame.from_bytes(assemble(parts.flags, parts.body, json.dumps(meta).encode(), fields))
    except DecodeError:
        return
    assert isinstance(decoded, RgbdFrame)


# Hostile meta that once escaped as RecursionError, OverflowError or numpy's ValueError.
_HOSTILE_META = {
    "deeply-nested-layout": b"[" * 100_000,
    "infinite-body-size": b'{"kind":"rgbd","v":1,"arrays":[],"body":Infinity}',
    "overflowing-body-size": b'{"kind":"rgbd","v":1,"arrays":[],"body":1e400}',
    "float-body-size": b'{"kind":"rgbd","v":1,"arrays":[],"body":0.0}',
    "infinite-dimension": b'{"kind":"rgbd","v":1,"arrays":[["a","|u1",[1e400],0]],"body":0}',
    "infinite-offset": b'{"kind":"rgbd","v":1,"arrays":[["a","|u1",[0],1e400]],"body":0}',
    "empty-array-with-huge-dims":
        b'{"kind":"rgbd","v":1,"arrays":[["a","|u1",[0,99999999999999999999999],0]],"body":0}',
    "empty-array-with-70-dims":
        b'{"kind":"rgbd","v":1,"arrays":[["a","|u1",[' + b",".join([b"0"] * 70) + b'],0]],"body":0}',
    "version-true": b'{"kind":"rgbd","v":true,"arrays":[],"body":0}',
    "null-dtype": b'{"kind":"rgbd","v":1,"arrays":[["a",null,[0],0]],"body":0}',
    "string-shape": b'{"kind":"rgbd","v":1,"arrays":[["a","|u1","12",0]],"body":64}',
    "string-entry": b'{"kind":"rgbd","v":1,"arrays":["ab10"],"body":64}',
}


@pytest.mark.parametrize("layout", list(_HOSTILE_META.values()), ids=list(_HOSTILE_META))
def test_hostile_layout_raises_decode_error(layout: bytes) -> None:
    """A subscriber catches DecodeError only; anything else would kill its callback."""
    for body in (b"", bytes(64)):
        with pytest.raises(DecodeError):
            unpack(assemble(0, body, layout), "rgbd", 1)
        with pytest.raises(DecodeError):
            RgbdFrame.from_bytes(assemble(0, body, layout))


@pytest.mark.parametrize("fields", [b"[" * 100_000, b'{"seq": 1', b'{"odom_session": "\\ud800"}', b"\xff\xfe{}"],
                         ids=["deeply-nested", "truncated", "lone-surrogate", "not-utf8"])
def test_malformed_fields_raise_decode_error(fields: bytes) -> None:
    parts = split(sample_frame().to_bytes())
    with pytest.raises(DecodeError, match="fields are not valid JSON"):
        RgbdFrame.from_bytes(assemble(parts.flags, parts.body, parts.layout, fields))


def test_zip_bomb_declaring_an_empty_body_is_not_inflated() -> None:
    """A ~64 KiB payload must not make a subscriber allocate 64 MiB (tracemalloc sees zlib's output)."""
    import tracemalloc

    bomb = zlib.compress(bytes(64 << 20), 9)
    payload = assemble(FLAG_ZLIB, bomb, b'{"kind":"map","v":1,"arrays":[],"body":0}')
    tracemalloc.start()
    try:
        with pytest.raises(DecodeError):
            unpack(payload, "map", 1)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < 8 << 20, f"decoding a {len(payload)} B payload peaked at {peak >> 20} MiB"


def test_body_size_is_what_pack_lays_out_and_max_body_bounds_it() -> None:
    """``body_size`` (from which each message type's limit is derived) matches what ``pack`` writes;
    ``unpack`` takes a body of exactly ``max_body`` and refuses one byte less, before inflating."""
    arrays = {"a": np.ones((3, 5), np.float32), "b": np.ones(7, np.uint8)}
    size = codec.body_size({name: (arr.shape, arr.dtype.str) for name, arr in arrays.items()})
    payload = bytes(pack("k", 1, {}, arrays, compress_level=1))
    assert json.loads(split(payload).layout)["body"] == size
    assert unpack(payload, "k", 1, max_body=size)[1]["b"].sum() == 7
    with pytest.raises(DecodeError, match=f"body of {size} bytes exceeds the {size - 1} bytes"):
        unpack(payload, "k", 1, max_body=size - 1)


def test_bytes_after_the_compressed_stream_are_rejected() -> None:
    """Appended bytes mean the payload is not what the producer wrote."""
    flags, body, layout, fields = split(sample_map().to_bytes())
    with pytest.raises(DecodeError):
        MapSnapshot.from_bytes(assemble(flags, body + b"trailing", layout, fields))


# ---------------------------------------------------------------------------------------------
# Producer-side validation
# ---------------------------------------------------------------------------------------------

_GOOD_FRAME: dict[str, Any] = dict(seq=0, stamp=0.0, intrinsics=Intrinsics(fx=1, fy=1, cx=0, cy=0),
                                   rgb=np.zeros((4, 5, 3), np.uint8), depth=np.zeros((4, 5), np.float32))


@pytest.mark.parametrize("change", [
    {"rgb": np.zeros((4, 5, 3), np.float32)},
    {"rgb": np.zeros((4, 5), np.uint8)},
    {"rgb": np.zeros((4, 5, 4), np.uint8)},
    {"rgb": np.zeros((5, 4, 3), np.uint8)},
    {"rgb": [[[0, 0, 0]]]},
    {"depth": np.zeros((4, 5), np.float64)},
    {"depth": np.zeros((4, 5), ">f4")},
    {"depth": np.zeros((4, 5), np.int16)},
    {"depth": np.zeros((4, 5, 1), np.float32)},
    {"instance_ids": np.zeros((4, 5), np.int64)},
    {"instance_ids": np.zeros((5, 4), np.int32)},
    {"camera_pose": (1.0,) * 15},
    {"seq": -1},
    {"depth_scale": 0.0},
    {"extra": 1},
], ids=lambda c: next(iter(c)))
def test_bad_frame_fails_at_the_producer(change: dict[str, Any]) -> None:
    """A producer bug is caught where it happens, not by every subscriber."""
    RgbdFrame(**_GOOD_FRAME)  # the baseline is valid
    with pytest.raises(ValidationError):
        RgbdFrame(**{**_GOOD_FRAME, **change})


def test_bad_intrinsics_fail_at_the_producer() -> None:
    for fx, fy in ((0.0, 1.0), (1.0, -1.0)):
        with pytest.raises(ValidationError):
            Intrinsics(fx=fx, fy=fy, cx=0, cy=0)


_GOOD_MAP: dict[str, Any] = dict(seq=-1, stamp=0.0, resolution=0.1, origin=(0.0, 0.0), layers=("a",),
                                 obstacle=np.zeros((3, 4), bool), explored=np.zeros((3, 4), bool),
                                 counts=np.zeros((1, 3, 4), np.uint16), values=np.zeros((1, 3, 4), np.float32),
                                 frontiers=np.zeros((0, 2)))


@pytest.mark.parametrize("change", [
    {"obstacle": np.zeros((3, 4), np.uint8)},
    {"explored": np.zeros((4, 3), bool)},
    {"counts": np.zeros((1, 3, 4), np.int32)},
    {"counts": np.zeros((1, 3, 5), np.uint16)},
    {"counts": np.zeros((2, 3, 4), np.uint16)},
    {"searched": np.zeros((1, 3, 5), bool)},
    {"values": np.zeros((2, 3, 4), np.float32)},
    {"values": np.zeros((1, 3, 4), np.float64)},
    {"frontiers": np.zeros((2, 3))},
    {"frontiers": np.zeros(2)},
    {"frontiers": np.zeros((2, 2), np.float32)},
    {"seq": -2},
    {"resolution": 0.0},
], ids=lambda c: next(iter(c)))
def test_bad_map_fails_at_the_producer(change: dict[str, Any]) -> None:
    MapSnapshot(**_GOOD_MAP)
    with pytest.raises(ValidationError):
        MapSnapshot(**{**_GOOD_MAP, **change})


# ---------------------------------------------------------------------------------------------
# JSON messages
# ---------------------------------------------------------------------------------------------

counters = st.dictionaries(small_text, st.builds(CounterSet, received=st.integers(0, 10**9),
                                                 dropped=st.integers(0, 10**9)), max_size=3)
json_info = st.dictionaries(small_text, st.recursive(
    st.one_of(st.none(), st.booleans(), st.integers(-10**9, 10**9), finite, small_text),
    lambda inner: st.lists(inner, max_size=3) | st.dictionaries(small_text, inner, max_size=3),
    max_leaves=8), max_size=3)


@SETTINGS
@given(st.builds(ServiceStats, robot_id=small_text, service=small_text, instance=small_text,
                 pid=st.integers(0, 2**31), started=finite, counters=counters, info=json_info))
def test_service_stats_round_trip(stats: ServiceStats) -> None:
    assert ServiceStats.from_bytes(stats.to_bytes()) == stats
    out = bytearray(b"old contents that are longer than nothing")
    assert ServiceStats.from_bytes(stats.to_bytes(out=out)) == stats


def _stats_json(**changes: Any) -> bytes:
    data = json.loads(service_stats().to_bytes())
    data.update(changes)
    return json.dumps(data).encode()


def test_service_stats_wrong_version_is_rejected() -> None:
    with pytest.raises(DecodeError, match="v"):
        ServiceStats.from_bytes(_stats_json(v=2))
    with pytest.raises(ValidationError):
        service_stats(v=2)


def test_service_stats_extra_field_is_rejected() -> None:
    """Unknown fields are errors, so a schema change without a version bump is noticed."""
    with pytest.raises(DecodeError, match="surprise"):
        ServiceStats.from_bytes(_stats_json(surprise=1))


def test_service_stats_missing_or_mistyped_field_is_rejected() -> None:
    data = json.loads(service_stats().to_bytes())
    del data["pid"]
    with pytest.raises(DecodeError, match="pid"):
        ServiceStats.from_bytes(json.dumps(data).encode())
    with pytest.raises(DecodeError, match="counters"):
        ServiceStats.from_bytes(_stats_json(counters={"k": {"received": "many"}}))


@SETTINGS
@given(st.binary(max_size=200))
@example(b"")
@example(b"{")
@example(b"\xff\xfe")
@example(b"[]")
@example(b"null")
@example(bytes(sample_frame().to_bytes()))
def test_service_stats_not_json_is_rejected(garbage: bytes) -> None:
    with pytest.raises(DecodeError):
        ServiceStats.from_bytes(garbage)


def test_binary_payload_length_and_layout() -> None:
    """The layout the module docstring promises: header, body at BODY_OFFSET, aligned arrays."""
    frame = sample_frame(3, 3)
    payload = bytes(frame.to_bytes())
    magic, wire, flags, slack, stored, layout_len, fields_len = HEADER.unpack_from(payload, 0)
    assert (magic, wire, flags) == (MAGIC, WIRE_VERSION, 0)
    assert len(payload) == BODY_OFFSET + stored + layout_len + fields_len + slack
    parts = split(payload)
    layout = json.loads(parts.layout)
    assert (layout["kind"], layout["v"]) == ("rgbd", 1)
    assert [e[0] for e in layout["arrays"]] == ["rgb", "depth", "instance_ids"]
    assert all(e[3] % codec.ALIGN == 0 for e in layout["arrays"])
    assert json.loads(parts.fields)["seq"] == frame.seq
    rgb_off = layout["arrays"][0][3]
    assert payload[BODY_OFFSET + rgb_off:BODY_OFFSET + rgb_off + frame.rgb.nbytes] == frame.rgb.tobytes()
