"""Procedural homes from a seed: rooms, walls with doorways, furniture and small objects.

The house is a rectangle split recursively into rooms (binary space
partition); the biggest room becomes the living room, the smallest a
bathroom, and the rest cover the other types. Doorways join rooms along a
random spanning tree of the room-adjacency graph plus a few extra loops, so
every room is reachable. Furniture stands against walls, away from
doorways; which classes go in which room, and what stands on what, follows
the object prior imported from ProcTHOR (``world/prior.py``). Some
small objects are tucked on the floor beside furniture, where they are
visible only from some viewpoints.
"""

from __future__ import annotations

import colorsys
import hashlib
import math
from collections import defaultdict
from dataclasses import dataclass
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from ovamos.world.occupancy import box_corners
from ovamos.world.prior import ObjectPrior
from ovamos.world.scene import Room, Scene, SceneObject, Wall

SIDES = ("south", "north", "west", "east")
# Room types besides the living room (the biggest) and a bathroom (the smallest), taken in
# this order as homes get more rooms.
_MIDDLE_ROOMS = ("kitchen", "bedroom", "office", "dining_room", "bedroom", "bathroom", "office",
                 "bedroom", "bathroom", "bedroom", "office")


class GeneratorConfig(BaseModel):
    """Every knob of the generator. The defaults give 40-150 m2 homes of 3-7 rooms shaped like
    ProcTHOR-10K's, the houses the object prior comes from (``ovamos bench homes``): about 4 rooms of
    about 25 m2 (ProcTHOR-10K: 4.05 rooms, kitchen 26.5 m2, bedroom 28.1 m2 median), a piece of
    furniture per 4 m2 (ProcTHOR: at most 7 floor placements in a 25 m2 room, 3.6 m2 each) and 3-6
    small objects per room (ProcTHOR tries 3-17 on each large surface)."""

    model_config = ConfigDict(extra="forbid")
    min_area_m2: float = Field(default=40.0, gt=0)
    max_area_m2: float = Field(default=150.0, gt=0)
    min_room_side_m: float = Field(default=2.4, gt=1.0)
    m2_per_room: float = Field(default=26.0, gt=0)
    min_rooms: int = Field(default=3, ge=2, description="area / m2_per_room is clipped to this range")
    max_rooms: int = Field(default=7, ge=2, le=2 + len(_MIDDLE_ROOMS))
    door_width_m: float = Field(default=0.9, gt=0.5)
    door_clearance_m: float = Field(default=1.0, ge=0, description="kept free around doorways")
    extra_door_probability: float = Field(default=0.3, ge=0, le=1)
    m2_per_furniture: float = Field(default=4.0, gt=0)
    small_objects_per_room: tuple[int, int] = (3, 6)
    tucked_fraction: float = Field(default=0.3, ge=0, le=1,
                                   description="share of small objects put on the floor beside furniture")
    placement_tries: int = Field(default=40, ge=1)

    @model_validator(mode="after")
    def _ranges(self) -> GeneratorConfig:
        if self.min_area_m2 > self.max_area_m2 or self.min_rooms > self.max_rooms:
            raise ValueError("min_area_m2 / min_rooms must not exceed max_area_m2 / max_rooms")
        return self


HomeTier = Literal["default", "large"]
HOME_TIERS: dict[str, GeneratorConfig] = {
    "default": GeneratorConfig(),
    # The upper range of HM3D's scenes: 150-300 m2 and 8-12 rooms.
    "large": GeneratorConfig(min_area_m2=150.0, max_area_m2=300.0, m2_per_room=22.0, min_rooms=8, max_rooms=12),
}
"""The benchmark's home sizes (``ovamos bench search --homes``)."""


def home_tier(name: str) -> GeneratorConfig:
    """The generator config of a tier; a clear error for an unknown name."""
    try:
        return HOME_TIERS[name]
    except KeyError:
        raise ValueError(f"unknown home tier {name!r} (known: {', '.join(HOME_TIERS)})") from None


@dataclass
class _Rect:
    x0: float
    y0: float
    x1: float
    y1: float

    @property
    def w(self) -> float:
        return self.x1 - self.x0

    @property
    def h(self) -> float:
        return self.y1 - self.y0


def class_color(cls: str) -> tuple[float, float, float, float]:
    """A stable, distinct-looking colour per class (so renders and maps are readable)."""
    h = int(hashlib.sha1(cls.encode()).hexdigest()[:6], 16) / 0xFFFFFF
    r, g, b = colorsys.hsv_to_rgb(h, 0.55, 0.85)
    return (round(r, 3), round(g, 3), round(b, 3), 1.0)


