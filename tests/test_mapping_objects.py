"""The object map: masks projected with depth land on the object; instances merge and confirm.

Positions come from two kinds of frames whose answers are known:

* frames rendered by the simulator (``tests.sim_scenes.two_rooms``) with a
  perfect mask ``instance_ids == id``: the kitchen fridge (id 1) is a 0.7 x 0.7 x
  1.8 m box centred at (0.4, 3.0), so its footprint is x in [0.05, 0.75], y in
  [2.65, 3.35], and its front face (the one facing the room) is the plane x = 0.75;
* hand-made frames: a flat patch of pixels, symmetric about the principal
  point, at depth ``D`` in front of a level camera; its median point is exactly
  ``D`` ahead of the camera at camera height, so a camera placed ``D`` behind a
  point puts the detection on that point.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from ovamos.services.mapping.objects import ObjectMap, detection_position, mask_points
from ovamos.shared.camera import CAMERA_HEIGHT_M, camera_pose, pinhole
from ovamos.shared.detections import Detection
from ovamos.shared.messages import ObjectInstance, RgbdFrame
from ovamos.world.render import SceneRenderer
from tests.sim_scenes import two_rooms

CELL = 0.05  # the map's resolution: "within one cell"
W, H = 160, 120
D = 2.0  # depth of the hand-made patch
PATCH = np.s_[50:70, 70:90]  # 20 x 20 pixels centred on the principal point (59.5, 79.5)
FRIDGE_X = (0.05, 0.75)
FRIDGE_Y = (2.65, 3.35)
FRIDGE_FACE_X = 0.75
FRIDGE_HEIGHT = 1.8


# -- helpers ---------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def renderer():
    with SceneRenderer(two_rooms(), W, H) as r:
        yield r


def in_footprint(x: float, y: float, xs: tuple[float, float], ys: tuple[float, float],
                 tol: float = 1e-3) -> bool:
    """(x, y) inside a box's footprint, give or take ``tol`` (depth buffer precision)."""
    return xs[0] - tol <= x <= xs[1] + tol and ys[0] - tol <= y <= ys[1] + tol


def detection(label: str, score: float, mask: np.ndarray) -> Detection:
    """A detection with its mask's bounding box (the object map reads only the mask)."""
    v, u = np.nonzero(mask)
    box = (0, 0, 0, 0)
    if v.size:
        box = (int(u.min()), int(v.min()), int(u.max()) + 1, int(v.max()) + 1)
    return Detection(label, score, box, mask)


def patch_frame(x: float, y: float, depth: np.ndarray | None = None, seq: int = 0) -> RgbdFrame:
    """A frame whose patch is ``D`` m in front of a camera looking along +x, so at (x, y)."""
    if depth is None:
        depth = np.zeros((H, W), np.float32)
        depth[PATCH] = D
    return RgbdFrame(seq=seq, stamp=0.0, intrinsics=pinhole(W, H),
                     camera_pose=camera_pose(x - D, y, 0.0), rgb=np.zeros((H, W, 3), np.uint8),
                     depth=depth)


def patch_mask() -> np.ndarray:
    mask = np.zeros((H, W), bool)
    mask[PATCH] = True
    return mask


def see(obj_map: ObjectMap, label: str, x: float, y: float, score: float = 0.8
        ) -> list[ObjectInstance]:
    """One detection of ``label`` at world (x, y), as a hand-made frame shows it."""
    return obj_map.add([detection(label, score, patch_mask())], patch_frame(x, y))


# -- projection: where a mask lands ----------------------------------------------------------

def test_the_hand_made_patch_lands_exactly_where_it_was_put() -> None:
    pos = detection_position(detection("cup", 0.9, patch_mask()), patch_frame(1.5, -0.7))
    assert pos == pytest.approx([1.5, -0.7, CAMERA_HEIGHT_M], abs=1e-9)


