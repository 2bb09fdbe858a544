"""Message types exchanged between services, with their encoding.

Two families share one interface (``to_bytes()`` / ``from_bytes()``), so the
bus can publish and validate any of them the same way:

* :class:`JsonMessage` for small messages (odometry, task events, stats): a
  pydantic model sent as JSON, readable with any Zenoh tool.
* :class:`BinaryMessage` for messages with arrays (frames, maps): pydantic for
  the scalar fields, :mod:`ovamos.shared.codec` for the arrays.

Every message carries its schema version; decoding the wrong kind, an unknown
version or an inconsistent payload raises :class:`DecodeError` and nothing else.
"""

from __future__ import annotations

import secrets
import time
from dataclasses import dataclass
from enum import Enum
from typing import Annotated, Any, ClassVar, Literal, Self

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from ovamos.shared.codec import DecodeError, body_size, loan, pack, unpack
from ovamos.shared.detections import Detection
from ovamos.shared.motion import IDENTITY, Action, Pose, to_odom
from ovamos.shared.robot import Primitives

__all__ = ["DecodeError", "MAX_TEXT_CHARS", "MAX_NAME_CHARS", "MAX_TARGETS", "MAX_FRAME_SHAPE",
           "MAX_DETECTIONS", "MAX_MAP_SIDE", "WIRE_CONFIG", "Name", "OdomSession", "new_odom_session", "JsonMessage", "BinaryMessage", "ArraySpec",
           "Intrinsics", "RgbdFrame",
           "MapSnapshot", "ObjectInstance", "PerceptionResult", "CounterSet", "ServiceStats", "CameraState", "Odometry", "PlanCommand", "DriverMode",
           "Outcome", "DriverState", "EStop", "TaskSpec", "TaskStatus", "FINAL", "FoundObject",
           "Goal", "TaskEvent", "TraceOption", "DecisionTrace", "UnknownTargets"]


OdomSession = Annotated[str, Field(
    max_length=64, pattern=r"^[A-Za-z0-9_-]*$",
    description="the odometry session: new at every start of the base's odometry integration (its "
                "frame starts again at the initial pose); '' = not said (a producer older than sessions)")]
"""Which odometry frame a pose is in. Poses, frames and maps of two sessions must never be mixed: a
restarted driver's odometry starts again at its initial pose, wherever the robot stands. Letters,
digits, '-' and '_' only: the mapping service names files with it."""

MAX_TEXT_CHARS = 4096
"""The longest string any wire message carries (free text: a reason, a fault, an exception's
message; tighter bounds where a field says so): ample for what the services write, short enough
that a forged message cannot bloat every log line and event stream it reaches."""

MAX_NAME_CHARS = 256
"""The longest target, label or map layer name: four times the gateway's 64 characters a target
(labels are target or simulated class names), so no honest name comes near it."""

Name = Annotated[str, Field(max_length=MAX_NAME_CHARS)]
"""A target, label or map layer name."""

MAX_TARGETS = 16
"""Most targets a task searches for (the gateway's limit too): a perception result scores at most
these, so a map holds at most this many value layers."""

MAX_FRAME_SHAPE = (1080, 1920)
"""(height, width) of the largest frame a camera of the stack sends: 1080p. A RealSense D4xx
streams colour and depth at one size, 1280 x 720 at most (its depth's largest mode); the OAK-D and
the simulator default to 640 x 480; 1080p leaves room for depth aligned to a 1080p colour camera.
A perception result's masks have the frame's shape."""

MAX_DETECTIONS = 32
"""Most detections one perception result carries: the perception service keeps 20 by default
(its ``max_detections``), with room above that."""

MAX_PATH_POINTS = 512
"""Most waypoints one path command carries: a path across the largest map (75 m) at one waypoint
every 0.15 m, with room to spare."""

MAX_PATH_OBSTACLES = 512
"""Most obstacle points one path command names (the mapped obstacles near the path, which the
follower slows near): a wall each side of a 10 m path at 0.1 m spacing, with room to spare."""

MAX_MAP_SIDE = 1500
"""Cells a side of the largest map grid: the mapping default (and the deployed config) is 1000,
50 m at 5 cm (a large house, an office floor); half as much again leaves room for 75 m."""

