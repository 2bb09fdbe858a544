"""The object prior: the committed data file, the loader, and the importer that made it."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from ovamos.world.prior import DEFAULT_PATH, ObjectPrior, PriorError
from ovamos.world.scene import ROOM_TYPES

ROOT = Path(__file__).resolve().parents[1]
PROCTHOR_DB = Path("/tmp/pt/whl/procthor/databases")
LARGE = ("fridge", "bed", "sofa", "toilet", "television")
SMALL = ("cup", "mug", "book", "laptop", "remote")


@pytest.fixture(scope="module")
def prior() -> ObjectPrior:
    return ObjectPrior.load()


def test_data_file_is_compact_and_attributed() -> None:
    data = json.loads(DEFAULT_PATH.read_text(encoding="utf-8"))
    assert DEFAULT_PATH.stat().st_size < 50_000
    assert "procthor" in data["source"].lower() and "Apache-2.0" in data["license"]
    assert {"office", "dining_room"} <= set(data["derivation"])


def test_classes(prior: ObjectPrior) -> None:
    assert len(prior.classes) >= 30
    assert set(LARGE + SMALL) <= set(prior.classes)
    assert all(name.islower() and " " not in name for name in prior.classes)
    assert not {"light_switch", "window", "doorway", "umbrella"} & set(prior.classes)


def test_weights_are_probabilities(prior: ObjectPrior) -> None:
    for name in prior.classes:
        c = prior[name]
        assert set(c.rooms) == set(ROOM_TYPES)
        assert all(0 <= w <= 1 for w in c.rooms.values()), name
        assert max(c.rooms.values()) > 0, name
        assert all(0 <= p <= 1 for p in c.receptacle_p.values()), name


@pytest.mark.parametrize("name, room", [
    ("fridge", "kitchen"), ("toilet", "bathroom"), ("bed", "bedroom"), ("sofa", "living_room"),
    ("desk", "office"), ("dining_table", "dining_room"), ("plate", "dining_room")])
def test_most_likely_room(prior: ObjectPrior, name: str, room: str) -> None:
    rooms = prior[name].rooms
    assert rooms[room] == max(rooms.values()) > 0


@pytest.mark.parametrize("name, room", [
    ("fridge", "kitchen"), ("toilet", "bathroom"), ("bed", "bedroom"), ("sofa", "living_room")])
def test_only_most_likely_room(prior: ObjectPrior, name: str, room: str) -> None:
    rooms = prior[name].rooms
    assert all(rooms[room] > w for r, w in rooms.items() if r != room)


def test_placement(prior: ObjectPrior) -> None:
    for name in LARGE:
        assert prior[name].on_floor and not prior[name].small, name
    for name in prior.classes:
        c = prior[name]
        if not c.on_floor:
            assert c.small and c.receptacles, name
            assert set(c.receptacles) <= set(prior.classes)
    assert prior["remote"].receptacles[0] in ("ottoman", "coffee_table")
    assert "toilet" in prior["toilet_paper"].receptacles


def test_rooms_lists(prior: ObjectPrior) -> None:
    kitchen = dict(prior.furniture("kitchen"))
    assert "fridge" in kitchen and "bed" not in kitchen and "cup" not in kitchen
    assert "cup" in dict(prior.small_objects("kitchen"))
    office = prior.furniture("office")
    assert {"desk", "chair"} <= dict(office).keys()
    assert [w for _, w in office] == sorted((w for _, w in office), reverse=True)
    for room in ROOM_TYPES:
        assert prior.furniture(room) and prior.small_objects(room), room
    with pytest.raises(ValueError, match="unknown room type"):
        prior.furniture("garage")


def test_sizes_are_plausible(prior: ObjectPrior) -> None:
    for name in prior.classes:
        sx, sy, sz = prior[name].size
        assert sx >= sy > 0 and sz > 0 and max(sx, sy, sz) < 3, name
    assert prior["fridge"].size[2] > 1.5 and prior["cup"].size[2] < 0.3
    assert prior["bed"].size[0] > 1.8 and prior["sofa"].size[0] > 1.5
    assert max(prior["cup"].size) < 0.2 and max(prior["remote"].size) < 0.3


def test_cooccurrence(prior: ObjectPrior) -> None:
    names = prior.classes
    for a in names[::7]:
        assert prior.cooccurrence(a, a) == 1.0
        for b in names[::5]:
            ab = prior.cooccurrence(a, b)
            assert 0 <= ab <= 1 and ab == prior.cooccurrence(b, a), (a, b)
    assert prior.cooccurrence("pillow", "bed") > prior.cooccurrence("pillow", "fridge")
    assert prior.cooccurrence("toilet_paper", "toilet") > prior.cooccurrence("toilet_paper", "sofa")
    assert prior.cooccurrence("remote", "sofa") > prior.cooccurrence("remote", "toilet") == 0


def test_relatedness(prior: ObjectPrior) -> None:
    assert prior.relatedness("cup", ["sofa", "cup"], []) == 1.0
    assert prior.relatedness("toilet", [], ["bathroom"]) > prior.relatedness("toilet", [], ["kitchen"])
    assert prior.relatedness("toilet", [], []) == 0.0
    with_sofa = prior.relatedness("remote", ["sofa"], [])
    assert with_sofa == prior.cooccurrence("remote", "sofa") > prior.relatedness("remote", ["fridge"], [])
    assert prior.relatedness("remote", ["sofa", "flying_saucer"], []) == with_sofa
    for name in prior.classes[::9]:
        assert 0 <= prior.relatedness(name, ["bed", "cup"], ROOM_TYPES) <= 1


def test_unknown_class_is_a_clear_key_error(prior: ObjectPrior) -> None:
    with pytest.raises(KeyError, match="unknown object class 'fridg'.*fridge"):
        prior["fridg"]
    with pytest.raises(KeyError, match="known classes include"):
        prior.relatedness("zzz", [], [])


def test_bad_files_are_clear_errors(tmp_path: Path) -> None:
    with pytest.raises(PriorError, match="not found"):
        ObjectPrior.load(tmp_path / "missing.json")
    (tmp_path / "bad.json").write_text("{not json")
    with pytest.raises(PriorError, match="cannot be read"):
        ObjectPrior.load(tmp_path / "bad.json")
    data = json.loads(DEFAULT_PATH.read_text(encoding="utf-8"))
    data["classes"]["cup"]["rooms"]["kitchen"] = 2
    (tmp_path / "range.json").write_text(json.dumps(data))
    with pytest.raises(PriorError, match="'cup'.*rooms.kitchen"):
        ObjectPrior.load(tmp_path / "range.json")
    del data["classes"]["countertop"]
    data["classes"]["cup"]["rooms"]["kitchen"] = 1
    (tmp_path / "dangling.json").write_text(json.dumps(data))
    with pytest.raises(PriorError, match="unknown classes.*countertop"):
        ObjectPrior.load(tmp_path / "dangling.json")


@pytest.mark.skipif(not PROCTHOR_DB.is_dir(), reason=f"ProcTHOR databases not at {PROCTHOR_DB} "
                    "(pip download --no-deps --pre procthor==0.0.1.dev2 -d /tmp/pt, unzip to /tmp/pt/whl)")
def test_importer_reproduces_committed_file(tmp_path: Path) -> None:
    out = tmp_path / "object_prior.json"
    subprocess.run([sys.executable, str(ROOT / "tools" / "import_procthor.py"), str(PROCTHOR_DB),
                    "--out", str(out)], check=True, timeout=120)
    assert out.read_bytes() == DEFAULT_PATH.read_bytes()