def test_a_head_on_fridge_lands_on_the_centre_of_its_front_face(renderer) -> None:
    # Camera 1.25 m in front of the face, on its centre line, looking at it (-x). The whole
    # face width is in view (y in [2.65, 3.35]), so the visible points are the face itself:
    # x = 0.75 everywhere, y symmetric about 3.0, z in the visible band of [0, 1.8].
    frame = renderer.render(2.0, 3.0, math.pi)
    mask = frame.instance_ids == 1
    assert mask.sum() > 2000  # the mask is subsampled: this checks the subsampled median
    points = mask_points(mask, frame, max_points=10**6)
    assert np.abs(points[:, 0] - FRIDGE_FACE_X).max() < 1e-3  # every point is on the face
    x, y, z = detection_position(detection("fridge", 0.9, mask), frame)
    assert abs(x - FRIDGE_FACE_X) < 0.01       # on the face plane
    assert abs(y - 3.0) < CELL                 # at the face's centre, within one cell
    assert 0.0 < z < FRIDGE_HEIGHT


@pytest.mark.parametrize("pose", [(2.0, 2.0, math.atan2(1.0, -1.6)),
                                  (1.8, 2.2, 0.8 * math.pi)])
def test_an_oblique_fridge_lands_inside_its_footprint(renderer, pose) -> None:
    # Seen from the side, the mask covers the front face and a side face: every point is on
    # the box's surface, so the component-wise median lies in the box's extent, and the
    # nearer face (x = 0.75) holds most points.
    frame = renderer.render(*pose)
    mask = frame.instance_ids == 1
    points = mask_points(mask, frame, max_points=10**6)
    assert (points[:, 1] < FRIDGE_Y[0] + 0.01).any()  # the side face y = 2.65 is in view
    x, y, z = detection_position(detection("fridge", 0.9, mask), frame)
    assert in_footprint(x, y, FRIDGE_X, FRIDGE_Y)
    assert 0.0 <= z <= FRIDGE_HEIGHT


def test_edge_pixels_on_the_wall_behind_do_not_drag_the_position(renderer) -> None:
    # A sloppy mask (the true one grown by 4 pixels, as a segmenter's often is) also covers
    # the wall behind the fridge (x = 0.05) and the floor: the mean moves off the face, the
    # median stays on it.
    frame = renderer.render(2.0, 3.0, math.pi)
    true_mask = frame.instance_ids == 1
    sloppy = cv2.dilate(true_mask.astype(np.uint8), np.ones((9, 9), np.uint8)).astype(bool)
    points = mask_points(sloppy, frame, max_points=10**6)
    assert (points[:, 0] < 0.1).any()  # some points did hit the wall
    x, y, _ = detection_position(detection("fridge", 0.9, sloppy), frame)
    assert abs(x - FRIDGE_FACE_X) < CELL and abs(y - 3.0) < CELL
    assert abs(points[:, 0].mean() - FRIDGE_FACE_X) > CELL  # what a mean would have done


def test_subsampling_is_bounded_deterministic_and_keeps_the_answer(renderer) -> None:
    frame = renderer.render(2.0, 2.0, math.atan2(1.0, -1.6))
    mask = frame.instance_ids == 1
    few = mask_points(mask, frame, max_points=500)
    assert len(few) == 500
    np.testing.assert_array_equal(few, mask_points(mask, frame, max_points=500))
    full = np.median(mask_points(mask, frame, max_points=10**6), axis=0)
    assert np.abs(np.median(few, axis=0)[:2] - full[:2]).max() < CELL


def test_uint16_depth_in_millimetres_gives_the_same_position() -> None:
    depth = np.zeros((H, W), np.uint16)
    depth[PATCH] = int(D * 1000)
    f = patch_frame(3.0, 1.0, depth=depth)
    frame = RgbdFrame(seq=0, stamp=0.0, intrinsics=f.intrinsics, camera_pose=f.camera_pose,
                      depth_scale=0.001, rgb=f.rgb, depth=depth)
    pos = detection_position(detection("cup", 0.9, patch_mask()), frame)
    assert pos == pytest.approx([3.0, 1.0, CAMERA_HEIGHT_M], abs=1e-6)


