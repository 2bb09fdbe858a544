"""Import the object-to-room / object-to-object prior from the ProcTHOR asset database.

One-off tool, not imported by the simulator: it turns the ProcTHOR databases
(Allen Institute for AI, Apache-2.0, https://github.com/allenai/procthor) into
``world/data/object_prior.json``, which ``world/prior.py`` loads.

Rerun (stdlib only; the procthor package is only used as a data carrier)::

    pip download --no-deps --pre procthor==0.0.1.dev2 -d /tmp/pt
    unzip -q /tmp/pt/procthor-0.0.1.dev2-py3-none-any.whl -d /tmp/pt/whl
    python tools/import_procthor.py /tmp/pt/whl/procthor/databases

The output is deterministic, so rerunning on the same data reproduces the file
byte for byte (tests/test_prior.py checks this when /tmp/pt/whl exists).

Rules (also written into the data file under "derivation"):

* Classes: the ProcTHOR object types in ``NAMES`` (renamed to snake_case);
  structure, wall-mounted fixtures, and vague decor types are left out. A
  class that is not on the floor and has no kept receptacle is dropped
  too, because a generator could not place it.
* kitchen / living_room / bedroom / bathroom: placement-annotations.json
  ``in<Room>s`` (0 never, 1 sometimes, 2 commonly) divided by 2, raised to
  ``roomWeights / 2`` of every asset group (asset_groups/*.json) that contains
  the class, because ProcTHOR also places classes through those groups
  (Television only ever appears through them).
* office and dining_room (ProcTHOR has neither) are derived from an anchor
  class, Desk and DiningTable. Weight = max of: 1 for the anchor; the share
  of the anchor's asset groups that contain the class (Chair: 1); the
  receptacles.json probability that the class stands on the anchor, divided
  by the largest such probability on that anchor; for classes ProcTHOR puts
  in all four of its room types, the smallest of those four weights. So an
  office's furniture is desk, chair, garbage_can, side_table and nothing
  else (no armchair or shelving unit): the data links nothing else to a Desk.
* on_floor, multiple: placement-annotations.json ``onFloor`` and
  ``multiplePerRoom``.
* receptacles: receptacles.json ``p``, the share of receptacle instances in
  the AI2-THOR scenes that carry the class, for kept receptacle classes.
* size: per asset, the bounding box's horizontal sides sorted (sx >= sy) and
  its height sz (AI2-THOR's y axis is up); the median of each over all
  assets of the class in asset-database.json.
* small: pickupable (``isPickupable``) or not on the floor: things that
  stand on furniture or are carried around, as opposed to furniture.
"""

from __future__ import annotations

import argparse
import json
import statistics
from pathlib import Path
from typing import Any

OUT = Path(__file__).resolve().parents[1] / "world" / "data" / "object_prior.json"
SOURCE = ("ProcTHOR databases (placement-annotations.json, receptacles.json, asset-database.json, "
          "asset_groups/) from the procthor 0.0.1.dev2 wheel, Allen Institute for AI, "
          "https://github.com/allenai/procthor")
PROCTHOR_ROOMS = {"kitchen": "inKitchens", "living_room": "inLivingRooms",
                  "bedroom": "inBedrooms", "bathroom": "inBathrooms"}
GROUP_ROOMS = {"kitchen": "kitchens", "living_room": "livingRooms",
               "bedroom": "bedrooms", "bathroom": "bathrooms"}
ANCHORS = {"office": "Desk", "dining_room": "DiningTable"}
Json = dict[str, Any]

