"""The scene renderer: deterministic pixels, metric z-depth, instance ids, a pose that agrees.

Small hand-made scenes whose answers are known: a wall a given distance ahead,
a box in front of or behind it. Importing ovamos.world.render sets MUJOCO_GL=egl.
"""

from __future__ import annotations

import hashlib
import math
import sys

import numpy as np
import pytest

from ovamos.shared.camera import CAMERA_HEIGHT_M, DEPTH_RANGE_M
from ovamos.shared.messages import RgbdFrame
from ovamos.world import render
from ovamos.world.render import SceneRenderer
from ovamos.world.scene import WALL_THICKNESS, Room, Scene, SceneObject, Wall

W, H = 160, 120
CAMERA = (1.0, 0.0)  # where the camera stands in the scenes below, looking along +x (yaw 0)


def box(id: int, x: float, y: float, *, size: tuple[float, float, float] = (0.4, 0.4, 1.0),
        z: float = 0.0, yaw: float = 0.0, room: int = 2) -> SceneObject:
    return SceneObject(id=id, cls="box", x=x, y=y, z=z, sx=size[0], sy=size[1], sz=size[2], yaw=yaw,
                       room=room, rgba=(0.2, 0.6, 0.3, 1.0))


def wall_scene(face_distance: float | None, objects: tuple[SceneObject, ...] = ()) -> Scene:
    """Room 2 (the camera's, x in [-1, 12]), room 5 beyond, a wall ``face_distance`` ahead."""
    walls = ()
    if face_distance is not None:
        x = CAMERA[0] + face_distance + WALL_THICKNESS / 2
        walls = (Wall(x0=x, y0=-20.0, x1=x, y1=20.0),)
    rooms = (Room(id=2, type="kitchen", x0=-1.0, y0=-20.0, x1=12.0, y1=20.0),
             Room(id=5, type="bedroom", x0=12.0, y0=-20.0, x1=20.0, y1=20.0))
    return Scene(width=20.0, depth=40.0, rooms=rooms, walls=walls, objects=objects)


def frame(scene: Scene, x: float = CAMERA[0], y: float = CAMERA[1], yaw: float = 0.0,
          width: int = W, height: int = H) -> RgbdFrame:
    with SceneRenderer(scene, width, height) as renderer:
        return renderer.render(x, y, yaw)


def back_project(f: RgbdFrame, v: np.ndarray, u: np.ndarray) -> np.ndarray:
    """World points (N x 3) of pixels (v, u) from the frame's depth, intrinsics and pose."""
    k, z = f.intrinsics, f.depth[v, u].astype(np.float64)
    cam = np.stack([(u - k.cx) / k.fx * z, (v - k.cy) / k.fy * z, z, np.ones_like(z)])
    return (f.pose_matrix @ cam)[:3].T


def sha(a: np.ndarray) -> str:
    return hashlib.sha256(np.ascontiguousarray(a).tobytes()).hexdigest()


# -- (a) determinism -------------------------------------------------------------------------


def test_same_scene_and_pose_give_identical_frames() -> None:
    scene = wall_scene(3.0, (box(1, 2.5, 0.4, yaw=0.3), box(2, 3.0, -0.8, size=(0.3, 0.6, 0.5))))
    pose = (1.2, 0.1, 0.2)
    with SceneRenderer(scene, W, H) as first, SceneRenderer(scene, W, H) as second:
        a = first.render(*pose)
        second.render(2.0, 1.0, 2.0)  # a different pose in between changes nothing
        b = second.render(*pose)
        c = first.render(*pose)
    for name in ("rgb", "depth", "instance_ids"):
        assert sha(getattr(a, name)) == sha(getattr(b, name)) == sha(getattr(c, name)), name
    assert a.rgb.max() > 50, "the image is lit"


# -- (b) metric z-depth ----------------------------------------------------------------------