def test_pixels_without_depth_are_left_out() -> None:
    depth = np.zeros((H, W), np.float32)
    depth[PATCH] = D
    depth[50:60, 70:90] = 0.0          # no reading on the top half of the patch ...
    depth[PATCH][:, 0] = np.nan        # ... and garbage on a column
    mask = np.zeros((H, W), bool)
    mask[40:80, 60:100] = True         # the mask also covers pixels with no depth
    points = mask_points(mask, patch_frame(0.0, 0.0, depth=depth))
    assert len(points) == 10 * 19
    assert np.isfinite(points).all()


# -- instances: merging, hits, confirmation ------------------------------------------------

def test_repeated_detections_merge_count_hits_and_confirm() -> None:
    obj_map = ObjectMap(merge_distance_m=0.5, confirm_hits=3, decision_threshold=0.35)
    (first,) = see(obj_map, "cup", 1.0, 1.0, score=0.5)
    assert (first.hits, first.confirmed) == (1, False)
    (second,) = see(obj_map, "cup", 1.3, 1.0, score=0.9)
    assert (second.hits, second.confirmed, second.score) == (2, False, 0.9)
    assert second.x == pytest.approx(1.15) and second.y == pytest.approx(1.0)
    (third,) = see(obj_map, "cup", 1.15, 1.3, score=0.4)
    assert (third.hits, third.confirmed, third.score) == (3, True, 0.9)  # best score kept
    assert (third.x, third.y) == pytest.approx((1.15, 1.1))  # hit-weighted mean of the three
    assert obj_map.instances() == (third,)
    assert obj_map.confirmed("cup") == [third]


def test_confirmation_follows_confirm_hits() -> None:
    obj_map = ObjectMap(confirm_hits=2)
    see(obj_map, "bed", 2.0, 2.0)
    assert obj_map.confirmed("bed") == []
    see(obj_map, "bed", 2.1, 2.0)
    assert [i.hits for i in obj_map.confirmed("bed")] == [2]


def test_another_label_or_a_far_position_makes_a_new_instance() -> None:
    obj_map = ObjectMap(merge_distance_m=0.5)
    see(obj_map, "cup", 1.0, 1.0)
    see(obj_map, "mug", 1.0, 1.0)    # same place, other label
    see(obj_map, "cup", 1.0, 1.6)    # same label, 0.6 m away
    see(obj_map, "cup", 1.0, 1.45)   # 0.45 from the first, 0.15 from the third: nearest wins
    got = [(i.label, i.x, round(i.y, 3), i.hits) for i in obj_map.instances()]
    assert got == [("cup", 1.0, 1.0, 1), ("mug", 1.0, 1.0, 1), ("cup", 1.0, 1.525, 2)]


def test_merging_uses_the_floor_plane_distance() -> None:
    # The same object seen at another height (more or less of it in view) is the same object.
    obj_map = ObjectMap(merge_distance_m=0.5)
    see(obj_map, "fridge", 1.0, 1.0)
    frame = patch_frame(1.0, 1.0)
    low = np.zeros((H, W), bool)
    low[100:110, 70:90] = True  # pixels well below the optical axis: about 0.9 m lower
    depth = frame.depth.copy()
    depth[100:110, 70:90] = D
    frame = RgbdFrame(seq=1, stamp=0.0, intrinsics=frame.intrinsics, camera_pose=frame.camera_pose,
                      rgb=frame.rgb, depth=depth)
    (inst,) = obj_map.add([detection("fridge", 0.8, low)], frame)
    assert inst.hits == 2 and len(obj_map) == 1


def test_low_score_detections_are_ignored_entirely() -> None:
    obj_map = ObjectMap(confirm_hits=1, decision_threshold=0.35)
    for _ in range(5):
        assert see(obj_map, "cup", 1.0, 1.0, score=0.34) == []
    assert obj_map.instances() == ()
    assert see(obj_map, "cup", 1.0, 1.0, score=float("nan")) == []
    (inst,) = see(obj_map, "cup", 1.0, 1.0, score=0.35)  # the threshold itself counts
    assert (inst.hits, inst.confirmed) == (1, True)
    see(obj_map, "cup", 1.0, 1.0, score=0.2)  # ... and a low one afterwards adds no hit
    assert obj_map.instances()[0].hits == 1


