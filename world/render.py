"""Renders what the robot's camera sees in a :class:`~ovamos.world.scene.Scene`: RGB, depth, ids.

The scene becomes a static MuJoCo model once (a thin floor box per room, walls
as boxes, every object as an oriented box); each :meth:`SceneRenderer.render`
then moves a level camera to the robot's pose and draws two passes into an
offscreen OpenGL buffer (EGL, headless):

* a lit pass for ``rgb``;
* a segmentation pass (flat id colours, no anti-aliasing) whose colours give
  ``instance_ids`` and whose depth buffer gives ``depth``.

The frame follows the shared camera model (:mod:`ovamos.shared.camera`): square-pixel
pinhole intrinsics from the horizontal field of view, ``camera_pose`` from the
robot pose, image row 0 at the top, ``depth`` the metric z-depth along the
optical axis (what an RGB-D sensor reports, not the ray length), 0 outside
``DEPTH_RANGE_M``. ``instance_ids`` holds the object's id on object pixels,
``-(room.id + 1)`` on a room's floor and 0 on walls and empty space.

MuJoCo is imported lazily (``pip install 'ovamos[sim]'``) with ``MUJOCO_GL=egl``
unless the caller chose another backend. A renderer owns an OpenGL context:
use it from one thread and :meth:`~SceneRenderer.close` it (or use ``with``).
"""

from __future__ import annotations

import math
import os
from types import ModuleType
from typing import Any

import numpy as np

from ovamos.shared.camera import CAMERA_HEIGHT_M, DEPTH_RANGE_M, HFOV_DEG, camera_pose, pinhole
from ovamos.shared.messages import RgbdFrame
from ovamos.shared.motion import Pose
from ovamos.world.scene import WALL_HEIGHT, WALL_THICKNESS, Scene

# Floor colour per room type (RGBA); unknown types get FLOOR_DEFAULT.
FLOOR_RGBA: dict[str, tuple[float, float, float, float]] = {
    "kitchen": (0.78, 0.76, 0.70, 1.0),      # light tiles
    "living_room": (0.62, 0.47, 0.32, 1.0),  # wood
    "bedroom": (0.55, 0.60, 0.72, 1.0),      # blue carpet
    "bathroom": (0.85, 0.88, 0.90, 1.0),     # white tiles
    "office": (0.50, 0.50, 0.52, 1.0),       # grey carpet
    "dining_room": (0.58, 0.40, 0.28, 1.0),  # dark wood
}
FLOOR_DEFAULT = (0.6, 0.6, 0.6, 1.0)
WALL_RGBA = (0.92, 0.90, 0.85, 1.0)
FLOOR_THICKNESS = 0.01  # the floor boxes' top face is z = 0
# Clipping planes (metres). The near plane is far below DEPTH_RANGE_M[0], so a
# wall the camera almost touches is still drawn, not clipped away; depth uses a
# float reversed-Z buffer, so the ratio costs no precision worth mentioning.
ZNEAR = 0.02
ZFAR = 100.0

_INSTALL_HINT = "pip install 'ovamos[sim]'"
# MuJoCo picks its GL backend when it is first imported: set ours before anyone
# imports it (a process that imported mujoco without MUJOCO_GL gets GLFW, which
# needs a display).
os.environ.setdefault("MUJOCO_GL", "egl")


def _mujoco() -> ModuleType:
    """Import MuJoCo with a headless GL backend unless the caller chose one."""
    os.environ.setdefault("MUJOCO_GL", "egl")
    try:
        import mujoco
    except ImportError as exc:
        raise ImportError(f"the simulator needs MuJoCo: {_INSTALL_HINT} ({exc})") from exc
    return mujoco


def _f(*values: float) -> str:
    return " ".join(repr(float(v)) for v in values)