@pytest.mark.parametrize("distance", [2.0, 3.3])
def test_wall_ahead_reads_its_distance_at_the_centre(distance: float) -> None:
    f = frame(wall_scene(distance))
    centre = f.depth[H // 2 - 1:H // 2 + 1, W // 2 - 1:W // 2 + 1]
    assert f.depth.dtype == np.float32
    assert np.abs(centre - distance).max() < 0.01


def test_off_centre_pixel_reads_z_depth_not_ray_length() -> None:
    f = frame(wall_scene(2.0))
    v, u = H // 2, 2  # near the left edge: the ray is ~38 degrees off axis, 2.5 m long
    k = f.intrinsics
    ray_length = 2.0 * math.hypot(1.0, (u - k.cx) / k.fx, (v - k.cy) / k.fy)
    assert ray_length > 2.4
    assert abs(f.depth[v, u] - 2.0) < 0.01
    # the whole band of wall between floor and wall top is one plane: constant z-depth
    wall_rows = f.depth[H // 2 - 10:H // 2 + 10]
    assert np.abs(wall_rows - 2.0).max() < 0.01


# -- (c) instance ids ------------------------------------------------------------------------


def test_object_in_view_carries_its_id() -> None:
    red = box(7, 3.0, 0.0, yaw=0.4).model_copy(update={"rgba": (0.9, 0.1, 0.1, 1.0)})
    f = frame(wall_scene(4.0, (red,)))
    mask = f.instance_ids == 7
    assert mask.sum() > 50
    assert f.instance_ids[H // 2, W // 2] == 7
    # the colour image agrees with the ids pixel for pixel (same rows, same columns)
    rgb = f.rgb.astype(int)
    is_red = rgb[..., 0] > 2 * rgb[..., 1] + 10
    assert is_red[mask].all() and not is_red[~mask].any()


def test_object_behind_a_wall_never_appears() -> None:
    hidden = (box(9, 4.5, 0.0, size=(0.6, 0.6, 2.0)),)
    with SceneRenderer(wall_scene(2.0, hidden), W, H) as walled, \
            SceneRenderer(wall_scene(None, hidden), W, H) as open_:
        for yaw in (-0.6, -0.2, 0.0, 0.3, 0.6):
            assert not (walled.render(*CAMERA, yaw).instance_ids == 9).any(), yaw
        assert (open_.render(*CAMERA, 0.0).instance_ids == 9).any(), "visible without the wall"


def test_floor_walls_and_empty_space_ids() -> None:
    f = frame(wall_scene(2.0))
    ids = f.instance_ids
    assert ids[-1, W // 2] == -(2 + 1), "the floor of room 2, where the camera stands"
    assert ids[H // 2, W // 2] == 0, "walls are 0"
    assert set(np.unique(ids)) <= {0, -3}
    # with no wall, the far room's floor shows up with its own id, and the sky is 0 too
    open_ids = frame(wall_scene(None)).instance_ids
    assert -(5 + 1) in open_ids
    assert open_ids[0, W // 2] == 0


# -- (d) depth range -------------------------------------------------------------------------


def test_depth_outside_the_sensor_range_is_zero() -> None:
    lo, hi = DEPTH_RANGE_M
    too_close = frame(wall_scene(0.3), width=64, height=48)
    assert too_close.depth[24, 32] == 0.0 and too_close.instance_ids[24, 32] == 0
    too_far = frame(wall_scene(6.0), width=64, height=48)
    assert too_far.depth[24, 32] == 0.0
    assert too_far.depth[-1, 32] > 0, "the floor near the robot is in range"
    for f in (too_close, too_far, frame(wall_scene(2.0), width=64, height=48)):
        d = f.depth[f.depth != 0]
        assert d.size == 0 or (d.min() >= lo and d.max() <= hi)


# -- (e) the pose agrees with the pixels -----------------------------------------------------


def test_centre_pixel_back_projects_onto_the_wall() -> None:
    x, y, yaw = 0.7, -0.4, 0.25
    face_x = CAMERA[0] + 2.5
    f = frame(wall_scene(2.5), x=x, y=y, yaw=yaw)
    p = back_project(f, np.array([H // 2]), np.array([W // 2]))[0]
    assert abs(p[0] - face_x) < 0.01
    # and it lies on the centre pixel's ray: ~level, along the heading
    assert abs(p[2] - CAMERA_HEIGHT_M) < 0.02
    assert abs(math.atan2(p[1] - y, p[0] - x) - yaw) < 0.01


def test_every_labelled_pixel_back_projects_onto_its_surface() -> None:
    """Object pixels land on their box, floor pixels on the floor: intrinsics, pose, flips agree."""
    left = box(3, 2.6, 0.9, size=(0.5, 0.3, 0.7), yaw=0.5)
    right = box(4, 3.2, -0.7, size=(0.4, 0.8, 1.2), z=0.2, yaw=-0.3)
    f = frame(wall_scene(4.0, (left, right)), yaw=0.05)
    for obj in (left, right):
        v, u = np.nonzero(f.instance_ids == obj.id)
        assert v.size > 30
        p = back_project(f, v, u)
        c, s = math.cos(obj.yaw), math.sin(obj.yaw)
        local_x = (p[:, 0] - obj.x) * c + (p[:, 1] - obj.y) * s
        local_y = -(p[:, 0] - obj.x) * s + (p[:, 1] - obj.y) * c
        tol = 0.01
        assert np.abs(local_x).max() < obj.sx / 2 + tol
        assert np.abs(local_y).max() < obj.sy / 2 + tol
        assert p[:, 2].min() > obj.z - tol and p[:, 2].max() < obj.z + obj.sz + tol
    # left of the image is +y (REP-103 left), the top of the image is up
    assert np.nonzero(f.instance_ids == 3)[1].mean() < f.intrinsics.cx
    assert np.nonzero(f.instance_ids == 4)[1].mean() > f.intrinsics.cx
    v, u = np.nonzero((f.instance_ids == -3) & (f.depth > 0))
    assert v.min() > H // 2, "the floor is in the lower half"
    assert np.abs(back_project(f, v, u)[:, 2]).max() < 0.01


# -- (f) the wire ----------------------------------------------------------------------------


def test_frame_survives_encode_and_decode() -> None:
    f = frame(wall_scene(2.0, (box(5, 2.0, 0.3),)), width=64, height=48)
    assert f.depth[24, 32] > 0 and (f.instance_ids == 5).any() and f.rgb.any()
    g = RgbdFrame.from_bytes(bytes(f.to_bytes()))
    assert g.intrinsics == f.intrinsics and g.camera_pose == f.camera_pose
    for name in ("rgb", "depth", "instance_ids"):
        a, b = getattr(f, name), getattr(g, name)
        assert a.dtype == b.dtype and np.array_equal(a, b), name
    assert g.rgb.shape == (48, 64, 3) and g.instance_ids.dtype == np.int32


def test_render_takes_seq_and_stamp_and_close_is_final() -> None:
    renderer = SceneRenderer(wall_scene(2.0), 64, 48)
    f = renderer.render(*CAMERA, 0.0, seq=12, stamp=3.5)
    assert (f.seq, f.stamp) == (12, 3.5)
    renderer.close()
    renderer.close()
    with pytest.raises(RuntimeError, match="close"):
        renderer.render(*CAMERA, 0.0)


def test_missing_mujoco_says_how_to_install(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "mujoco", None)
    with pytest.raises(ImportError, match=r"ovamos\[sim\]"):
        render._mujoco()