def test_detections_without_depth_or_pixels_are_skipped() -> None:
    obj_map = ObjectMap()
    empty_mask = np.zeros((H, W), bool)
    no_depth = patch_frame(1.0, 1.0, depth=np.zeros((H, W), np.float32))
    nan_depth = patch_frame(1.0, 1.0, depth=np.full((H, W), np.nan, np.float32))
    assert obj_map.add([detection("cup", 0.9, empty_mask)], patch_frame(1.0, 1.0)) == []
    assert obj_map.add([detection("cup", 0.9, patch_mask())], no_depth) == []
    assert obj_map.add([detection("cup", 0.9, patch_mask())], nan_depth) == []
    assert obj_map.add([], patch_frame(1.0, 1.0)) == []
    assert len(obj_map) == 0
    with pytest.raises(ValueError, match="mask shape"):
        obj_map.add([detection("cup", 0.9, np.ones((10, 10), bool))], patch_frame(1.0, 1.0))


def test_one_frame_with_several_detections() -> None:
    obj_map = ObjectMap()
    frame = patch_frame(1.0, 1.0)
    used = obj_map.add([detection("cup", 0.9, patch_mask()), detection("cup", 0.1, patch_mask()),
                        detection("bowl", 0.6, patch_mask())], frame)
    assert [(i.label, i.hits) for i in used] == [("cup", 1), ("bowl", 1)]


def test_confirmed_lists_most_seen_first() -> None:
    obj_map = ObjectMap(confirm_hits=2)
    for x, n in ((1.0, 2), (3.0, 4), (5.0, 1)):
        for _ in range(n):
            see(obj_map, "cup", x, 1.0)
    assert [(i.x, i.hits) for i in obj_map.confirmed("cup")] == [(3.0, 4), (1.0, 2)]
    assert obj_map.confirmed("bed") == []


def test_from_instances_round_trips_and_recomputes_confirmation() -> None:
    obj_map = ObjectMap(confirm_hits=2)
    for x, n in ((1.0, 2), (3.0, 1)):
        for _ in range(n):
            see(obj_map, "cup", x, 1.0)
    see(obj_map, "bed", 2.0, 2.0)
    saved = obj_map.instances()
    restored = ObjectMap.from_instances(saved, confirm_hits=2)
    assert restored.instances() == saved
    see(restored, "cup", 3.1, 1.0)  # the restored map keeps fusing
    assert restored.instances()[1].hits == 2 and restored.instances()[1].confirmed
    stricter = ObjectMap.from_instances(saved, confirm_hits=5)
    assert not any(i.confirmed for i in stricter.instances())
    weak = ObjectInstance(label="cup", x=0, y=0, score=0.1, hits=9, confirmed=True)
    assert not ObjectMap.from_instances([weak]).instances()[0].confirmed


def test_bad_parameters_are_refused() -> None:
    with pytest.raises(ValueError, match="merge_distance_m"):
        ObjectMap(merge_distance_m=0)
    with pytest.raises(ValueError, match="confirm_hits"):
        ObjectMap(confirm_hits=0)


# -- end to end with the simulator -----------------------------------------------------------

def test_two_views_of_the_fridge_confirm_one_instance_and_the_other_fridge_is_another(
        renderer) -> None:
    obj_map = ObjectMap()
    for pose in [(2.0, 3.0, math.pi), (2.0, 2.0, math.atan2(1.0, -1.6))]:
        frame = renderer.render(*pose)
        obj_map.add([detection("fridge", 0.7, frame.instance_ids == 1)], frame)
    (kitchen,) = obj_map.confirmed("fridge")
    assert kitchen.hits == 2
    assert in_footprint(kitchen.x, kitchen.y, FRIDGE_X, FRIDGE_Y)
    # The office fridge (id 4, centred at (5.6, 3.4), 0.7 m square) from the office.
    frame = renderer.render(4.2, 2.0, math.atan2(1.4, 1.4))
    (office,) = obj_map.add([detection("fridge", 0.7, frame.instance_ids == 4)], frame)
    assert office.hits == 1 and not office.confirmed
    assert in_footprint(office.x, office.y, (5.25, 5.95), (3.05, 3.75))
    assert [i.hits for i in obj_map.instances()] == [2, 1]