WIRE_CONFIG = ConfigDict(extra="forbid", allow_inf_nan=False, str_max_length=MAX_TEXT_CHARS)
"""What every model that travels on the wire shares: unknown fields are errors, floats are finite
(NaN and inf never travel honestly: pydantic writes them as ``null``, and a NaN pose or stamp
poisons whatever fuses it) and strings are bounded. ``from_bytes`` also validates strictly: no
bool or string is taken as a number (an int still is, for a float: JSON may write 1.0 as 1)."""


def new_odom_session() -> str:
    """A new odometry session id: the UTC start time (for people) and 6 random hex digits (two
    starts in one second differ). Deliberately not seeded: it must differ at every start, also
    of a seeded simulation, and no result depends on its value."""
    return time.strftime("%Y%m%dT%H%M%SZ", time.gmtime()) + "-" + secrets.token_hex(3)


def _validation_error(cls: type, exc: ValidationError) -> DecodeError:
    first = exc.errors()[0]
    where = ".".join(str(p) for p in first["loc"]) or "message"
    return DecodeError(f"invalid {cls.__name__}: {where}: {first['msg']} "
                       f"({exc.error_count()} error(s))")


def _tuples(value: Any) -> Any:
    """Parsed JSON with its arrays as tuples, for strict validation: pydantic's strict mode takes a
    tuple field from a JSON array but, from Python input, only from a tuple."""
    if isinstance(value, list):
        return tuple(map(_tuples, value))
    if isinstance(value, dict):
        return {k: _tuples(v) for k, v in value.items()}
    return value


class JsonMessage(BaseModel):
    """A small message sent as JSON; unknown fields are rejected, not ignored.

    Producers build messages leniently (a numpy scalar is a number), but what is decoded from the
    wire is validated strictly: ``true`` or ``"1"`` is no number there."""

    model_config = ConfigDict(**WIRE_CONFIG, frozen=True)
    VERSION: ClassVar[int] = 1
    v: int = 1

    @model_validator(mode="after")
    def _check_version(self) -> Self:
        if self.v != self.VERSION:
            raise ValueError(f"version {self.v} is not supported (expected {self.VERSION})")
        return self

    def to_bytes(self, out: bytearray | None = None) -> bytes | bytearray:
        # pydantic-core's serializer straight to UTF-8 bytes: model_dump_json's Python layer and its
        # str round trip cost more than the serialising itself on a hot path (every message).
        data = self.__pydantic_serializer__.to_json(self)
        if out is None:
            return data
        out[:] = data
        return out

    @classmethod
    def from_bytes(cls, data: bytes | bytearray | memoryview) -> Self:
        try:
            return cls.__pydantic_validator__.validate_json(bytes(data), strict=True)
        except ValidationError as exc:
            raise _validation_error(cls, exc) from None


@dataclass(frozen=True)
class ArraySpec:
    """What a binary message accepts for one array field."""

    dtypes: tuple[str, ...]
    ndim: int
    finite: bool = False
    """Float values must be finite on the wire. Checked on receipt only: no honest producer sends
    NaN or inf where this is set, while the cores built in-process tolerate them (the mapping core
    leaves non-finite depth out), so only a payload from outside needs refusing."""

    def check(self, name: str, arr: np.ndarray) -> None:
        if arr.dtype.str not in self.dtypes or arr.ndim != self.ndim:
            raise ValueError(f"{name} must be a {self.ndim}-d array of {'/'.join(self.dtypes)}, "
                             f"got {arr.ndim}-d {arr.dtype}")

    def non_finite(self, arr: np.ndarray) -> bool:
        """Whether ``arr`` holds NaN or inf where this spec wants finite floats."""
        return self.finite and arr.dtype.kind == "f" and not np.isfinite(arr).all()


