"""Mapping core: obstacles, explored area, frontiers, value layers, decay, checkpoints."""

from __future__ import annotations

import math

import numpy as np
import pytest

from ovamos.services.mapping.checkpoint import CheckpointError, load_checkpoint, save_checkpoint
from ovamos.services.mapping.config import MappingConfig
from ovamos.services.mapping.layers import aggregate, decay, fov_confidence, fuse
from ovamos.services.mapping.state import MapState
from ovamos.shared.detections import Detection
from ovamos.shared.messages import PerceptionResult
from ovamos.world.render import SceneRenderer
from ovamos.world.scene import Room, Scene, Wall
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
    assert state.values["fridge"][behind] == 0.0 and state.counts["fridge"][behind] == 0
    assert state.counts["fridge"][ahead] == 1 and "bed" not in state.layers
    look_around(closed_room(door=False), state, turns=1, scores={"fridge": 0.2})
    assert state.values["fridge"][ahead] == pytest.approx(0.4)  # equal confidence: the mean
    assert state.counts["fridge"][ahead] == 2
    assert state.counts["cup"][ahead] == 1  # a layer counts the views of its own target only
    state.remove_layer("cup")
    assert state.layers == ("fridge",)
    state.add_layer("bed")
    assert state.values["bed"].max() == 0.0 and state.counts["bed"].max() == 0


def _grids(state: MapState) -> dict[str, np.ndarray]:
    return {"obstacle": state.obstacle, "explored": state.explored,
            **{f"counts {t}": v for t, v in state.counts.items()},
            **{f"searched {t}": v for t, v in state.searched.items()},
            **{f"value {t}": v for t, v in state.values.items()},
            **{f"confidence {t}": c for t, c in state.confidence.items()}}


def test_a_frame_counts_once_and_a_second_result_adds_only_new_targets_values() -> None:
    """The services' order (the first view fused before the task reached perception, then
    re-scored for the task's targets; the camera re-publishing it while the robot stands still)
    builds the map the benchmark's order (the frame once, with the targets) builds."""
    with SceneRenderer(closed_room(door=False), 160, 120) as renderer:
        frame = renderer.render(0.0, 0.0, 0.0, seq=0, stamp=0.0)
    mask = np.zeros(frame.depth.shape, bool)
    mask[50:70, 70:90] = True  # the wall ahead, in range
    cup = Detection("cup", 0.9, (70, 50, 90, 70), mask)

    def result(scores: dict[str, float], detections: list[Detection]) -> PerceptionResult:
        return PerceptionResult.build(frame.seq, frame.stamp, scores, detections, frame.depth.shape)

    once = MapState(CONFIG)
    assert once.apply(frame, result({"cup": 0.6, "fridge": 0.2}, [cup]))
    services = MapState(CONFIG)
    services.apply(frame, result({}, []))                        # before the task
    assert services.apply(frame, result({"cup": 0.6}, [cup]))   # re-scored for the task
    assert services.apply(frame, result({"cup": 0.6, "fridge": 0.2}, [cup]))  # a target added
    assert not services.apply(frame)                             # re-published, no result yet
    assert not services.apply(frame, result({"cup": 0.6, "fridge": 0.2}, [cup]))  # and its result
    a, b = _grids(once), _grids(services)
    assert a.keys() == b.keys() and services.layers == ("cup", "fridge")
    for name in a:
        assert np.array_equal(a[name], b[name]), name
    assert services.counts["cup"].max() == 1
    assert services.objects.instances() == once.objects.instances()
    assert [o.hits for o in once.objects.instances()] == [1]
    # the same seq with another stamp is another frame (a restarted camera counts from 0 again)
    services.apply(frame.model_copy(update={"stamp": 5.0}), result({"cup": 0.6, "fridge": 0.2}, [cup]))
    assert services.counts["cup"].max() == 2


def test_field_of_view_edges_get_less_weight_and_the_far_edge_none() -> None:
    state = MapState(CONFIG, targets=["t"])
    look_around(closed_room(door=False), state, turns=1, scores={"t": 1.0})
    g = state.grid
    conf = state.confidence["t"]
    assert conf[g.to_cell(1.5, 0.0)] == pytest.approx(1.0, abs=0.01)
    x, y = g.to_world(*g.to_cell(1.5, 0.6))  # the cell centre, to compute its true angle
    assert conf[g.to_cell(1.5, 0.6)] == pytest.approx(float(fov_confidence(np.array(math.atan2(y, x)), HFOV)))
    assert conf[g.to_cell(1.5, 1.1)] == 0.0  # below the confidence floor: ignored
    assert state.counts["t"][g.to_cell(1.5, 1.1)] == 0 and state.explored[g.to_cell(1.5, 1.1)]
    assert state.searched["t"][g.to_cell(1.5, 1.1)]  # searched: seen, whatever the confidence


def test_checkpoints_round_trip_and_damage_is_reported(tmp_path) -> None:
    state = MapState(CONFIG, targets=["fridge"])
    look_around(two_rooms().model_copy(), state, x=1.5, y=2.0, turns=3, scores={"fridge": 0.5})
    path = tmp_path / "map.ckpt"
    save_checkpoint(state, path, stamp=1.0)
    back = load_checkpoint(path, CONFIG)
    assert back.seq == state.seq and back.layers == state.layers and back.odom_session == ""
    state.odom_session = "20261201T120000Z-abc123"
    save_checkpoint(state, path, stamp=1.0)
    assert load_checkpoint(path, CONFIG).odom_session == state.odom_session
    for name in ("obstacle", "explored"):
        assert np.array_equal(getattr(back, name), getattr(state, name))
    for name in ("values", "confidence", "counts", "searched"):
        assert np.array_equal(getattr(back, name)["fridge"], getattr(state, name)["fridge"]), name
    assert np.array_equal(back.values["fridge"], state.values["fridge"])
    assert np.array_equal(back.confidence["fridge"], state.confidence["fridge"])
    path.write_bytes(path.read_bytes()[:-10])
    with pytest.raises(CheckpointError, match="unusable"):
        load_checkpoint(path, CONFIG)
    save_checkpoint(state, path, stamp=1.0)
    with pytest.raises(CheckpointError, match="grid"):
        load_checkpoint(path, MappingConfig(grid_cells=300))
    assert [p.name for p in tmp_path.iterdir()] == ["map.ckpt"]  # no temp file left