# -- negative evidence: views without detections ---------------------------------------------

def test_views_without_detections_keep_a_rare_false_positive_unconfirmed() -> None:
    obj_map = ObjectMap(confirm_hits=2, min_hit_ratio=0.3)
    see(obj_map, "cup", 1.5, 0.0)
    for seq in range(8):  # the place seen again and again, nothing detected there
        obj_map.observe(patch_frame(1.5, 0.0, seq=seq), ["cup"])
    (inst,) = see(obj_map, "cup", 1.5, 0.0)
    assert (inst.hits, inst.views) == (2, 9) and not inst.confirmed
    for _ in range(2):
        (inst,) = see(obj_map, "cup", 1.5, 0.0)
    assert inst.hits == 4 and inst.confirmed   # a real object keeps being detected


def test_defaults_are_the_mapping_services_and_a_ratio_of_zero_switches_views_off() -> None:
    from ovamos.services.mapping.config import MappingConfig

    c, obj_map = MappingConfig(), ObjectMap()
    assert (obj_map.merge_distance_m, obj_map.confirm_hits, obj_map.decision_threshold,
            obj_map.min_hit_ratio, obj_map.view_range_m) == (
        c.object_merge_distance_m, c.object_confirm_hits, c.decision_threshold,
        c.object_min_hit_ratio, c.object_view_range_m)
    assert obj_map.min_hit_ratio > 0  # production's rule: the one unit tests exercise
    counted = ObjectMap(min_hit_ratio=0.0)
    for m in (obj_map, counted):
        see(m, "cup", 1.5, 0.0)
        for seq in range(8):
            m.observe(patch_frame(1.5, 0.0, seq=seq), ["cup"])
        see(m, "cup", 1.5, 0.0)
    assert not obj_map.instances()[0].confirmed and counted.instances()[0].confirmed


def test_only_unoccluded_in_range_views_of_the_searched_labels_count() -> None:
    obj_map = ObjectMap(min_hit_ratio=0.5, view_range_m=3.0)
    see(obj_map, "cup", 1.5, 0.0)
    blocked = np.zeros((H, W), np.float32)
    blocked[:] = 0.5 * D  # a wall between the camera and the cup
    obj_map.observe(patch_frame(1.5, 0.0, depth=blocked), ["cup"])
    obj_map.observe(patch_frame(1.5, 0.0), ["bed"])         # not searched for the cup
    far = RgbdFrame(seq=1, stamp=0.0, intrinsics=pinhole(W, H), camera_pose=camera_pose(-3.0, 0.0, 0.0),
                    rgb=np.zeros((H, W, 3), np.uint8), depth=np.zeros((H, W), np.float32))
    obj_map.observe(far, ["cup"])                             # 4.5 m away: beyond the view range
    behind = RgbdFrame(seq=2, stamp=0.0, intrinsics=pinhole(W, H), camera_pose=camera_pose(3.0, 0.0, 0.0),
                       rgb=np.zeros((H, W, 3), np.uint8), depth=np.zeros((H, W), np.float32))
    obj_map.observe(behind, ["cup"])                          # looking away
    assert obj_map.instances()[0].views == 1
    obj_map.observe(patch_frame(1.5, 0.0), ["cup"])
    assert obj_map.instances()[0].views == 2


def test_views_survive_a_checkpoint() -> None:
    obj_map = ObjectMap(min_hit_ratio=0.3)
    see(obj_map, "cup", 1.5, 0.0)
    for seq in range(5):
        obj_map.observe(patch_frame(1.5, 0.0, seq=seq), ["cup"])
    restored = ObjectMap.from_instances(obj_map.instances(), min_hit_ratio=0.3)
    assert restored.instances() == obj_map.instances()