class BinaryMessage(BaseModel):
    """A message whose ``ARRAYS`` fields travel as raw bytes (see :mod:`ovamos.shared.codec`).

    Subclasses declare ``KIND``, ``ARRAYS``, ``MAX_BODY_BYTES`` and, for large but sparse content
    such as map grids, ``COMPRESS_LEVEL``. Array shapes and dtypes are checked
    when a message is built, so a producer bug fails at the producer.
    """

    model_config = ConfigDict(**WIRE_CONFIG, frozen=True, arbitrary_types_allowed=True)
    KIND: ClassVar[str]
    VERSION: ClassVar[int] = 1
    ARRAYS: ClassVar[dict[str, ArraySpec]]
    MAX_BODY_BYTES: ClassVar[int]
    """The most array bytes a message of this type may declare: its largest honest arrays. A
    payload declaring more is refused before it is inflated (a 1 MB zlib stream can inflate to
    1 GiB)."""
    COMPRESS_LEVEL: ClassVar[int | None] = None

    @model_validator(mode="after")
    def _check_arrays(self) -> Self:
        for name, spec in self.ARRAYS.items():
            arr = getattr(self, name)
            if arr is not None:
                spec.check(name, arr)
        return self

    def to_bytes(self, out: bytearray | None = None) -> bytearray:
        """The encoded message; ``out`` (a previous payload) is reused when given."""
        fields = self.__pydantic_serializer__.to_json(self, exclude=set(self.ARRAYS))
        arrays = {n: getattr(self, n) for n in self.ARRAYS if getattr(self, n) is not None}
        return pack(self.KIND, self.VERSION, fields, arrays, compress_level=self.COMPRESS_LEVEL,
                    out=out)

    @classmethod
    def from_bytes(cls, data: bytes | bytearray | memoryview) -> Self:
        fields, arrays = unpack(data, cls.KIND, cls.VERSION, cls.MAX_BODY_BYTES)
        unknown = set(arrays) - set(cls.ARRAYS)
        if unknown:
            raise DecodeError(f"invalid {cls.__name__}: unexpected arrays {sorted(unknown)}")
        if clash := set(fields) & set(cls.ARRAYS):
            raise DecodeError(f"invalid {cls.__name__}: fields named like arrays {sorted(clash)}")
        if bad := [name for name, arr in arrays.items() if cls.ARRAYS[name].non_finite(arr)]:
            raise DecodeError(f"invalid {cls.__name__}: {bad[0]} holds NaN or inf values")
        try:
            return cls.__pydantic_validator__.validate_python({**_tuples(fields), **arrays},
                                                              strict=True)
        except ValidationError as exc:
            raise _validation_error(cls, exc) from None


class Intrinsics(BaseModel):
    """Pinhole intrinsics in pixels."""

    model_config = ConfigDict(**WIRE_CONFIG, frozen=True)
    fx: float = Field(gt=0)
    fy: float = Field(gt=0)
    cx: float
    cy: float


_IDENTITY = tuple(float(x) for x in np.eye(4).ravel())


class RgbdFrame(BinaryMessage):
    """One camera frame with everything needed to project it into the world.

    ``camera_pose`` is world_T_camera, row-major 4x4; the camera frame is the
    optical one (x right, y down, z forward), the world frame REP-103 (x
    forward, y left, z up). ``depth`` is metres when float32, or units of
    ``depth_scale`` metres when uint16 (0.001 for millimetre sensors); 0 means
    no reading. ``instance_ids`` exists only on simulated frames.

    ``after_action`` makes lock-step causal: the id of the last command the base
    had completed when the frame was captured (the camera reads it from
    ``driver/state``). A planner waits for a map that fused a frame after its
    command, and never compares the clocks of two machines (``stamp`` is the
    capture time on the camera's host, for people and latency figures only).
    ``odom_session`` is the :data:`OdomSession` of the odometry ``camera_pose`` came from: the
    map fuses only frames of the driver's current session.
    """

    KIND: ClassVar[str] = "rgbd"
    ARRAYS: ClassVar[dict[str, ArraySpec]] = {
        "rgb": ArraySpec(("|u1",), 3),
        "depth": ArraySpec(("<f4", "<u2"), 2, finite=True),  # no reading is 0, never NaN
        "instance_ids": ArraySpec(("<i4",), 2),
    }
    MAX_BODY_BYTES: ClassVar[int] = body_size({
        "rgb": ((*MAX_FRAME_SHAPE, 3), "|u1"), "depth": (MAX_FRAME_SHAPE, "<f4"),
        "instance_ids": (MAX_FRAME_SHAPE, "<i4")})
    """A :data:`MAX_FRAME_SHAPE` frame with float depth and instance ids: 11 bytes a pixel, 22.8 MB."""
    seq: int = Field(ge=0)
    stamp: float
    after_action: int = Field(default=0, ge=0, description="last completed command at capture")
    odom_session: OdomSession = ""  # of the odometry the frame was posed with
    intrinsics: Intrinsics
    camera_pose: tuple[float, ...] = _IDENTITY
    depth_scale: float = Field(default=1.0, gt=0)
    rgb: np.ndarray
    depth: np.ndarray
    instance_ids: np.ndarray | None = None

    @model_validator(mode="after")
    def _check_shapes(self) -> Self:
        h, w = self.depth.shape
        if self.rgb.shape != (h, w, 3):
            raise ValueError(f"rgb shape {self.rgb.shape} does not match depth {(h, w)} x 3")
        if self.instance_ids is not None and self.instance_ids.shape != (h, w):
            raise ValueError(f"instance_ids shape {self.instance_ids.shape} != depth {(h, w)}")
        if len(self.camera_pose) != 16:
            raise ValueError("camera_pose must hold 16 numbers (a row-major 4x4 matrix)")
        return self

    @staticmethod
    def loan(height: int, width: int, *, depth_dtype: str = "<f4", instance_ids: bool = False
             ) -> dict[str, np.ndarray]:
        """Zeroed ``rgb``, ``depth`` (and ``instance_ids``) arrays inside a payload buffer.

        A camera or renderer that writes into these publishes without a copy.
        """
        specs = {"rgb": ((height, width, 3), "|u1"), "depth": ((height, width), depth_dtype)}
        if instance_ids:
            specs["instance_ids"] = ((height, width), "<i4")
        return loan(specs)

    @property
    def pose_matrix(self) -> np.ndarray:
        return np.asarray(self.camera_pose, dtype=np.float64).reshape(4, 4)