def _split_rooms(rng: np.random.Generator, w: float, d: float, n: int, min_side: float) -> list[_Rect]:
    rects = [_Rect(0.0, 0.0, w, d)]
    while len(rects) < n:
        splittable = [r for r in rects if max(r.w, r.h) >= 2 * min_side]
        if not splittable:
            break
        r = max(splittable, key=lambda q: q.w * q.h)
        rects.remove(r)
        vertical = r.w >= r.h
        span = r.w if vertical else r.h
        cut = round(float(rng.uniform(max(min_side, 0.35 * span), min(span - min_side, 0.65 * span))), 2)
        if vertical:
            rects += [_Rect(r.x0, r.y0, r.x0 + cut, r.y1), _Rect(r.x0 + cut, r.y0, r.x1, r.y1)]
        else:
            rects += [_Rect(r.x0, r.y0, r.x1, r.y0 + cut), _Rect(r.x0, r.y0 + cut, r.x1, r.y1)]
    return rects


def _room_types(rng: np.random.Generator, rects: list[_Rect]) -> list[str]:
    order = sorted(range(len(rects)), key=lambda i: -rects[i].w * rects[i].h)
    rest = list(_MIDDLE_ROOMS[:len(order) - 2])
    rng.shuffle(rest)
    types = ["living_room", *rest, "bathroom"]
    out = [""] * len(rects)
    for i, t in zip(order, types):
        out[i] = t
    return out


def _shared_edge(a: _Rect, b: _Rect) -> tuple[str, float, float, float] | None:
    """(axis, coordinate, lo, hi) of the wall two rooms share, if any."""
    eps = 1e-6
    for axis, a_hi, b_lo, lo, hi in (("x", a.x1, b.x0, max(a.y0, b.y0), min(a.y1, b.y1)),
                                     ("x", b.x1, a.x0, max(a.y0, b.y0), min(a.y1, b.y1)),
                                     ("y", a.y1, b.y0, max(a.x0, b.x0), min(a.x1, b.x1)),
                                     ("y", b.y1, a.y0, max(a.x0, b.x0), min(a.x1, b.x1))):
        if abs(a_hi - b_lo) < eps and hi - lo > eps:
            return axis, a_hi, lo, hi
    return None


def _doors(rng: np.random.Generator, rects: list[_Rect], cfg: GeneratorConfig
           ) -> list[tuple[str, float, float, float]]:
    """Doorways (axis, coordinate, lo, hi) along a random spanning tree plus some loops."""
    need = cfg.door_width_m + 0.4
    edges = []
    for i in range(len(rects)):
        for j in range(i + 1, len(rects)):
            shared = _shared_edge(rects[i], rects[j])
            if shared and shared[3] - shared[2] >= need:
                edges.append((i, j, shared))
    rng.shuffle(edges)
    parent = list(range(len(rects)))

    def root(i: int) -> int:
        while parent[i] != i:
            i = parent[i]
        return i

    doors = []
    for i, j, (axis, coord, lo, hi) in edges:
        joins = root(i) != root(j)
        if joins or rng.random() < cfg.extra_door_probability:
            parent[root(i)] = root(j)
            centre = rng.uniform(lo + 0.2 + cfg.door_width_m / 2, hi - 0.2 - cfg.door_width_m / 2)
            doors.append((axis, coord, centre - cfg.door_width_m / 2, centre + cfg.door_width_m / 2))
    return doors


def _walls(rects: list[_Rect], doors: list[tuple[str, float, float, float]]) -> list[Wall]:
    """Every room edge once (collinear pieces merged), with doorway gaps cut out."""
    lines: dict[tuple[str, float], list[tuple[float, float]]] = defaultdict(list)
    for r in rects:
        lines[("x", round(r.x0, 6))].append((r.y0, r.y1))
        lines[("x", round(r.x1, 6))].append((r.y0, r.y1))
        lines[("y", round(r.y0, 6))].append((r.x0, r.x1))
        lines[("y", round(r.y1, 6))].append((r.x0, r.x1))
    gaps: dict[tuple[str, float], list[tuple[float, float]]] = defaultdict(list)
    for axis, coord, lo, hi in doors:
        gaps[(axis, round(coord, 6))].append((lo, hi))
    walls = []
    for (axis, coord), spans in sorted(lines.items()):
        merged: list[list[float]] = []
        for lo, hi in sorted(spans):
            if merged and lo <= merged[-1][1] + 1e-6:
                merged[-1][1] = max(merged[-1][1], hi)
            else:
                merged.append([lo, hi])
        for lo, hi in merged:
            cursor = lo
            for g_lo, g_hi in sorted(gaps[(axis, coord)]):
                if g_lo > cursor:
                    walls.append(_wall(axis, coord, cursor, min(g_lo, hi)))
                cursor = max(cursor, g_hi)
            if hi - cursor > 1e-6:
                walls.append(_wall(axis, coord, cursor, hi))
    return walls