def _box(pos: tuple[float, ...], yaw: float, half: tuple[float, ...], rgba: tuple[float, ...]
         ) -> str:
    """A box geom: centre, rotation about z, half sizes, colour."""
    quat = (math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2))
    return (f'<geom type="box" pos="{_f(*pos)}" quat="{_f(*quat)}" size="{_f(*half)}" '
            f'rgba="{_f(*rgba)}"/>')


def build_mjcf(scene: Scene, width: int, height: int, hfov_deg: float = HFOV_DEG,
               antialias: bool = False) -> tuple[str, list[int]]:
    """The scene as an MJCF string, and the instance id of each geom in model order.

    Geoms are listed as floors (one per room), walls, objects, so geom ``i`` of
    the compiled model has id ``ids[i]``.
    """
    fovy = math.degrees(2 * math.atan(math.tan(math.radians(hfov_deg) / 2) * height / width))
    geoms: list[str] = []
    ids: list[int] = []
    for room in scene.rooms:
        hx, hy = (room.x1 - room.x0) / 2, (room.y1 - room.y0) / 2
        rgba = FLOOR_RGBA.get(room.type, FLOOR_DEFAULT)
        geoms.append(_box((room.x0 + hx, room.y0 + hy, -FLOOR_THICKNESS / 2), 0.0,
                          (hx, hy, FLOOR_THICKNESS / 2), rgba))
        ids.append(-(room.id + 1))
    for wall in scene.walls:
        if wall.length < 1e-6:
            continue
        yaw = math.atan2(wall.y1 - wall.y0, wall.x1 - wall.x0)
        geoms.append(_box(((wall.x0 + wall.x1) / 2, (wall.y0 + wall.y1) / 2, WALL_HEIGHT / 2), yaw,
                          (wall.length / 2, WALL_THICKNESS / 2, WALL_HEIGHT / 2), WALL_RGBA))
        ids.append(0)
    for obj in scene.objects:
        geoms.append(_box((obj.x, obj.y, obj.z + obj.sz / 2), obj.yaw,
                          (obj.sx / 2, obj.sy / 2, obj.sz / 2), obj.rgba))
        ids.append(obj.id)
    cx, cy = scene.width / 2, scene.depth / 2
    xml = f"""<mujoco model="ovamos-scene">
  <statistic extent="1" center="{_f(cx, cy, 1.0)}"/>
  <visual>
    <global offwidth="{width}" offheight="{height}"/>
    <quality offsamples="{4 if antialias else 0}"/>
    <map znear="{ZNEAR!r}" zfar="{ZFAR!r}"/>
    <headlight ambient="0.35 0.35 0.35" diffuse="0.35 0.35 0.35" specular="0 0 0"/>
  </visual>
  <default><geom contype="0" conaffinity="0"/></default>
  <worldbody>
    <light directional="true" pos="{_f(cx, cy, 10)}" dir="0.3 0.2 -1" diffuse="0.45 0.45 0.45"
           specular="0 0 0" castshadow="false"/>
    <light directional="true" pos="{_f(cx, cy, 10)}" dir="-0.3 -0.4 -1" diffuse="0.2 0.2 0.2"
           specular="0 0 0" castshadow="false"/>
    <body name="camera" mocap="true" pos="{_f(cx, cy, CAMERA_HEIGHT_M)}">
      <camera name="camera" fovy="{fovy!r}"/>
    </body>
    {chr(10).join('    ' + g for g in geoms).lstrip()}
  </worldbody>
</mujoco>
"""
    return xml, ids