# Left out: Blinds, Doorframe, Doorway, Window, LightSwitch, Painting, Faucet,
# ShowerCurtain, ShowerHead, HandTowelHolder, TowelHolder, ToiletPaperHanger
# (structure and wall-mounted fixtures); Cart, GarbageBag, RoomDecor,
# TableTopDecor (vague or not household items). build() also drops the named
# classes that cannot be placed: AluminumFoil, Footstool, ScrubBrush and
# WateringCan stand on no receptacle in receptacles.json, and Towel only on a
# TowelHolder.
NAMES = {
    "AlarmClock": "alarm_clock", "AluminumFoil": "aluminum_foil", "Apple": "apple",
    "ArmChair": "armchair", "BaseballBat": "baseball_bat", "BasketBall": "basketball",
    "Bed": "bed", "Book": "book", "Boots": "boots", "Bottle": "bottle", "Bowl": "bowl",
    "Box": "box", "Bread": "bread", "ButterKnife": "butter_knife", "CD": "cd",
    "Candle": "candle", "CellPhone": "cell_phone", "Chair": "chair", "Cloth": "cloth",
    "ClothesDryer": "clothes_dryer", "CoffeeMachine": "coffee_machine",
    "CoffeeTable": "coffee_table", "CounterTop": "countertop", "CreditCard": "credit_card",
    "Cup": "cup", "Desk": "desk", "DeskLamp": "desk_lamp", "Desktop": "desktop_computer",
    "DiningTable": "dining_table", "DishSponge": "dish_sponge", "DogBed": "dog_bed",
    "Dresser": "dresser", "Dumbbell": "dumbbell", "Egg": "egg", "FloorLamp": "floor_lamp",
    "Footstool": "footstool", "Fork": "fork", "Fridge": "fridge", "GarbageCan": "garbage_can",
    "HandTowel": "hand_towel", "HousePlant": "house_plant", "Kettle": "kettle",
    "KeyChain": "keychain", "Knife": "knife", "Ladle": "ladle", "Laptop": "laptop",
    "LaundryHamper": "laundry_hamper", "Lettuce": "lettuce", "Microwave": "microwave",
    "Mug": "mug", "Newspaper": "newspaper", "Ottoman": "ottoman", "Pan": "pan",
    "PaperTowelRoll": "paper_towel_roll", "Pen": "pen", "Pencil": "pencil",
    "PepperShaker": "pepper_shaker", "Pillow": "pillow", "Plate": "plate", "Plunger": "plunger",
    "Pot": "pot", "Potato": "potato", "RemoteControl": "remote", "Safe": "safe",
    "SaltShaker": "salt_shaker", "ScrubBrush": "scrub_brush", "ShelvingUnit": "shelving_unit",
    "SideTable": "side_table", "Sink": "sink", "SoapBar": "soap_bar",
    "SoapBottle": "soap_bottle", "Sofa": "sofa", "Spatula": "spatula", "Spoon": "spoon",
    "SprayBottle": "spray_bottle", "Statue": "statue", "Stool": "stool", "TVStand": "tv_stand",
    "TeddyBear": "teddy_bear", "Television": "television", "TennisRacket": "tennis_racket",
    "TissueBox": "tissue_box", "Toaster": "toaster", "Toilet": "toilet",
    "ToiletPaper": "toilet_paper", "Tomato": "tomato", "Towel": "towel",
    "VacuumCleaner": "vacuum_cleaner", "Vase": "vase", "WashingMachine": "washing_machine",
    "Watch": "watch", "WateringCan": "watering_can", "WineBottle": "wine_bottle",
}

DERIVATION = {
    "classes": "ProcTHOR object types minus structure, wall fixtures and vague decor; a class "
               "neither on the floor nor on a kept receptacle is dropped",
    "rooms": "kitchen/living_room/bedroom/bathroom: placement-annotations in<Room>s (0 never, "
             "1 sometimes, 2 commonly) / 2, raised to roomWeights / 2 of every asset group "
             "containing the class",
    "office": "anchor Desk; max of: 1 for Desk; share of Desk asset groups containing the class; "
              "p(class on Desk) / max p on Desk (receptacles.json); for classes in all four "
              "ProcTHOR room types, the smallest of those four weights",
    "dining_room": "same rule as office with anchor DiningTable",
    "on_floor": "placement-annotations onFloor",
    "multiple": "placement-annotations multiplePerRoom",
    "receptacles": "receptacles.json p: share of receptacle instances in AI2-THOR scenes "
                   "that carry the class",
    "size": "median over asset-database.json assets of [longer horizontal side, shorter "
            "horizontal side, height] in metres",
    "small": "isPickupable or not onFloor",
}


def load(path: Path) -> Any:
    with open(path, encoding="utf-8") as f:
        return json.load(f)