def _wall(axis: str, coord: float, lo: float, hi: float) -> Wall:
    return Wall(x0=coord, y0=lo, x1=coord, y1=hi) if axis == "x" else Wall(x0=lo, y0=coord, x1=hi, y1=coord)


class _Placer:
    """Puts boxes into one room without overlaps and away from doorways."""

    def __init__(self, rng: np.random.Generator, room: Room, keep_clear: list[tuple[float, float]],
                 cfg: GeneratorConfig) -> None:
        self.rng, self.room, self.cfg = rng, room, cfg
        self.keep_clear = keep_clear
        self.footprints: list[np.ndarray] = []

    def _fits(self, corners: np.ndarray) -> bool:
        r, margin = self.room, 0.05 + 0.001
        if (corners[:, 0].min() < r.x0 + margin or corners[:, 0].max() > r.x1 - margin or
                corners[:, 1].min() < r.y0 + margin or corners[:, 1].max() > r.y1 - margin):
            return False
        lo, hi = corners.min(axis=0), corners.max(axis=0)
        for cx, cy in self.keep_clear:
            if (lo[0] < cx + self.cfg.door_clearance_m and hi[0] > cx - self.cfg.door_clearance_m and
                    lo[1] < cy + self.cfg.door_clearance_m and hi[1] > cy - self.cfg.door_clearance_m):
                return False
        for other in self.footprints:
            o_lo, o_hi = other.min(axis=0) - 0.05, other.max(axis=0) + 0.05
            if (lo < o_hi).all() and (hi > o_lo).all():
                return False
        return True

    def against_wall(self, sx: float, sy: float) -> tuple[float, float, float] | None:
        """(x, y, yaw) for a box with its back (the sy side) against a random wall of the room."""
        r, gap = self.room, 0.06
        for _ in range(self.cfg.placement_tries):
            side = SIDES[int(self.rng.integers(4))]
            yaw = {"south": 0.0, "north": math.pi, "west": -math.pi / 2, "east": math.pi / 2}[side]
            along = self.rng.uniform(0, 1)
            if side in ("south", "north"):
                x = r.x0 + gap + sx / 2 + along * max(0.0, r.x1 - r.x0 - 2 * gap - sx)
                y = r.y0 + gap + sy / 2 if side == "south" else r.y1 - gap - sy / 2
            else:
                y = r.y0 + gap + sx / 2 + along * max(0.0, r.y1 - r.y0 - 2 * gap - sx)
                x = r.x0 + gap + sy / 2 if side == "west" else r.x1 - gap - sy / 2
            corners = box_corners(x, y, sx, sy, yaw)
            if self._fits(corners):
                self.footprints.append(corners)
                return x, y, yaw
        return None

    def beside(self, host: SceneObject, sx: float, sy: float) -> tuple[float, float] | None:
        """A floor spot for a small box touching the side of ``host``, in the lee of it."""
        c, s = math.cos(host.yaw), math.sin(host.yaw)
        for sign in self.rng.permutation([-1.0, 1.0]):
            offset = host.sx / 2 + sx / 2 + 0.07  # beyond the 0.05 m spacing _fits keeps
            back = (host.sy - sy) / 2  # flush with the host's back, i.e. against the wall
            x = host.x + sign * offset * c + back * s
            y = host.y + sign * offset * s - back * c
            corners = box_corners(x, y, sx, sy, host.yaw)
            if self._fits(corners):
                self.footprints.append(corners)
                return x, y
        return None


