"""Mapping core: obstacles, explored area, frontiers, value layers, decay, checkpoints."""

from __future__ import annotations

import math

import numpy as np
import pytest

from services.mapping.checkpoint import CheckpointError, load_checkpoint, save_checkpoint
from services.mapping.config import MappingConfig
from services.mapping.layers import aggregate, decay, fov_confidence, fuse
from services.mapping.state import MapState
from services.sim.render import SceneRenderer
from services.sim.world import Room, Scene, Wall
from tests.sim_scenes import two_rooms

CONFIG = MappingConfig(grid_cells=200)  # 10 x 10 m around the origin
HFOV = math.radians(79)


def closed_room(door: bool) -> Scene:
    """A 4 x 4 m room around the origin (the map's grid is centred there), optional east door."""
    east = ([Wall(x0=2, y0=-2, x1=2, y1=-0.5), Wall(x0=2, y0=0.5, x1=2, y1=2)] if door
            else [Wall(x0=2, y0=-2, x1=2, y1=2)])
    return Scene(width=6.0, depth=4.0, rooms=(Room(id=0, type="office", x0=-2, y0=-2, x1=2, y1=2),),
                 walls=(Wall(x0=-2, y0=-2, x1=2, y1=-2), Wall(x0=-2, y0=2, x1=2, y1=2),
                        Wall(x0=-2, y0=-2, x1=-2, y1=2), *east), objects=())


def look_around(scene: Scene, state: MapState, x: float = 0.0, y: float = 0.0, turns: int = 12,
                scores: dict[str, float] | None = None) -> None:
    with SceneRenderer(scene, 320, 240) as renderer:
        for i in range(turns):
            state.integrate(renderer.render(x, y, 2 * math.pi * i / turns, seq=i), scores)


def test_fov_confidence_is_1_on_the_axis_and_0_at_the_edge() -> None:
    assert fov_confidence(np.array(0.0), HFOV) == pytest.approx(1.0)
    assert fov_confidence(np.array(HFOV / 2), HFOV) == pytest.approx(0.0, abs=1e-12)
    assert fov_confidence(np.array(HFOV / 4), HFOV) == pytest.approx(0.5)


def test_fusion_matches_hand_computed_values() -> None:
    v, c = fuse(np.array([0.0, 0.5, 0.2]), np.array([0.0, 0.5, 1.0]), 0.4, np.array([1.0, 0.5, 0.25]))
    assert v == pytest.approx([0.4, 0.45, 0.24])
    assert c == pytest.approx([1.0, 0.5, 0.85])


def test_decay_curve() -> None:
    out = decay(np.ones(3, np.float32), np.array([0, 6, 12], np.uint16), tau=6, kappa=2)
    assert out == pytest.approx([1 / (1 + math.exp(-3)), 0.5, 1 / (1 + math.exp(3))], rel=1e-6)


def test_aggregate_normalises_each_layer() -> None:
    total = aggregate([np.array([0.0, 0.2, 0.4]), np.array([1.0, 0.0, 0.0])])
    assert total == pytest.approx([1.0, 0.5, 1.0])
    assert aggregate([]) is None


def test_a_closed_room_gives_its_walls_and_no_frontier() -> None:
    state = MapState(CONFIG)
    look_around(closed_room(door=False), state)
    g = state.grid
    # every wall face is an obstacle; the floor inside is explored and free
    for x, y in [(1.96, 0.0), (-1.96, 0.0), (0.0, 1.96), (0.0, -1.96), (1.96, 1.5)]:
        r, c = g.to_cell(x, y)
        assert state.obstacle[r - 1:r + 2, c - 1:c + 2].any(), (x, y)
    for x, y in [(0.0, 0.0), (1.0, 1.0), (-1.5, -1.5), (1.7, -0.3)]:
        r, c = g.to_cell(x, y)
        assert state.explored[r, c] and not state.obstacle[r, c], (x, y)
    r, c = g.to_cell(3.0, 0.0)
    assert not state.explored[r, c]  # behind the wall
    assert state.frontiers().shape == (0, 2)


def test_a_doorway_is_where_the_frontier_is() -> None:
    state = MapState(CONFIG)
    look_around(closed_room(door=True), state)
    frontiers = state.frontiers()
    assert len(frontiers) >= 1
    assert (frontiers[:, 0] > 1.8).all()  # beyond the doorway in the east wall


def test_value_layers_fuse_only_what_was_seen_and_count_updates() -> None:
    state = MapState(CONFIG, targets=["fridge", "cup"])
    look_around(closed_room(door=False), state, turns=1, scores={"fridge": 0.6, "cup": 0.1, "bed": 0.9})
    g = state.grid
    ahead, behind = g.to_cell(1.0, 0.0), g.to_cell(-1.0, 0.0)
    assert state.values["fridge"][ahead] == pytest.approx(0.6)
    assert state.values["cup"][ahead] == pytest.approx(0.1)
    assert state.values["fridge"][behind] == 0.0 and state.counts[behind] == 0
    assert state.counts[ahead] == 1 and "bed" not in state.layers
    look_around(closed_room(door=False), state, turns=1, scores={"fridge": 0.2})
    assert state.values["fridge"][ahead] == pytest.approx(0.4)  # equal confidence: the mean
    assert state.counts[ahead] == 2
    state.remove_layer("cup")
    assert state.layers == ("fridge",)
    state.add_layer("bed")
    assert state.values["bed"].max() == 0.0


def test_field_of_view_edges_get_less_weight_and_the_far_edge_none() -> None:
    state = MapState(CONFIG, targets=["t"])
    look_around(closed_room(door=False), state, turns=1, scores={"t": 1.0})
    g = state.grid
    conf = state.confidence["t"]
    assert conf[g.to_cell(1.5, 0.0)] == pytest.approx(1.0, abs=0.01)
    x, y = g.to_world(*g.to_cell(1.5, 0.6))  # the cell centre, to compute its true angle
    assert conf[g.to_cell(1.5, 0.6)] == pytest.approx(float(fov_confidence(np.array(math.atan2(y, x)), HFOV)))
    assert conf[g.to_cell(1.5, 1.1)] == 0.0  # below the confidence floor: ignored
    assert state.counts[g.to_cell(1.5, 1.1)] == 0 and state.explored[g.to_cell(1.5, 1.1)]


def test_checkpoints_round_trip_and_damage_is_reported(tmp_path) -> None:
    state = MapState(CONFIG, targets=["fridge"])
    look_around(two_rooms().model_copy(), state, x=1.5, y=2.0, turns=3, scores={"fridge": 0.5})
    path = tmp_path / "map.ckpt"
    save_checkpoint(state, path, stamp=1.0)
    back = load_checkpoint(path, CONFIG)
    assert back.seq == state.seq and back.layers == state.layers
    for name in ("obstacle", "explored", "counts"):
        assert np.array_equal(getattr(back, name), getattr(state, name))
    assert np.array_equal(back.values["fridge"], state.values["fridge"])
    assert np.array_equal(back.confidence["fridge"], state.confidence["fridge"])
    path.write_bytes(path.read_bytes()[:-10])
    with pytest.raises(CheckpointError, match="unusable"):
        load_checkpoint(path, CONFIG)
    save_checkpoint(state, path, stamp=1.0)
    with pytest.raises(CheckpointError, match="grid"):
        load_checkpoint(path, MappingConfig(grid_cells=300))
    assert [p.name for p in tmp_path.iterdir()] == ["map.ckpt"]  # no temp file left