def base_rooms(annotations: Json, groups: list[Json]) -> dict[str, dict[str, float]]:
    """Weights of every ProcTHOR type in ProcTHOR's own four room types."""
    rooms = {t: {r: (annotations[key][t] or 0) / 2 for r, key in PROCTHOR_ROOMS.items()}
             for t in annotations["instances"]}
    for group in groups:
        weights = group["groupProperties"]["roomWeights"]
        for t in group_types(group):
            for r, key in GROUP_ROOMS.items():
                rooms[t][r] = max(rooms[t][r], weights[key] / 2)
    return rooms


def group_types(group: Json) -> set[str]:
    return {t for member in group["assetMetadata"].values() for t in member["assetIds"]}


def derived_room(anchor: str, rooms: dict[str, dict[str, float]], receptacles: Json,
                 groups: list[Json]) -> dict[str, float]:
    """Weights for a room type ProcTHOR lacks, from the class that defines it."""
    weights = {t: min(w.values()) for t, w in rooms.items()}
    weights[anchor] = 1.0
    anchored = [group_types(g) for g in groups if anchor in group_types(g)]
    for t in set().union(*anchored):
        weights[t] = max(weights[t], sum(t in g for g in anchored) / len(anchored))
    on_anchor = receptacles[anchor]
    top = max(v["p"] for v in on_anchor.values())
    for t, v in on_anchor.items():
        weights[t] = max(weights.get(t, 0.0), v["p"] / top)
    return weights


def size(assets: list[Json]) -> list[float]:
    boxes = [sorted((a["boundingBox"]["x"], a["boundingBox"]["z"]), reverse=True)
             + [a["boundingBox"]["y"]] for a in assets]
    return [round(statistics.median(b[i] for b in boxes), 3) for i in range(3)]


def build(db: Path) -> Json:
    annotations = load(db / "placement-annotations.json")
    receptacles = load(db / "receptacles.json")
    assets = load(db / "asset-database.json")
    groups = [load(p) for p in sorted((db / "asset_groups").glob("*.json"))]

    rooms = base_rooms(annotations, groups)
    derived = {r: derived_room(a, rooms, receptacles, groups) for r, a in ANCHORS.items()}
    on: dict[str, dict[str, float]] = {}
    for parent, children in receptacles.items():
        for child, v in children.items():
            if parent in NAMES:
                on.setdefault(child, {})[NAMES[parent]] = round(v["p"], 3)

    classes: dict[str, Json] = {}
    for t, name in NAMES.items():
        weights = rooms[t] | {r: d.get(t, 0.0) for r, d in derived.items()}
        on_floor = bool(annotations["onFloor"][t])
        if not (on_floor or on.get(t)):
            continue
        classes[name] = {
            "procthor": t,
            "rooms": {r: round(w, 3) for r, w in weights.items()},
            "on_floor": on_floor,
            "receptacles": on.get(t, {}),
            "size": size(assets[t]),
            "small": bool(annotations["isPickupable"][t]) or not on_floor,
            "multiple": bool(annotations["multiplePerRoom"][t]),
        }
    return {"source": SOURCE, "license": "Apache-2.0 (Copyright 2022 Allen Institute for AI)",
            "derivation": DERIVATION, "importer": "tools/import_procthor.py",
            "classes": classes}


def dump(data: Json) -> str:
    """Sorted keys, one class per line: small, deterministic and readable in diffs."""
    head = {k: v for k, v in data.items() if k != "classes"}
    rows = [f"  {json.dumps(k)}: {json.dumps(v, sort_keys=True, separators=(',', ':'))}"
            for k, v in sorted(data["classes"].items())]
    text = json.dumps(head | {"classes": "@"}, indent=1, sort_keys=True)
    return text.replace('"@"', "{\n" + ",\n".join(rows) + "\n }") + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("databases", type=Path, help="procthor/databases folder of the wheel")
    parser.add_argument("--out", type=Path, default=OUT, help=f"output file (default {OUT})")
    args = parser.parse_args()
    args.out.write_text(dump(build(args.databases)), encoding="utf-8")


if __name__ == "__main__":
    main()