def generate_scene(seed: int, prior: ObjectPrior | None = None,
                   config: GeneratorConfig | None = None) -> Scene:
    """The home for ``seed``: same seed, prior and config => the same scene."""
    prior = prior or ObjectPrior.load()
    cfg = config or GeneratorConfig()
    rng = np.random.default_rng(seed)
    area = rng.uniform(cfg.min_area_m2, cfg.max_area_m2)
    aspect = rng.uniform(0.6, 1.0)
    width, depth = round(math.sqrt(area / aspect), 2), round(math.sqrt(area * aspect), 2)
    n_rooms = int(np.clip(round(area / cfg.m2_per_room), cfg.min_rooms, cfg.max_rooms))
    rects = _split_rooms(rng, width, depth, n_rooms, cfg.min_room_side_m)
    types = _room_types(rng, rects)
    rooms = [Room(id=i, type=t, x0=r.x0, y0=r.y0, x1=r.x1, y1=r.y1)
             for i, (r, t) in enumerate(zip(rects, types))]
    doors = _doors(rng, rects, cfg)
    door_centres = [((lo + hi) / 2, c) if axis == "y" else (c, (lo + hi) / 2)
                    for axis, c, lo, hi in doors]
    objects: list[SceneObject] = []
    for room in rooms:
        objects += _furnish(rng, room, door_centres, prior, cfg, first_id=len(objects) + 1)
    return Scene(seed=seed, width=width, depth=depth, rooms=tuple(rooms),
                 walls=tuple(_walls(rects, doors)), objects=tuple(objects))


def _pick(rng: np.random.Generator, options: list[tuple[str, float]], k: int,
          prior: ObjectPrior) -> list[str]:
    """``k`` classes drawn by weight; a class repeats only if the prior allows several per room."""
    chosen: list[str] = []
    pool = [(c, w) for c, w in options if w > 0]
    while pool and len(chosen) < k:
        weights = np.array([w for _, w in pool])
        i = int(rng.choice(len(pool), p=weights / weights.sum()))
        cls = pool[i][0]
        chosen.append(cls)
        if not prior[cls].multiple:
            pool.pop(i)
    return chosen


def _furnish(rng: np.random.Generator, room: Room, doors: list[tuple[float, float]],
             prior: ObjectPrior, cfg: GeneratorConfig, first_id: int) -> list[SceneObject]:
    placer = _Placer(rng, room, doors, cfg)
    objects: list[SceneObject] = []

    def add(cls: str, x: float, y: float, z: float, size: tuple[float, float, float], yaw: float,
            on: int | None) -> SceneObject:
        obj = SceneObject(id=first_id + len(objects), cls=cls, x=round(x, 4), y=round(y, 4),
                          z=round(z, 4), sx=size[0], sy=size[1], sz=size[2], yaw=round(yaw, 6),
                          room=room.id, rgba=class_color(cls), on=on)
        objects.append(obj)
        return obj

    n_furniture = max(2, round(room.area / cfg.m2_per_furniture))
    for cls in _pick(rng, prior.furniture(room.type), n_furniture, prior):
        size = _jitter(rng, prior[cls].size)
        spot = placer.against_wall(size[0], size[1])
        if spot is not None:
            add(cls, spot[0], spot[1], 0.0, size, spot[2], None)

    lo, hi = cfg.small_objects_per_room
    for cls in _pick(rng, prior.small_objects(room.type), int(rng.integers(lo, hi + 1)), prior):
        size = _jitter(rng, prior[cls].size)
        hosts = [o for o in objects if o.on is None]
        if hosts and rng.random() < cfg.tucked_fraction:
            host = hosts[int(rng.integers(len(hosts)))]
            spot = placer.beside(host, size[0], size[1])
            if spot is not None:
                add(cls, spot[0], spot[1], 0.0, size, host.yaw, None)
                continue
        receptacles = [o for o in hosts if o.cls in prior[cls].receptacles
                       and o.sx > size[0] and o.sy > size[1]]
        if receptacles:
            host = receptacles[int(rng.integers(len(receptacles)))]
            u = rng.uniform(-1, 1) * (host.sx - size[0]) / 2
            v = rng.uniform(-1, 1) * (host.sy - size[1]) / 2
            c, s = math.cos(host.yaw), math.sin(host.yaw)
            add(cls, host.x + c * u - s * v, host.y + s * u + c * v, host.z + host.sz, size,
                host.yaw, host.id)
    return objects


def _jitter(rng: np.random.Generator, size: tuple[float, float, float]) -> tuple[float, float, float]:
    """Instances of a class differ a little in size (+-10 %), as real ones do."""
    return tuple(round(float(s * rng.uniform(0.9, 1.1)), 3) for s in size)  # type: ignore[return-value]
