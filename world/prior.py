"""Where objects are found in homes: an object-room and object-object prior from real data.

The procedural home generator needs to know which furniture goes in which room
and what stands on it; the simulated perception model needs to know how
strongly what it sees hints at a target. Both read ``data/object_prior.json``,
which ``tools/import_procthor.py`` derives from the ProcTHOR asset database
(Allen Institute for AI, Apache-2.0; see ``data/ATTRIBUTION.md``). Nothing here
depends on the procthor package.
"""

from __future__ import annotations

import difflib
import json
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ovamos.world.scene import ROOM_TYPES

DEFAULT_PATH = Path(__file__).parent / "data" / "object_prior.json"


class PriorError(ValueError):
    """The prior data file is missing or is not a consistent prior."""


@dataclass(frozen=True)
class ClassPrior:
    """What the data says about one object class.

    ``rooms`` maps every room type to a weight in [0, 1] (1: common, 0: never);
    ``receptacle_p`` is the probability that an instance of a receptacle class
    carries this class, and ``receptacles`` lists those classes, likeliest first;
    ``size`` is (sx, sy, sz) in metres with sx >= sy horizontal and sz up;
    ``small`` marks things that stand on furniture or are carried, not furniture;
    ``multiple`` says whether a room may hold more than one.
    """

    name: str
    rooms: dict[str, float]
    on_floor: bool
    receptacles: tuple[str, ...]
    receptacle_p: dict[str, float]
    size: tuple[float, float, float]
    small: bool
    multiple: bool


def _unit(value: Any, what: str) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not 0 <= value <= 1:
        raise ValueError(f"{what} must be a number in [0, 1], got {value!r}")
    return float(value)


def _flag(value: Any, what: str) -> bool:
    if not isinstance(value, bool):
        raise ValueError(f"{what} must be true or false, got {value!r}")
    return value


def _parse(name: str, entry: dict[str, Any]) -> ClassPrior:
    if set(entry["rooms"]) != set(ROOM_TYPES):
        raise ValueError(f"rooms must be exactly {', '.join(ROOM_TYPES)}")
    rooms = {r: _unit(entry["rooms"][r], f"rooms.{r}") for r in ROOM_TYPES}
    p = {r: _unit(v, f"receptacles.{r}") for r, v in entry["receptacles"].items()}
    sx, sy, sz = (float(s) for s in entry["size"])
    if min(sx, sy, sz) <= 0:
        raise ValueError(f"size must be positive, got {entry['size']!r}")
    return ClassPrior(name=name, rooms=rooms, on_floor=_flag(entry["on_floor"], "on_floor"),
                      receptacles=tuple(sorted(p, key=lambda r: (-p[r], r))), receptacle_p=p,
                      size=(sx, sy, sz), small=_flag(entry["small"], "small"),
                      multiple=_flag(entry["multiple"], "multiple"))


def _check_room(room_type: str) -> str:
    if room_type not in ROOM_TYPES:
        raise ValueError(f"unknown room type {room_type!r}; expected one of {', '.join(ROOM_TYPES)}")
    return room_type


class ObjectPrior:
    """The per-class priors plus the object-object and object-scene relations built on them."""

    def __init__(self, classes: dict[str, ClassPrior]) -> None:
        self._classes = classes

    @classmethod
    def load(cls, path: str | Path | None = None) -> ObjectPrior:
        """Read a prior file (default: the one shipped with the package), checking every entry."""
        path = Path(path) if path is not None else DEFAULT_PATH
        try:
            data = json.loads(path.read_text(encoding="utf-8"))
        except FileNotFoundError:
            raise PriorError(f"object prior {path} not found; "
                             "regenerate it with tools/import_procthor.py") from None
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
            raise PriorError(f"object prior {path} cannot be read: {e}") from None
        if not isinstance(data, dict) or not isinstance(data.get("classes"), dict):
            raise PriorError(f"object prior {path} has no 'classes' object")
        classes = {}
        for name, entry in data["classes"].items():
            try:
                classes[name] = _parse(name, entry)
            except (KeyError, TypeError, ValueError) as e:
                raise PriorError(f"object prior {path}: class {name!r}: {e!r}") from None
        for c in classes.values():
            if unknown := set(c.receptacles) - set(classes):
                raise PriorError(f"object prior {path}: class {c.name!r} stands on unknown "
                                 f"classes {sorted(unknown)}")
        return cls(classes)

    @property
    def classes(self) -> list[str]:
        return sorted(self._classes)

    def __contains__(self, name: object) -> bool:
        return name in self._classes

    def __getitem__(self, name: str) -> ClassPrior:
        try:
            return self._classes[name]
        except KeyError:
            hint = difflib.get_close_matches(name, self.classes, n=3) or self.classes[:5]
            raise KeyError(f"unknown object class {name!r}; known classes include "
                           f"{', '.join(hint)} ({len(self._classes)} in all)") from None

    def _by_weight(self, room_type: str, small: bool) -> list[tuple[str, float]]:
        room_type = _check_room(room_type)
        found = [(c.name, c.rooms[room_type]) for c in self._classes.values()
                 if c.small == small and c.rooms[room_type] > 0]
        return sorted(found, key=lambda cw: (-cw[1], cw[0]))

    def furniture(self, room_type: str) -> list[tuple[str, float]]:
        """Floor-standing furniture a room of this type may hold, likeliest first."""
        return self._by_weight(room_type, small=False)

    def small_objects(self, room_type: str) -> list[tuple[str, float]]:
        """Small objects (on receptacles, or loose on the floor) for this room type, likeliest first."""
        return self._by_weight(room_type, small=True)

    def cooccurrence(self, a: str, b: str) -> float:
        """How strongly two classes go together, in [0, 1], symmetric; 1 for a == b.

        The mean of two data-derived terms: the probability that one stands on
        an instance of the other (the larger of both directions), and the
        overlap of their room profiles, sum(min) / sum(max) over room types.
        """
        pa, pb = self[a], self[b]
        if a == b:
            return 1.0
        on = max(pa.receptacle_p.get(b, 0.0), pb.receptacle_p.get(a, 0.0))
        low = sum(min(pa.rooms[r], pb.rooms[r]) for r in ROOM_TYPES)
        high = sum(max(pa.rooms[r], pb.rooms[r]) for r in ROOM_TYPES)
        return (on + (low / high if high else 0.0)) / 2

    def relatedness(self, target: str, visible_classes: Iterable[str],
                    room_types: Iterable[str]) -> float:
        """How strongly what is visible suggests the target is near, in [0, 1].

        1 if the target itself is visible; otherwise the largest of the target's
        weight in each visible room type and its co-occurrence with each visible
        class; 0 with nothing visible. Visible classes the prior does not know
        (perception is open-vocabulary) carry no evidence and are skipped.
        """
        prior = self[target]
        visible = set(visible_classes)
        if target in visible:
            return 1.0
        rooms = [prior.rooms[_check_room(r)] for r in room_types]
        objects = [self.cooccurrence(target, v) for v in visible if v in self._classes]
        return max(rooms + objects, default=0.0)