class SceneRenderer:
    """Renders :class:`RgbdFrame` s of one scene from any robot pose (see the module docstring).

    ``antialias`` turns on 4x multisampling of the colour image (depth and ids are
    never blended); it halves the frame rate on a CPU (Mesa llvmpipe) renderer.
    """

    def __init__(self, scene: Scene, width: int = 640, height: int = 480,
                 hfov_deg: float = HFOV_DEG, *, antialias: bool = False) -> None:
        if width <= 0 or height <= 0:
            raise ValueError(f"image size must be positive, got {width}x{height}")
        self._gl: Any = None
        self._con: Any = None
        mj = self._mj = _mujoco()
        self.scene, self.width, self.height, self.hfov_deg = scene, width, height, hfov_deg
        self.intrinsics = pinhole(width, height, hfov_deg)
        xml, geom_ids = build_mjcf(scene, width, height, hfov_deg, antialias)
        self.model = mj.MjModel.from_xml_string(xml)
        self._data = mj.MjData(self.model)
        self._geom_ids = np.asarray(geom_ids, dtype=np.int32)
        self._mjv_scene = mj.MjvScene(self.model, maxgeom=self.model.ngeom + 16)
        self._option = mj.MjvOption()
        self._camera = mj.MjvCamera()
        self._camera.type = mj.mjtCamera.mjCAMERA_FIXED
        self._camera.fixedcamid = 0
        self._rect = mj.MjrRect(0, 0, width, height)
        try:
            self._gl = mj.GLContext(width, height)
            self._gl.make_current()
            self._con = mj.MjrContext(self.model, mj.mjtFontScale.mjFONTSCALE_50.value)
        except Exception as exc:
            self.close()
            raise RuntimeError(
                f"cannot create an OpenGL context (MUJOCO_GL={os.environ.get('MUJOCO_GL')!r}): "
                f"{exc}. Headless Linux needs MUJOCO_GL=egl set before mujoco is first imported "
                "and the EGL/Mesa libraries (apt-get install libegl1 libgl1-mesa-dri libgles2)"
            ) from exc
        mj.mjr_setBuffer(mj.mjtFramebuffer.mjFB_OFFSCREEN.value, self._con)
        if self._con.currentBuffer != mj.mjtFramebuffer.mjFB_OFFSCREEN.value:
            raise RuntimeError("MuJoCo has no offscreen framebuffer on this OpenGL context")
        # Reversed Z: 1 at the near plane, 0 at the far one (what linearize() expects).
        self._con.readDepthMap = mj.mjtDepthMap.mjDEPTH_ZEROFAR
        # Read-back buffers, bottom row first as OpenGL delivers them.
        self._rgb_gl = np.empty((height, width, 3), np.uint8)
        self._seg_gl = np.empty((height, width, 3), np.uint8)
        self._depth_gl = np.empty((height, width), np.float32)
        self._code = np.empty((height, width), np.int32)
        self._tmp = np.empty((height, width), np.int32)
        extent = float(self.model.stat.extent)
        self._near = float(self.model.vis.map.znear) * extent
        self._far = float(self.model.vis.map.zfar) * extent

    # -- rendering ---------------------------------------------------------------------------

    def _place_camera(self, x: float, y: float, yaw: float) -> None:
        mj, d = self._mj, self._data
        c, s = math.cos(yaw), math.sin(yaw)
        # MuJoCo camera axes in the world (columns): x right, y up, z backwards.
        rot = np.array([[s, 0.0, -c], [-c, 0.0, -s], [0.0, 1.0, 0.0]])
        quat = np.empty(4)
        mj.mju_mat2Quat(quat, rot.ravel())
        d.mocap_pos[0] = (x, y, CAMERA_HEIGHT_M)
        d.mocap_quat[0] = quat
        mj.mj_kinematics(self.model, d)
        mj.mj_camlight(self.model, d)
        mj.mjv_updateScene(self.model, d, self._option, None, self._camera,
                           mj.mjtCatBit.mjCAT_ALL.value, self._mjv_scene)

    def _segment_lut(self) -> np.ndarray:
        """Instance id per segmentation colour code (segid + 1); 0 for anything unknown."""
        scn = self._mjv_scene
        lut = np.zeros(scn.ngeom + 2, np.int32)
        geom_type = self._mj.mjtObj.mjOBJ_GEOM
        for i in range(scn.ngeom):
            g = scn.geoms[i]
            if g.segid >= 0 and g.objtype == geom_type and 0 <= g.objid < len(self._geom_ids):
                lut[g.segid + 1] = self._geom_ids[g.objid]
        return lut

    def linearize(self, raw: np.ndarray, out: np.ndarray) -> np.ndarray:
        """Metric z-depth from reversed-Z buffer values (1 near, 0 far), in float32.

        With OpenGL's perspective matrix the window depth is ``n (f - z) / (z (f - n))``
        for eye-space depth ``z`` in reversed-Z mode; solved for ``z``.
        """
        n, f = self._near, self._far
        np.multiply(raw, np.float32(f - n), out=out)
        out += np.float32(n)
        np.divide(np.float32(f * n), out, out=out)
        return out

    def render(self, x: float, y: float, yaw: float, *, seq: int = 0, stamp: float = 0.0,
               after_action: int = 0, odom_session: str = "", posed_at: Pose | None = None) -> RgbdFrame:
        """The frame a level camera at (x, y, ``CAMERA_HEIGHT_M``) sees looking along ``yaw``
        (``after_action``: the last command completed before it; ``odom_session``: the base's,
        see :class:`RgbdFrame`), posed where the robot believes it took it (``posed_at``, its
        odometry, as a camera service poses frames) or, without one, where it truly did."""
        if self._con is None:
            raise RuntimeError("render() after close()")
        mj = self._mj
        self._gl.make_current()
        self._place_camera(x, y, yaw)
        arrays = RgbdFrame.loan(self.height, self.width, instance_ids=True)
        scn, flags = self._mjv_scene, self._mjv_scene.flags
        # Lit pass: the colour image.
        mj.mjr_render(self._rect, scn, self._con)
        mj.mjr_readPixels(self._rgb_gl, None, self._rect, self._con)
        # Segmentation pass: flat colours that encode segid + 1, and the depth buffer.
        saved = flags.copy()
        flags[mj.mjtRndFlag.mjRND_SEGMENT] = 1
        flags[mj.mjtRndFlag.mjRND_IDCOLOR] = 1
        try:
            mj.mjr_render(self._rect, scn, self._con)
            mj.mjr_readPixels(self._seg_gl, self._depth_gl, self._rect, self._con)
        finally:
            np.copyto(flags, saved)
        # OpenGL rows run bottom-up; frames are top-down.
        np.copyto(arrays["rgb"], self._rgb_gl[::-1])
        depth = self.linearize(self._depth_gl[::-1], arrays["depth"])
        lo, hi = DEPTH_RANGE_M
        depth[(depth < lo) | (depth > hi)] = 0.0
        seg, code, tmp = self._seg_gl[::-1], self._code, self._tmp
        np.copyto(code, seg[..., 0], casting="unsafe")
        np.left_shift(seg[..., 1], 8, out=tmp, dtype=np.int32)
        code |= tmp
        np.left_shift(seg[..., 2], 16, out=tmp, dtype=np.int32)
        code |= tmp
        np.take(self._segment_lut(), code, out=arrays["instance_ids"], mode="clip")
        posed = Pose(x=x, y=y, yaw=yaw) if posed_at is None else posed_at
        return RgbdFrame(seq=seq, stamp=stamp, after_action=after_action, odom_session=odom_session,
                         intrinsics=self.intrinsics, camera_pose=camera_pose(posed.x, posed.y, posed.yaw), **arrays)

    # -- lifetime ----------------------------------------------------------------------------

    def close(self) -> None:
        """Free the OpenGL context; idempotent."""
        con, gl = self._con, self._gl
        self._con = self._gl = None
        if con is not None:
            if gl is not None:
                gl.make_current()
            con.free()
        if gl is not None:
            gl.free()

    def __enter__(self) -> SceneRenderer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __del__(self) -> None:
        try:
            self.close()
        except Exception:
            pass
