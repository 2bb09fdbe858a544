"""The simulated world's data model: rooms, walls with doorways, objects; saved as JSON.

A scene is plain data so users can author their own (``Scene.load``) and every
consumer (renderer, occupancy, evaluator, map drawing) reads the same thing.
Coordinates are metres in the REP-103 world frame (x forward, y left, z up);
the house occupies ``[0, width] x [0, depth]``.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Self

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

ROOM_TYPES = ("kitchen", "living_room", "bedroom", "bathroom", "office", "dining_room")
WALL_HEIGHT = 2.5
WALL_THICKNESS = 0.1


class SceneError(ValueError):
    """A scene file that cannot be read or is not a consistent scene."""


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class Room(_Model):
    """An axis-aligned rectangular room."""

    id: int = Field(ge=0)
    type: str
    x0: float
    y0: float
    x1: float
    y1: float

    @model_validator(mode="after")
    def _check(self) -> Self:
        if not (self.x1 > self.x0 and self.y1 > self.y0):
            raise ValueError(f"room {self.id} has no area")
        return self

    @property
    def area(self) -> float:
        return (self.x1 - self.x0) * (self.y1 - self.y0)


class Wall(_Model):
    """A straight wall segment along its centre line, ``WALL_THICKNESS`` thick."""

    x0: float
    y0: float
    x1: float
    y1: float

    @property
    def length(self) -> float:
        return math.hypot(self.x1 - self.x0, self.y1 - self.y0)


class SceneObject(_Model):
    """An object modelled as an oriented box: centre (x, y), base height z, full sizes."""

    id: int = Field(ge=1, description="instance id; 0 means 'no object' in id images")
    cls: str
    x: float
    y: float
    z: float = Field(ge=0, description="height of the box bottom above the floor")
    sx: float = Field(gt=0)
    sy: float = Field(gt=0)
    sz: float = Field(gt=0)
    yaw: float = 0.0
    room: int = Field(ge=0)
    rgba: tuple[float, float, float, float]
    on: int | None = Field(default=None, description="id of the object it stands on")


class Scene(_Model):
    seed: int | None = None
    width: float = Field(gt=0)
    depth: float = Field(gt=0)
    rooms: tuple[Room, ...]
    walls: tuple[Wall, ...]
    objects: tuple[SceneObject, ...]

    @model_validator(mode="after")
    def _check(self) -> Self:
        ids = [o.id for o in self.objects]
        if len(set(ids)) != len(ids):
            raise ValueError("object ids must be unique")
        room_ids = {r.id for r in self.rooms}
        if len(room_ids) != len(self.rooms):
            raise ValueError("room ids must be unique")
        for o in self.objects:
            if o.room not in room_ids:
                raise ValueError(f"object {o.id} is in unknown room {o.room}")
            if o.on is not None and o.on not in ids:
                raise ValueError(f"object {o.id} stands on unknown object {o.on}")
        return self

    @property
    def area(self) -> float:
        return self.width * self.depth

    def classes(self) -> list[str]:
        return sorted({o.cls for o in self.objects})

    def instances(self, cls: str) -> list[SceneObject]:
        return [o for o in self.objects if o.cls == cls]

    def object(self, object_id: int) -> SceneObject:
        return next(o for o in self.objects if o.id == object_id)

    def save(self, path: str | Path) -> None:
        Path(path).write_text(self.model_dump_json(indent=1))

    @classmethod
    def load(cls, path: str | Path) -> Scene:
        try:
            return cls.model_validate_json(Path(path).read_text())
        except (OSError, ValidationError) as exc:
            raise SceneError(f"cannot load scene {path}: {exc}") from None

    def to_json(self) -> str:
        return json.dumps(self.model_dump(), sort_keys=True)
