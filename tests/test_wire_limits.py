"""What one hostile payload can make a receiver do (issue 33, findings 3 and 4).

A compressed body is refused before it is inflated when it declares more than its message type's
largest honest arrays, and is inflated with a bound, so a lying declared size cannot pass either;
numbers on the wire are strict (no ``true`` or ``"1"`` as a number) and finite, strings bounded.
Every test reproduces the attack first, then shows it refused as :class:`DecodeError`, the error
the bus counts as malformed while the service keeps serving.
"""

from __future__ import annotations

import json
import math
import resource
import subprocess
import sys
import threading
import zlib
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zenoh
from pydantic import ValidationError

from ovamos.services.camera.oakd import OakdConfig
from ovamos.services.camera.realsense import RealSenseConfig
from ovamos.services.diag.testpattern import pattern_frame
from ovamos.services.mapping.config import MappingConfig
from ovamos.services.perception.config import HfBackendConfig
from ovamos.shared import codec, keys, messages
from ovamos.shared.bus import Bus
from ovamos.shared.bus.zconfig import build_config
from ovamos.shared.codec import FLAG_ZLIB, DecodeError
from ovamos.shared.detections import Detection
from ovamos.shared.messages import (
    MAX_DETECTIONS,
    MAX_FRAME_SHAPE,
    MAX_MAP_SIDE,
    MAX_NAME_CHARS,
    MAX_TARGETS,
    MAX_TEXT_CHARS,
    BinaryMessage,
    CameraState,
    CounterSet,
    DecisionTrace,
    DriverMode,
    DriverState,
    EStop,
    FoundObject,
    Goal,
    Intrinsics,
    JsonMessage,
    MapSnapshot,
    Miss,
    ObjectInstance,
    Odometry,
    PerceptionResult,
    PlanCommand,
    RgbdFrame,
    ServiceStats,
    TargetMiss,
    TaskEvent,
    TaskSpec,
    TaskStatus,
    TraceOption,
    UnknownTargets,
)
from ovamos.shared.motion import Action
from ovamos.shared.robot import Primitives
from tests.polling import wait_for
from tests.test_codec import assemble, split  # the payload surgery of the codec tests

pytestmark = [pytest.mark.system, pytest.mark.serial]  # real-time devices, rates or deadlines: run alone, after the parallel tests (make test-all)

REPO = Path(__file__).resolve().parents[1]
BOMB_BYTES = 1 << 30
RSS_BOUND = 100 << 20  # what decoding the bomb may add to a receiver's peak memory, far below 1 GiB

# ---------------------------------------------------------------------------------------------
# Payloads built by hand, as a hostile peer would
# ---------------------------------------------------------------------------------------------


def compressed(body: bytes, layout: dict[str, Any], fields: dict[str, Any]) -> bytes:
    """A payload with a zlib ``body`` under a hand-written layout and fields."""
    return assemble(FLAG_ZLIB, body, json.dumps(layout).encode(), json.dumps(fields).encode())


def with_fields(msg: BinaryMessage, **changes: Any) -> bytes:
    """``msg``'s payload with some scalar fields changed (``json.dumps`` writes NaN as ``NaN``),
    its arrays as they were."""
    parts = split(msg.to_bytes())
    fields = {**json.loads(parts.fields), **changes}
    return assemble(parts.flags, parts.body, parts.layout, json.dumps(fields).encode())


def json_with(msg: JsonMessage, field: str, raw: str) -> bytes:
    """``msg`` as JSON with ``field`` set to the raw JSON text ``raw`` (a literal no encoder writes)."""
    data = json.loads(msg.to_bytes())
    data[field] = "\0"
    return json.dumps(data).replace('"\\u0000"', raw).encode()


RESULT_FIELDS = {"seq": 1, "stamp": 2.0, "odom_session": "", "targets": ["chair"], "scores": [0.5],
                 "labels": ["chair"], "detection_scores": [0.9]}
MASK_SHAPE = [1, 1 << 15, (1 << 15) - 1]  # one mask; boxes [1, 4] at 0, masks at 64: ~1 GiB