class ObjectInstance(BaseModel):
    """One object the map believes exists (world metres)."""

    model_config = ConfigDict(**WIRE_CONFIG, frozen=True)
    label: Name
    x: float
    y: float
    z: float = 0.0
    score: float
    hits: int = Field(ge=0)
    views: int = Field(default=0, ge=0, description="frames that saw its place (hits included)")
    confirmed: bool = False


class MapSnapshot(BinaryMessage):
    """The mapping service's state as the planner and gateway need it.

    Grids are H x W over a square-cell grid whose cell (0, 0) has its corner at
    ``origin`` (world metres); ``values``, ``counts`` (each layer's own update counts) and
    ``searched`` (cells seen in a frame scored for that layer's target) have one layer per name
    in ``layers`` (raw fused values: readers apply the decay with ``counts``).
    Compressed on the wire: most of a map is empty early in a search.

    Freshness is causal: ``seq`` is the newest fused frame's seq and
    ``after_action`` the newest ``RgbdFrame.after_action`` among the fused
    frames, so a planner knows whether the map has seen the world after its
    last command without reading any clock. ``stamp`` (the mapping host's
    clock) is for people only.

    A map belongs to one odometry session (``odom_session``, that of every frame it fused): a
    planner plans only on a map of its driver's current session.
    """

    KIND: ClassVar[str] = "map"
    COMPRESS_LEVEL: ClassVar[int | None] = 1
    ARRAYS: ClassVar[dict[str, ArraySpec]] = {
        "obstacle": ArraySpec(("|b1",), 2),
        "explored": ArraySpec(("|b1",), 2),
        "counts": ArraySpec(("<u2",), 3),
        "values": ArraySpec(("<f4",), 3),
        "confidence": ArraySpec(("<f4",), 3),
        "searched": ArraySpec(("|b1",), 3),
        "frontiers": ArraySpec(("<f8",), 2),
    }
    MAX_BODY_BYTES: ClassVar[int] = body_size({
        "obstacle": ((MAX_MAP_SIDE,) * 2, "|b1"), "explored": ((MAX_MAP_SIDE,) * 2, "|b1"),
        **{name: ((MAX_TARGETS, MAX_MAP_SIDE, MAX_MAP_SIDE), dtype) for name, dtype in (
            ("counts", "<u2"), ("values", "<f4"), ("confidence", "<f4"), ("searched", "|b1"))},
        "frontiers": ((MAX_MAP_SIDE ** 2 // 4, 2), "<f8")})
    """A checkpoint (confidences and searched areas included) of a :data:`MAX_MAP_SIDE` grid with
    :data:`MAX_TARGETS` layers: 2 + 11 x 16 bytes a cell, and at most one frontier a 2 x 2 block
    of cells (frontier segments are 8-connected components, so two never touch): 410 MB."""
    seq: int = Field(ge=-1, description="seq of the last fused frame, -1 before the first")
    after_action: int = Field(default=0, ge=0, description="newest after_action of a fused frame")
    odom_session: OdomSession = ""
    stamp: float
    map_T_odom: Pose = Field(default=IDENTITY, description="where the odometry frame lies in the map: "
                             "a pose in odometry is map_T_odom.compose(pose) here (localization's)")
    resolution: float = Field(gt=0)
    origin: tuple[float, float]
    layers: tuple[Name, ...] = Field(max_length=MAX_TARGETS)
    objects: tuple[ObjectInstance, ...] = ()
    obstacle: np.ndarray
    explored: np.ndarray
    counts: np.ndarray
    values: np.ndarray
    frontiers: np.ndarray
    confidence: np.ndarray | None = None  # per-layer fusion confidence: checkpoints carry it
    searched: np.ndarray | None = None    # per-layer searched area: checkpoints carry it

    def to_map(self, odom: Pose) -> Pose:
        """A pose of the odometry frame (the driver's) in this map's frame."""
        return self.map_T_odom.compose(odom)

    def to_odom(self, points: tuple[tuple[float, float], ...]) -> tuple[tuple[float, float], ...]:
        """Map-frame points (a path, obstacles) in the odometry frame, where the base follows them."""
        return to_odom(self.map_T_odom, points)

    def has_seen_after(self, action_id: int) -> bool:
        """Whether the map fused a frame captured after command ``action_id`` completed: the one
        freshness rule of lock-step, for the planner service and the in-process benchmark alike."""
        return self.after_action >= action_id


    @model_validator(mode="after")
    def _check_shapes(self) -> Self:
        shape = self.obstacle.shape
        if self.explored.shape != shape:
            raise ValueError(f"explored shape {self.explored.shape} != obstacle {shape}")
        for name in ("values", "counts", "confidence", "searched"):
            layers = getattr(self, name)
            if layers is not None and layers.shape != (len(self.layers), *shape):
                raise ValueError(f"{name} shape {layers.shape} != {(len(self.layers), *shape)}")
        if self.frontiers.shape[1:] != (2,):
            raise ValueError(f"frontiers must be N x 2 (x, y), got {self.frontiers.shape}")
        return self


class PerceptionResult(BinaryMessage):
    """Perception's output for one frame: a value score per target and detections with masks.

    ``targets`` is the target list the frame was scored for; consumers (the map)
    follow it, so adding or removing a target needs no other message. A frame may get a second
    result (re-scored when targets were added): the map then fuses the values of the targets
    it had not fused for that frame. ``odom_session`` is the frame's.
    """

    KIND: ClassVar[str] = "perception"
    COMPRESS_LEVEL: ClassVar[int | None] = 1  # masks are mostly zeros
    ARRAYS: ClassVar[dict[str, ArraySpec]] = {
        "boxes": ArraySpec(("<i4",), 2),
        "masks": ArraySpec(("|b1",), 3),
    }
    MAX_BODY_BYTES: ClassVar[int] = body_size({
        "boxes": ((MAX_DETECTIONS, 4), "<i4"), "masks": ((MAX_DETECTIONS, *MAX_FRAME_SHAPE), "|b1")})
    """:data:`MAX_DETECTIONS` masks of a :data:`MAX_FRAME_SHAPE` frame: 66 MB."""
    seq: int = Field(ge=0, description="seq of the frame this result is for")
    stamp: float
    odom_session: OdomSession = ""
    targets: tuple[Name, ...] = Field(max_length=MAX_TARGETS)
    scores: tuple[float, ...]
    labels: tuple[Name, ...] = ()
    detection_scores: tuple[float, ...] = ()
    boxes: np.ndarray
    masks: np.ndarray

    @model_validator(mode="after")
    def _check_lengths(self) -> Self:
        if len(self.scores) != len(self.targets):
            raise ValueError("one score per target")
        n = len(self.labels)
        if len(self.detection_scores) != n or self.boxes.shape != (n, 4) or self.masks.shape[0] != n:
            raise ValueError("labels, detection_scores, boxes and masks must describe the same detections")
        return self

    @classmethod
    def build(cls, seq: int, stamp: float, scores: dict[str, float], detections: list[Detection],
              image_shape: tuple[int, int], odom_session: str = "") -> PerceptionResult:
        masks = (np.stack([d.mask for d in detections]) if detections
                 else np.zeros((0, *image_shape), bool))
        return cls(seq=seq, stamp=stamp, odom_session=odom_session, targets=tuple(scores),
                   scores=tuple(scores.values()),
                   labels=tuple(d.label for d in detections),
                   detection_scores=tuple(d.score for d in detections),
                   boxes=np.array([d.box for d in detections], np.int32).reshape(-1, 4), masks=masks)

    def score_map(self) -> dict[str, float]:
        return dict(zip(self.targets, self.scores))

    def detections(self) -> list[Detection]:
        return [Detection(label, score, tuple(int(v) for v in box), mask)  # type: ignore[arg-type]
                for label, score, box, mask in zip(self.labels, self.detection_scores, self.boxes,
                                                   self.masks)]


class CounterSet(BaseModel):
    """Traffic on one key, as seen by one service instance."""

    model_config = WIRE_CONFIG
    received: int = 0
    dropped: int = 0
    malformed: int = 0
    errors: int = 0
    published: int = 0
    denied: int = 0  # a router's: messages on this key its access control refused


class ServiceStats(JsonMessage):
    """What a service instance answers on its ``stats`` key (shown by ``ovamos status``)."""

    robot_id: str
    service: str
    instance: str
    pid: int
    started: float
    counters: dict[str, CounterSet]
    info: dict[str, Any] = {}
    host: str = ""  # the instance's host name
    now: float | None = None  # its wall clock when it answered: another host's offset (ovamos doctor)


class CameraState(JsonMessage):
    """The robot camera's health, published at a few Hz and on every change.

    ``fault`` is empty while frames arrive; otherwise it says why not (no frame
    for 1 s, device unplugged, depth all zero), and the planner waits with it
    as its reason instead of deciding on a map that stopped growing.
    """

    stamp: float
    backend: str
    fault: str = ""
    frames: int = Field(default=0, ge=0, description="frames published since start")
    skipped: int = Field(default=0, ge=0, description="frames not published: no odometry around them")
    last_seq: int | None = None


class Odometry(JsonMessage):
    """The base's pose estimate (odometry frame, metres/radians) and body velocities.

    ``after_action``: the last command the base had completed when this pose was
    measured, so the planner books a command's distance with the pose it ended
    at (causal, like :attr:`RgbdFrame.after_action`: no clock comparison).
    ``odom_session``: which odometry frame the pose is in (:data:`OdomSession`).
    """

    seq: int = Field(ge=0)
    stamp: float
    after_action: int = Field(default=0, ge=0, description="last completed command when measured")
    odom_session: OdomSession = ""
    x: float
    y: float
    yaw: float
    linear: float = 0.0   # forward velocity, m/s
    angular: float = 0.0  # yaw rate, rad/s
    map_T_odom: Pose | None = Field(default=None, description="where the base's own localization (AMCL, "
                                    "slam_toolbox) places this odometry frame in its map; none: it has none")


class PlanCommand(JsonMessage):
    """One command for the base, identified so that a re-sent copy is executed once.

    ``action`` is a discrete primitive (the planner's); ``velocity`` a teleop
    command held for ``duration_s`` at most (the deadman still applies); ``path`` waypoints (x, y)
    in the odometry frame, followed closed-loop to the last one while the command keeps being
    re-sent (the deadman applies to it as to a velocity), slowing near ``obstacles`` (points in the
    same frame: the mapped obstacles the planner saw near the path; the robot has no map), no faster
    than ``speed_m_s`` where given (a careful path after a bump) nor than the base's limit. Action
    ids grow within a session; a driver executes an id only once, and a newer id replaces what runs.
    """

    action_id: int = Field(ge=1)
    stamp: float
    task_id: str | None = None
    action: Action | None = None
    linear: float = 0.0   # m/s, velocity commands only
    angular: float = 0.0  # rad/s, velocity commands only
    duration_s: float = Field(default=0.0, ge=0)
    path: tuple[tuple[float, float], ...] = Field(default=(), max_length=MAX_PATH_POINTS)
    obstacles: tuple[tuple[float, float], ...] = Field(default=(), max_length=MAX_PATH_OBSTACLES)
    speed_m_s: float | None = Field(default=None, gt=0, description="a path's top speed (None: the base's)")

    @model_validator(mode="after")
    def _one_kind(self) -> Self:
        kinds = (self.action is not None) + bool(self.linear or self.angular) + bool(self.path)
        if kinds > 1:
            raise ValueError("a command is one of a discrete action, a velocity or a path")
        if (self.obstacles or self.speed_m_s is not None) and not self.path:
            raise ValueError("obstacles and a top speed come with a path command only")
        return self

    @property
    def kind(self) -> str:
        """What the command is, for logs: the primitive's name, ``path (N points)`` or ``velocity``."""
        if self.action is not None:
            return self.action.value
        return f"path ({len(self.path)} points)" if self.path else "velocity"


class DriverMode(str, Enum):
    IDLE = "idle"          # not enabled (start-up, or after a fault was cleared)
    READY = "ready"        # closed loop, holding zero velocity, accepting commands
    MOVING = "moving"      # executing a command
    FAULT = "fault"        # a CAN/motor error; see ``faults``
    ESTOP = "estop"        # latched until an explicit clear
    OFF = "off"            # shutting down on purpose: its liveliness token goes next


Outcome = Literal["done", "blocked", "aborted", "rejected"]
"""How a command ended: executed, stopped by an obstacle (a bump), cut short (e-stop, fault,
timeout, superseded) or refused (e-stop latched, fault, a command kind the base cannot run)."""


class DriverState(JsonMessage):
    """What the base reports: its mode, why it is not moving, and how far the commands got.

    ``last_completed`` is the id of the newest command that ended (with
    ``last_outcome``). Lock-step freshness is causal: a planner that sees
    ``last_completed`` reach its command waits for an :class:`Odometry` and a
    :class:`MapSnapshot` whose ``after_action`` reaches it too; no stamp is
    compared across machines. ``odom_session`` is the session of the odometry it publishes: a
    planner plans only on a map of that session.
    """

    stamp: float
    mode: DriverMode
    odom_session: OdomSession = ""
    faults: tuple[str, ...] = ()
    estop_latched: bool = False
    active_action: int | None = None
    last_completed: int = Field(default=0, ge=0)
    last_outcome: Outcome | None = None
    backing_off: bool = Field(
        default=False, description="the active command was stopped by a collision and drives back before "
                                   "it ends blocked: its outcome is known, a planner waits for it")
    primitives: Primitives | None = Field(
        default=None, description="the primitive sizes this base executes (None: it does not say); "
                                  "a planner whose own differ refuses to plan")
    warnings: tuple[str, ...] = Field(
        default=(), description="what a person should know that does not stop the base by itself "
                                "(\"planner unreachable\": the planner's liveliness token is gone)")


class EStop(JsonMessage):
    """Engage (any service, the gateway, a person) or clear (explicitly) the emergency stop."""

    engage: bool
    source: str = Field(min_length=1, max_length=64)
    reason: str = Field(default="", max_length=256)
    stamp: float


class TaskStatus(str, Enum):
    """A task's life, the same word at the gateway and in the planner: queued (the gateway:
    behind another task; the planner: not started) -> searching -> done | failed (the step
    limit, nothing left to explore) | cancelled."""

    QUEUED = "queued"
    SEARCHING = "searching"
    DONE = "done"
    FAILED = "failed"
    CANCELLED = "cancelled"


FINAL = (TaskStatus.DONE, TaskStatus.FAILED, TaskStatus.CANCELLED)
"""The statuses a task never leaves."""


class TaskSpec(JsonMessage):
    """The task a robot should work on (re-published by its owner until it ends).

    ``cancelled`` tells the planner to stop; targets may change while searching. ``steps``,
    ``distance_m``, ``found``, ``last_action`` and the position (``x``, ``y`` in the frame of
    ``odom_session``) are the task's progress as its owner recorded it from the planner's events:
    a planner that restarts mid-task goes on from them (its step budget too), and books the
    commands its predecessor completed after ``last_action`` unreported, measured from there.
    """

    task_id: str = Field(min_length=1, max_length=64)
    targets: tuple[Name, ...] = Field(min_length=1, max_length=MAX_TARGETS)
    max_steps: int = Field(default=500, ge=1, le=100_000)
    cancelled: bool = False
    stamp: float
    steps: int = Field(default=0, ge=0)
    distance_m: float = Field(default=0.0, ge=0)
    found: tuple[FoundObject, ...] = ()
    last_action: int = Field(default=0, ge=0)
    x: float | None = None
    y: float | None = None
    odom_session: OdomSession = ""


class FoundObject(BaseModel):
    """A target declared found: where (world metres) and at which step of its task."""

    model_config = ConfigDict(**WIRE_CONFIG, frozen=True)
    label: Name
    x: float
    y: float
    step: int = Field(ge=0)


class Miss(str, Enum):
    """Why a target was not found: the first stage of its search it never reached. The benchmark
    (which holds the ground truth) tells every stage apart; the planner, from what its map holds,
    the last three: it cannot tell an object never in view from one in view and missed, nor a
    wrong STOP from a right one."""

    WRONG_STOP = "wrong stop"
    NEVER_SEEN = "never in view"
    NOT_DETECTED = "never detected"
    NOT_CONFIRMED = "never confirmed"
    NOT_REACHED = "not reached"


class TargetMiss(BaseModel):
    """A target a task did not find, and how far its search got (the planner's word on it)."""

    model_config = ConfigDict(**WIRE_CONFIG, frozen=True)
    label: Name
    stage: Miss
    detections: int = Field(default=0, ge=0, description="detections the map holds of the label")

    def __str__(self) -> str:
        if self.stage is Miss.NOT_DETECTED:
            return f"{self.label} never seen"
        if self.stage is Miss.NOT_CONFIRMED:
            return f"{self.label} detected {self.detections} time{'s' * (self.detections != 1)}, never confirmed"
        return f"{self.label} {self.stage.value}"


class Goal(BaseModel):
    """Where the planner is taking the robot (world metres): a confirmed object to stop beside, a
    candidate of the value map, or a frontier; shown on the operator's map."""

    model_config = ConfigDict(**WIRE_CONFIG, frozen=True)
    kind: Literal["object", "candidate", "frontier"]
    x: float
    y: float
    label: Name | None = None


class TaskEvent(JsonMessage):
    """The planner's view of a task after each step: progress, found objects, the end."""

    task_id: str
    status: TaskStatus
    targets: tuple[Name, ...]
    found: tuple[FoundObject, ...] = ()
    steps: int = Field(ge=0)
    distance_m: float = Field(ge=0)
    stamp: float
    message: str = ""
    x: float | None = None  # robot position when the event was made
    y: float | None = None
    goal: Goal | None = None  # the goal being driven to; None between goals and once over
    odom_session: OdomSession = ""  # the driver's odometry session: the frame x, y and goal are in
    misses: tuple[TargetMiss, ...] = ()  # once failed: each target not found and how far it got
    last_action: int = Field(default=0, ge=0)  # the newest command booked as a step (0: none)


class TraceOption(BaseModel):
    """One action a decision step weighed: a candidate of the value map or the best frontier.

    ``belief``: the candidate's share of the belief (None for the frontier); ``path_m``: the
    path length from the robot on the obstacle map (None where the policy computed none, inf
    when unreachable); ``q`` and ``visits``: POUCT's mean return and visit count at the root
    (None when the policy ran no POUCT).
    """

    model_config = ConfigDict(**WIRE_CONFIG, frozen=True)
    kind: Literal["candidate", "frontier"]
    x: float
    y: float
    value: float = Field(description="the decision value map at the point")
    belief: float | None = None
    path_m: float | None = None
    q: float | None = None
    visits: int | None = None


class DecisionTrace(JsonMessage):
    """Why the planner chose its goal: the options of one decision step and the choice.

    Published at every decision (not at every command), so a recording or the live view shows
    why the robot went where it went. ``goal`` None: nothing left to go to.
    """

    task_id: str
    step: int = Field(ge=0)
    stamp: float
    map_seq: int = Field(ge=-1, description="seq of the snapshot the decision read")
    robot_x: float
    robot_y: float
    remaining: tuple[Name, ...]
    options: tuple[TraceOption, ...] = ()
    goal: Goal | None = None
    reason: str


class UnknownTargets(JsonMessage):
    """Perception's word that it can never see some of a robot's targets, and why (a closed
    vocabulary, the sim backend's: ``did you mean 'candle'?``): the planner fails the task with
    ``reason`` rather than wait for a map layer that never comes. Sent with each task it is true of."""

    targets: tuple[Name, ...] = Field(min_length=1, max_length=MAX_TARGETS)
    reason: str = Field(max_length=MAX_TEXT_CHARS)