@pytest.fixture(scope="module")
def bomb_stream() -> bytes:
    """About 1 MB of zlib that inflates to 1 GiB of zeros (deflate's ratio is ~1000:1)."""
    deflater, chunk = zlib.compressobj(9), bytes(16 << 20)
    return b"".join([*(deflater.compress(chunk) for _ in range(BOMB_BYTES // len(chunk))), deflater.flush()])


@pytest.fixture(scope="module")
def bomb(bomb_stream: bytes) -> bytes:
    """A perception result that is valid in every part, with a body of 1 GiB of masks."""
    layout = {"kind": PerceptionResult.KIND, "v": PerceptionResult.VERSION, "body": BOMB_BYTES,
              "arrays": [["boxes", "<i4", [1, 4], 0], ["masks", "|b1", MASK_SHAPE, 64]]}
    return compressed(bomb_stream, layout, RESULT_FIELDS)


def honest_result(shape: tuple[int, int] = (48, 64), n: int = 1) -> PerceptionResult:
    mask = np.zeros(shape, bool)
    mask[10:20, 5:30] = True
    return PerceptionResult.build(3, 4.5, {"chair": 0.7, "sofa": 0.1},
                                  [Detection("chair", 0.9, (5, 10, 30, 20), mask)] * n, shape, "s1")


# ---------------------------------------------------------------------------------------------
# Finding 3: the decompression bomb
# ---------------------------------------------------------------------------------------------


def test_the_bomb_is_a_megabyte_that_inflates_to_a_gibibyte(bomb: bytes, bomb_stream: bytes) -> None:
    """The attack as filed: a ~1 MB payload whose stream really holds the 1 GiB it declares
    (inflated here in 64 MiB steps, so the test itself stays small)."""
    assert len(bomb) < 1_100_000
    inflater, total, data = zlib.decompressobj(), 0, bomb_stream
    while data:
        total += len(inflater.decompress(data, 64 << 20))
        data = inflater.unconsumed_tail
    assert inflater.eof and total == BOMB_BYTES


_DECODE_IN_CHILD = """
import json, resource, sys
from pathlib import Path
from ovamos.shared import codec
from ovamos.shared.messages import DecodeError, PerceptionResult

payload = Path(sys.argv[1]).read_bytes()
decode = {"codec-wide bound": lambda: codec.unpack(payload, PerceptionResult.KIND, PerceptionResult.VERSION),
          "PerceptionResult.from_bytes": lambda: PerceptionResult.from_bytes(payload)}[sys.argv[2]]
before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
inflated = 0
try:
    decoded = decode()
    arrays = decoded[1] if isinstance(decoded, tuple) else {}
    inflated = sum(a.nbytes for a in arrays.values())
    outcome = "decoded"
except DecodeError as exc:
    outcome = str(exc)
print(json.dumps({"peak_increase": (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before) * 1024,
                  "outcome": outcome, "inflated": inflated}))
"""


def decode_in_child(payload: bytes, how: str, tmp_path: Path) -> dict[str, Any]:
    """Decode ``payload`` in a fresh interpreter: its peak RSS is this decode's alone."""
    path = tmp_path / "payload"
    path.write_bytes(payload)
    run = subprocess.run([sys.executable, "-c", _DECODE_IN_CHILD, str(path), how], cwd=REPO,
                         capture_output=True, text=True, timeout=120, check=True)
    return json.loads(run.stdout)


def test_the_bomb_is_refused_before_inflating_with_memory_bounded(bomb: bytes, tmp_path: Path) -> None:
    # The attack: with only the codec's own 1 GiB ceiling (every receiver before the fix), the
    # 1 MB payload is inflated into a gibibyte of arrays (what RSS shows of it depends on the
    # kernel's handling of zero pages, so the arrays are what is checked)
    before = decode_in_child(bomb, "codec-wide bound", tmp_path)
    assert before["outcome"] == "decoded" and before["inflated"] >= BOMB_BYTES - (64 << 10), before
    # The fix: the perception result's own limit refuses it before inflating.
    after = decode_in_child(bomb, "PerceptionResult.from_bytes", tmp_path)
    assert f"exceeds the {PerceptionResult.MAX_BODY_BYTES} bytes" in after["outcome"]
    assert after["peak_increase"] < RSS_BOUND and after["inflated"] == 0, after


def test_the_bomb_through_the_bus_is_counted_malformed_and_the_service_keeps_serving(
        inproc_router: str, client: zenoh.Session, bomb: bytes) -> None:
    """What mapping does with it: drops and counts it, memory bounded, the next result fused."""
    key = keys.perception_result("r1")
    bus = Bus.open(build_config(connect=[inproc_router]), "r1", "mapping", "0")
    try:
        got: list[PerceptionResult] = []
        arrived = threading.Event()
        bus.subscribe(key, PerceptionResult, lambda r: (got.append(r), arrived.set()))
        honest = bytes(honest_result().to_bytes())
        wait_for(lambda: client.put(key, honest) or arrived.wait(0.1), what="first delivery")
        Path("/proc/self/clear_refs").write_text("5")  # peak RSS := RSS now
        rss = _status_kib("VmRSS")
        arrived.clear()
        client.put(key, bomb)
        client.put(key, honest)
        assert arrived.wait(10)
        counters = wait_for(lambda: (c := bus.counters.snapshot()[key]).malformed == 1 and c,
                            what="the bomb counted")
        assert counters.errors == 0 and got[-1].seq == 3
        assert (_status_kib("VmHWM") - rss) << 10 < RSS_BOUND
    finally:
        bus.close()


def _status_kib(field: str) -> int:
    """A memory figure of this process from /proc (kB)."""
    line = next(ln for ln in Path("/proc/self/status").read_text().splitlines() if ln.startswith(field))
    return int(line.split()[1])


@pytest.mark.parametrize("msg_type", [RgbdFrame, PerceptionResult, MapSnapshot], ids=lambda t: t.__name__)
def test_a_body_declared_past_the_type_limit_is_refused_before_inflating(msg_type: type[BinaryMessage]) -> None:
    """Refused on what the layout declares: the body is not even looked at (it is garbage here,
    which inflating would report as corrupt)."""
    declared = msg_type.MAX_BODY_BYTES + codec.ALIGN
    payload = compressed(b"not zlib", {"kind": msg_type.KIND, "v": msg_type.VERSION, "arrays": [],
                                       "body": declared}, {})
    with pytest.raises(DecodeError, match=f"body of {declared} bytes exceeds the {msg_type.MAX_BODY_BYTES}"):
        msg_type.from_bytes(payload)


def test_a_lying_declared_size_is_refused_by_the_bounded_inflater(bomb_stream: bytes) -> None:
    """An honest small layout over the 1 GiB stream: inflating stops one byte past the declared
    size."""
    parts = split(honest_result().to_bytes())
    declared = json.loads(parts.layout)["body"]
    lying = assemble(parts.flags, bomb_stream, parts.layout, parts.fields)
    peak_before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    with pytest.raises(DecodeError, match=f"inflates past the declared {declared} bytes"):
        PerceptionResult.from_bytes(lying)
    assert (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - peak_before) << 10 < RSS_BOUND


def test_the_largest_honest_messages_fit_their_limits() -> None:
    """A result with MAX_DETECTIONS full-size masks and a full-size frame with float depth and
    instance ids decode; the producers' defaults are within what the limits were derived from."""
    result = honest_result(MAX_FRAME_SHAPE, MAX_DETECTIONS)
    assert len(PerceptionResult.from_bytes(result.to_bytes()).labels) == MAX_DETECTIONS
    frame = pattern_frame(1, 2.0, width=MAX_FRAME_SHAPE[1], height=MAX_FRAME_SHAPE[0])
    arrays = {"rgb": frame.rgb, "depth": frame.depth, "instance_ids": np.ones(MAX_FRAME_SHAPE, np.int32)}
    big = frame.model_copy(update=arrays)
    assert len(split(big.to_bytes()).body) == RgbdFrame.MAX_BODY_BYTES  # the largest frame is the limit
    assert np.array_equal(RgbdFrame.from_bytes(big.to_bytes()).instance_ids, arrays["instance_ids"])
    assert MappingConfig().grid_cells <= MAX_MAP_SIDE
    assert HfBackendConfig().max_detections <= MAX_DETECTIONS
    for camera in (RealSenseConfig(), OakdConfig()):
        assert camera.height <= MAX_FRAME_SHAPE[0] and camera.width <= MAX_FRAME_SHAPE[1]


def test_a_checkpoint_of_the_default_grid_with_every_layer_fits_the_map_limit() -> None:
    cells = MappingConfig().grid_cells
    layered = {name: ((MAX_TARGETS, cells, cells), dtype) for name, dtype in (
        ("counts", "<u2"), ("values", "<f4"), ("confidence", "<f4"), ("searched", "|b1"))}
    checkpoint = codec.body_size({"obstacle": ((cells, cells), "|b1"), "explored": ((cells, cells), "|b1"),
                                  **layered, "frontiers": ((cells * cells // 4, 2), "<f8")})
    assert checkpoint < MapSnapshot.MAX_BODY_BYTES < codec.MAX_BODY_BYTES


# ---------------------------------------------------------------------------------------------
# Finding 4: strict, finite numbers and bounded strings
# ---------------------------------------------------------------------------------------------

ODOM = Odometry(seq=5, stamp=10.5, x=1.0, y=2.0, yaw=0.5, linear=0.2, angular=-0.1, odom_session="s1")
HUGE = "9" * 5000


def test_lax_validation_took_bools_and_digit_strings_as_numbers() -> None:
    """The attack as filed: pydantic's lax mode reads ``true`` as 1 and a digit string as a number
    (a 5000-digit one is inf to Python)."""
    lax = Odometry.__pydantic_validator__.validate_json(json_with(ODOM, "x", "true"), strict=False)
    assert lax.x == 1.0
    assert Odometry.__pydantic_validator__.validate_json(json_with(ODOM, "seq", '"7"'), strict=False).seq == 7
    assert float(HUGE) == math.inf


@pytest.mark.parametrize(("field", "raw"), [
    ("x", "true"), ("x", '"1.5"'), ("x", f'"{HUGE}"'), ("x", HUGE), ("x", "9" * 400), ("x", "NaN"),
    ("x", "Infinity"), ("yaw", "-Infinity"), ("y", "1e999"), ("stamp", "NaN"), ("stamp", "true"),
    ("stamp", f'"{HUGE}"'), ("linear", "NaN"), ("angular", "Infinity"), ("seq", "true"), ("seq", '"5"'),
    ("seq", "5.0"),
])
def test_odometry_with_a_bad_number_is_refused(field: str, raw: str) -> None:
    with pytest.raises(DecodeError, match=f"invalid Odometry: {field}|fields are not valid JSON|Invalid JSON"):
        Odometry.from_bytes(json_with(ODOM, field, raw))


@pytest.mark.parametrize(("field", "raw"), [
    ("linear", "NaN"), ("angular", "Infinity"), ("linear", "true"), ("duration_s", "Infinity"),
    ("stamp", "NaN"), ("action_id", "true"),
])
def test_a_velocity_command_with_a_bad_number_is_refused(field: str, raw: str) -> None:
    command = PlanCommand(action_id=3, stamp=1.0, linear=0.1, angular=0.2, duration_s=0.5)
    with pytest.raises(DecodeError, match=f"invalid PlanCommand: {field}"):
        PlanCommand.from_bytes(json_with(command, field, raw))


def test_ints_for_floats_and_every_honest_json_number_are_accepted() -> None:
    """JSON may write 1.0 as 1: an int is still a float, a float is not an int."""
    raw = b'{"v":1,"seq":5,"stamp":10,"x":1,"y":-2,"yaw":0,"linear":0,"angular":0}'
    odom = Odometry.from_bytes(raw)
    assert (odom.stamp, odom.x, odom.y) == (10.0, 1.0, -2.0) and isinstance(odom.x, float)
    frame = with_fields(pattern_frame(1, 2.0, width=8, height=8), stamp=5, camera_pose=[1, 0, 0, 0] * 4,
                        intrinsics={"fx": 4, "fy": 4, "cx": 3, "cy": 3})
    assert RgbdFrame.from_bytes(frame).intrinsics == Intrinsics(fx=4.0, fy=4.0, cx=3.0, cy=3.0)


def test_producers_still_build_messages_from_numpy_scalars() -> None:
    """Construction stays lenient (a producer's numpy scalars are numbers); what it sends is strict."""
    odom = Odometry(seq=np.int64(5), stamp=np.float64(1.5), x=np.float32(1.25), y=0, yaw=np.float32(0.5))
    assert Odometry.from_bytes(odom.to_bytes()) == odom


@pytest.mark.parametrize("changes", [
    {"stamp": math.nan}, {"stamp": math.inf}, {"stamp": True}, {"stamp": HUGE},
    {"camera_pose": [math.nan] + [0.0] * 15}, {"camera_pose": [math.inf] * 16},
    {"camera_pose": [True] + [0.0] * 15},
    {"intrinsics": {"fx": math.inf, "fy": 1.0, "cx": 0.0, "cy": 0.0}},
    {"intrinsics": {"fx": 1.0, "fy": 1.0, "cx": math.nan, "cy": 0.0}},
    {"intrinsics": {"fx": 1.0, "fy": True, "cx": 0.0, "cy": 0.0}},
    {"depth_scale": math.inf}, {"seq": True}, {"after_action": "3"},
], ids=lambda c: f"{next(iter(c))}={str(next(iter(c.values())))[:20]}")
def test_a_frame_with_a_bad_number_is_refused(changes: dict[str, Any]) -> None:
    frame = pattern_frame(1, 2.0, width=8, height=8)
    with pytest.raises(DecodeError, match=f"invalid RgbdFrame: {next(iter(changes))}"):
        RgbdFrame.from_bytes(with_fields(frame, **changes))


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_non_finite_float_depth_is_refused(bad: float) -> None:
    """Float depth marks no reading with 0 (the renderer, every camera): NaN and inf in a received
    frame have no honest source, so they are refused before anything fuses them."""
    payload = bytearray(pattern_frame(1, 2.0, width=8, height=8).to_bytes())
    RgbdFrame.from_bytes(payload)  # honest, zeros (no reading) included
    _, arrays = codec.unpack(payload, RgbdFrame.KIND, RgbdFrame.VERSION)
    arrays["depth"][3, 4] = bad  # writable: a view into the bytearray
    with pytest.raises(DecodeError, match="invalid RgbdFrame: depth holds NaN or inf"):
        RgbdFrame.from_bytes(payload)


def test_uint16_depth_is_not_checked_for_finiteness() -> None:
    frame = pattern_frame(1, 2.0, width=8, height=8)
    raw = frame.model_copy(update={"depth": np.full((8, 8), 65535, np.uint16), "depth_scale": 0.001})
    assert RgbdFrame.from_bytes(raw.to_bytes()).depth.max() == 65535


@pytest.mark.parametrize(("msg_type", "changes"), [
    (MapSnapshot, {"stamp": math.nan}),
    (MapSnapshot, {"origin": [math.inf, 0.0]}),
    (MapSnapshot, {"resolution": "0.05"}),
    (MapSnapshot, {"objects": [{"label": "chair", "x": math.nan, "y": 0.0, "score": 1.0, "hits": 1}]}),
    (PerceptionResult, {"scores": [math.nan, 0.1]}),
    (PerceptionResult, {"stamp": True}),
], ids=["map-stamp-nan", "map-origin-inf", "map-resolution-str", "map-object-nan", "result-score-nan",
        "result-stamp-bool"])
def test_maps_and_results_with_bad_numbers_are_refused(msg_type: type[BinaryMessage],
                                                       changes: dict[str, Any]) -> None:
    sample = SAMPLES[msg_type][0]
    with pytest.raises(DecodeError, match=f"invalid {msg_type.__name__}: {next(iter(changes))}"):
        msg_type.from_bytes(with_fields(sample, **changes))


def test_strings_are_bounded() -> None:
    event = SAMPLES[TaskEvent][0]
    longest = event.model_copy(update={"message": "m" * MAX_TEXT_CHARS})
    assert TaskEvent.from_bytes(longest.to_bytes()).message == longest.message
    with pytest.raises(DecodeError, match="invalid TaskEvent: message: String should have at most"):
        TaskEvent.from_bytes(json_with(event, "message", json.dumps("m" * (MAX_TEXT_CHARS + 1))))
    with pytest.raises(DecodeError, match="invalid TaskEvent: targets.0: String should have at most"):
        TaskEvent.from_bytes(json_with(event, "targets", json.dumps(["t" * (MAX_NAME_CHARS + 1)])))
    with pytest.raises(DecodeError, match="invalid PerceptionResult: labels.0: String should have at most"):
        PerceptionResult.from_bytes(with_fields(honest_result(), labels=["l" * (MAX_NAME_CHARS + 1)]))
    with pytest.raises(ValidationError):  # a producer's bug fails at the producer
        TaskSpec(task_id="t", targets=("x" * (MAX_NAME_CHARS + 1),), stamp=0.0)
    with pytest.raises(ValidationError):
        TaskSpec(task_id="t", targets=tuple(f"t{i}" for i in range(MAX_TARGETS + 1)), stamp=0.0)
    unknown = SAMPLES[UnknownTargets][0]
    with pytest.raises(DecodeError, match="invalid UnknownTargets: targets: Tuple should have at most"):
        UnknownTargets.from_bytes(json_with(unknown, "targets", json.dumps([f"t{i}" for i in range(MAX_TARGETS + 1)])))
    with pytest.raises(DecodeError, match="invalid UnknownTargets: reason: String should have at most"):
        UnknownTargets.from_bytes(json_with(unknown, "reason", json.dumps("r" * (MAX_TEXT_CHARS + 1))))


# ---------------------------------------------------------------------------------------------
# Every honest message still round-trips
# ---------------------------------------------------------------------------------------------


def _map() -> MapSnapshot:
    layers = ("chair", "sofa")
    rng = np.random.default_rng(1)
    shape = (len(layers), 6, 7)
    return MapSnapshot(seq=4, after_action=2, odom_session="s1", stamp=12.25, resolution=0.05, origin=(-1, 2.5),
                       layers=layers, objects=(ObjectInstance(label="chair", x=1, y=2.5, z=0.4, score=0.8,
                                                              hits=3, views=4, confirmed=True),),
                       obstacle=rng.random(shape[1:]) > 0.5, explored=rng.random(shape[1:]) > 0.3,
                       counts=rng.integers(0, 9, shape).astype(np.uint16),
                       values=rng.random(shape, np.float32), confidence=rng.random(shape, np.float32),
                       searched=rng.random(shape) > 0.5, frontiers=rng.random((3, 2)))


_GOAL = Goal(kind="object", x=1.5, y=-2, label="chair")
SAMPLES: dict[type, list[Any]] = {
    RgbdFrame: [pattern_frame(7, 3.5, width=16, height=12),
                pattern_frame(8, 3.6, width=16, height=12).model_copy(update={
                    "depth": np.arange(192, dtype=np.uint16).reshape(12, 16), "depth_scale": 0.001,
                    "instance_ids": np.arange(192, dtype=np.int32).reshape(12, 16)})],
    MapSnapshot: [_map(), _map().model_copy(update={"confidence": None, "searched": None})],
    PerceptionResult: [honest_result(), honest_result(n=0)],
    ServiceStats: [ServiceStats(robot_id="r1", service="mapping", instance="0", pid=42, started=1.5,
                                counters={"ovamos/r1/rgbd": CounterSet(received=3, malformed=1)},
                                info={"frames": 7, "nested": {"a": [1, 2.5, None]}})],
    CameraState: [CameraState(stamp=1.0, backend="sim", fault="no frame for 1 s", frames=3, last_seq=2)],
    Odometry: [ODOM],
    PlanCommand: [PlanCommand(action_id=1, stamp=1.0, task_id="t1", action=Action.TURN_LEFT),
                  PlanCommand(action_id=2, stamp=1.0, linear=0.2, angular=-0.3, duration_s=0.5)],
    DriverState: [DriverState(stamp=2.0, mode=DriverMode.READY, odom_session="s1", faults=("can",),
                              active_action=3, last_completed=2, last_outcome="done",
                              primitives=Primitives(), warnings=("planner unreachable",))],
    EStop: [EStop(engage=True, source="gateway", reason="operator", stamp=3.0)],
    TaskSpec: [TaskSpec(task_id="t1", targets=("chair", "sofa"), max_steps=100, stamp=4.0)],
    TaskEvent: [TaskEvent(task_id="t1", status=TaskStatus.FAILED, targets=("chair",), steps=5, distance_m=2,
                          stamp=5.0, message="done", x=1.0, y=2, goal=_GOAL, odom_session="s1",
                          found=(FoundObject(label="chair", x=1, y=2, step=4),),
                          misses=(TargetMiss(label="sofa", stage=Miss.NOT_CONFIRMED, detections=2),))],
    DecisionTrace: [DecisionTrace(task_id="t1", step=2, stamp=6.0, map_seq=-1, robot_x=0, robot_y=1.5,
                                  remaining=("chair",), goal=_GOAL, reason="best candidate",
                                  options=(TraceOption(kind="candidate", x=1, y=2, value=0.5, belief=0.4,
                                                       path_m=3.5, q=0.2, visits=10),
                                           TraceOption(kind="frontier", x=0, y=0, value=0.1)))],
    UnknownTargets: [UnknownTargets(targets=("candel",), reason="unknown target 'candel': did you mean 'candle'?")],
}


def _wire_types() -> set[type]:
    return {t for t in vars(messages).values() if isinstance(t, type) and t not in (JsonMessage, BinaryMessage)
            and issubclass(t, (JsonMessage, BinaryMessage))}


def test_every_wire_message_type_has_a_sample() -> None:
    assert set(SAMPLES) == _wire_types()


@pytest.mark.parametrize("msg", [m for ms in SAMPLES.values() for m in ms], ids=lambda m: type(m).__name__)
def test_honest_messages_round_trip(msg: JsonMessage | BinaryMessage) -> None:
    got = type(msg).from_bytes(msg.to_bytes())
    if isinstance(msg, JsonMessage):
        assert got == msg
        return
    for name, value in msg:
        if isinstance(value, np.ndarray):
            assert np.array_equal(getattr(got, name), value)
        else:
            assert getattr(got, name) == value, name
