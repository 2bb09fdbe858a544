"""The RealSense backend through the real pyrealsense2 SDK, without a camera.

Frames rendered by the simulator go into the SDK's own ``software_device``
(:class:`ovamos.services.camera.software_device.SoftwareCamera`); the backend reads them
through the SDK's syncer, ``rs.align`` and its conversion, as it reads a D4xx.
The same device is recorded with ``rs.recorder`` and played back by the file
backend through ``rs.pipeline``.
"""

from __future__ import annotations

import math
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from scipy.ndimage import maximum_filter, minimum_filter

from ovamos.services.camera.capture import CameraError, CapturedFrame
from ovamos.services.camera.file import FileBackend, FileConfig, RecordingEnded
from ovamos.services.camera.oakd import OakdBackend, OakdConfig
from ovamos.services.camera.realsense import RealSenseBackend, RealSenseConfig
from ovamos.services.camera.software_device import SoftwareCamera
from ovamos.shared.messages import Intrinsics
from tests.sim_scenes import two_rooms

pytestmark = pytest.mark.system  # processes, routers, browsers or real-time devices: make test-all

W, H, FPS = 160, 120, 30
SCALE = 0.001


@pytest.fixture(scope="module")
def rendered() -> tuple[list[tuple[np.ndarray, np.ndarray]], Intrinsics]:
    """Six views of the two-room house as (rgb8, z16 in millimetres), and the intrinsics."""
    from ovamos.world.render import SceneRenderer

    with SceneRenderer(two_rooms(), W, H) as renderer:
        frames = [renderer.render(1.5, 2.0, i * math.pi / 3) for i in range(6)]
        intrinsics = renderer.intrinsics
    pairs = [(f.rgb.copy(), np.round(f.depth / SCALE).astype(np.uint16)) for f in frames]
    return pairs, intrinsics


def _backend(camera: SoftwareCamera, **config: object) -> RealSenseBackend:
    return RealSenseBackend(RealSenseConfig(width=W, height=H, fps=FPS, warmup_frames=0, **config),
                            source=camera)


def _index(frame: CapturedFrame, first: int = 0) -> int:
    """Which pushed frame this is: SoftwareCamera stamps frame n at n / fps seconds."""
    return round(frame.device_time_s * FPS) - first


def _feed(camera: SoftwareCamera, backend: RealSenseBackend,
          pairs: list[tuple[np.ndarray, np.ndarray]], first: int = 0, period_s: float = 0.0
          ) -> list[CapturedFrame]:
    """Push each pair (``period_s`` after reading the previous one) and read what comes out
    (the syncer's first pair comes out split)."""
    out = []
    for i, (rgb, depth) in enumerate(pairs):
        if i:
            time.sleep(period_s)
        camera.push(rgb, depth, frame_number=first + i)
        frame = backend.read(1.0)
        if frame is not None:
            out.append(frame)
    return out


def _assert_aligned_like_source(aligned: np.ndarray, source: np.ndarray) -> None:
    """Depth aligned to a colour camera with the same intrinsics and extrinsics is the source
    depth, up to the SDK's rasterisation: rs.align paints each depth pixel's footprint
    (its corners projected and rounded) into the colour image, so a few pixels stay empty
    (0: 2-6 % of them in these views) and, on surfaces seen at a slant, a few take a
    neighbour's value."""
    assert aligned.shape == source.shape and aligned.dtype == np.uint16
    out, src = aligned.astype(np.int64), source.astype(np.int64)
    valid = out > 0
    assert valid[src > 0].mean() > 0.9  # ~2-6 % holes, scattered
    same = np.abs(out - src) <= 1
    assert same[valid].mean() > 0.98
    lo, hi = minimum_filter(src, 3) - 1, maximum_filter(src, 3) + 1
    assert ((out >= lo) & (out <= hi))[valid].all(), "a depth value moved beyond its neighbours"


def test_software_device_frames_come_out_aligned(rendered) -> None:
    pairs, intrinsics = rendered
    camera = SoftwareCamera(W, H, intrinsics, depth_scale=SCALE, fps=FPS)
    backend = _backend(camera)
    backend.start()
    try:
        frames = _feed(camera, backend, pairs)
    finally:
        backend.stop()
    # The syncer sees each stream first with the first pair, which it cannot match yet.
    assert [_index(f) for f in frames] == list(range(1, len(pairs)))
    assert backend.skipped_incomplete == 2
    for frame in frames:
        rgb, depth = pairs[_index(frame)]
        assert frame.rgb.dtype == np.uint8 and frame.rgb.shape == (H, W, 3)
        np.testing.assert_array_equal(frame.rgb, rgb)
        _assert_aligned_like_source(frame.depth, depth)
        assert frame.depth_scale == pytest.approx(SCALE, rel=1e-6)
        for name in ("fx", "fy", "cx", "cy"):  # the SDK stores them as float32
            expected = getattr(intrinsics, name)
            assert getattr(frame.intrinsics, name) == pytest.approx(expected, rel=1e-6)
    device_times = [f.device_time_s for f in frames]
    assert device_times == sorted(device_times) and len(set(device_times)) == len(frames)
    assert device_times[1] - device_times[0] == pytest.approx(1 / FPS)
    host_times = [f.host_time_s for f in frames]
    assert host_times == sorted(host_times) and host_times[-1] <= time.monotonic()


def test_align_uses_the_extrinsics(rendered) -> None:
    """With a 5 cm baseline between depth and colour, rs.align re-projects: depth moves by the
    parallax (fx * b / z pixels), so it is no longer the source image."""
    pairs, intrinsics = rendered
    rotation = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
    camera = SoftwareCamera(W, H, intrinsics, depth_to_color=(rotation, [0.05, 0.0, 0.0]))
    backend = _backend(camera)
    backend.start()
    try:
        frame = _feed(camera, backend, pairs[:2])[-1]
    finally:
        backend.stop()
    src, out = pairs[_index(frame)][1].astype(np.int64), frame.depth.astype(np.int64)
    valid = out > 0
    assert valid.mean() > 0.8
    assert (np.abs(out - src) <= 1)[valid].mean() < 0.9
    # A point at depth z in the depth camera lands fx * 0.05 / z pixels to the right in colour.
    row = H // 2
    cols = np.nonzero(valid[row, W // 4:3 * W // 4])[0] + W // 4
    shift = np.median(np.round(intrinsics.fx * 0.05 / (out[row, cols] * SCALE)))
    assert shift >= 1
    np.testing.assert_allclose(out[row, cols], src[row, cols - int(shift)], rtol=0.05)


def test_depth_filters_run_in_the_sdk(rendered) -> None:
    """Filters change depth before the alignment (smoothed, holes filled), not its units."""
    pairs, intrinsics = rendered
    outputs = {}
    for filtered in (False, True):
        camera = SoftwareCamera(W, H, intrinsics)
        backend = _backend(camera, spatial=filtered, temporal=filtered, hole_filling=filtered)
        backend.start()
        try:
            outputs[filtered] = _feed(camera, backend, pairs[:4])
        finally:
            backend.stop()
    assert len(outputs[True]) == len(outputs[False]) == 3
    for plain, smooth in zip(outputs[False], outputs[True]):
        assert smooth.depth.dtype == np.uint16 and smooth.depth.shape == (H, W)
        both = (plain.depth > 0) & (smooth.depth > 0)
        diff = np.abs(plain.depth.astype(np.int64) - smooth.depth.astype(np.int64))[both]
        relative = diff / plain.depth[both]
        assert both.mean() > 0.9 and np.median(relative) < 0.01  # the same scene, in millimetres
        assert (diff > 1).mean() > 0.01  # but smoothed


def test_silence_is_none_and_frames_come_back_without_a_new_backend(rendered) -> None:
    pairs, intrinsics = rendered
    camera = SoftwareCamera(W, H, intrinsics)
    backend = _backend(camera)
    backend.start()
    try:
        assert _feed(camera, backend, pairs[:3])
        start = time.monotonic()
        assert backend.read(0.3) is None  # the core turns silences into "no camera frames"
        assert 0.25 <= time.monotonic() - start < 1.0
        again = _feed(camera, backend, pairs[3:], first=3)
        assert again and [_index(f) for f in again] == list(range(3, 3 + len(again)))
        np.testing.assert_array_equal(again[-1].rgb, pairs[_index(again[-1])][0])
        # start() again (the recovery path after a fault): streaming resumes.
        backend.start()
        assert _feed(camera, backend, pairs[:3], first=100)
    finally:
        backend.stop()
    with pytest.raises(CameraError, match="before start"):
        backend.read(0.1)


def test_warmup_frames_are_dropped(rendered) -> None:
    pairs, intrinsics = rendered
    camera = SoftwareCamera(W, H, intrinsics)
    backend = RealSenseBackend(RealSenseConfig(width=W, height=H, warmup_frames=2), source=camera)
    backend.start()
    try:
        frames = _feed(camera, backend, pairs)
    finally:
        backend.stop()
    assert [_index(f) for f in frames] == [3, 4, 5]


def _record(path: Path, pairs, intrinsics: Intrinsics) -> list[CapturedFrame]:
    """Record the software device, fed at its frame rate, while the backend reads it live;
    return the live frames. (The recording keeps the host time each frame arrived at, and
    that is the rate real-time playback replays.)"""
    camera = SoftwareCamera(W, H, intrinsics, depth_scale=SCALE, fps=FPS)
    camera.start_recording(path)
    backend = _backend(camera)
    backend.start()
    try:
        live = _feed(camera, backend, pairs, period_s=1 / FPS)
    finally:
        backend.stop()
        camera.stop_recording()
    return live


@pytest.fixture(scope="module")
def recording(rendered, tmp_path_factory) -> tuple[Path, list[CapturedFrame]]:
    pairs, intrinsics = rendered
    path = tmp_path_factory.mktemp("rec") / "two_rooms.db3"
    live = _record(path, pairs, intrinsics)
    assert path.is_file() and path.stat().st_size > 0
    return path, live


def _play(backend: FileBackend) -> list[CapturedFrame]:
    played = []
    backend.start()
    try:
        with pytest.raises(RecordingEnded, match="end of recording"):
            while True:
                frame = backend.read(2.0)
                assert frame is not None, "a playing recording went silent"
                played.append(frame)
        assert backend.ended
    finally:
        backend.stop()
    return played


@pytest.mark.parametrize("rate", ["max", "realtime"])
def test_recording_plays_back_the_same_frames(rendered, recording, rate: str) -> None:
    pairs, intrinsics = rendered
    path, live = recording
    backend = FileBackend(FileConfig(path=path, rate=rate))
    played = _play(backend)
    indices = [_index(f) for f in played]
    if rate == "max":
        # The recorder took each sensor's frames before the syncer, so even the first pair is
        # there, and a playback that waits for its consumer loses none.
        assert indices == list(range(len(pairs)))
        # As fast as consumed: the recording spans over a second (its first read waited for
        # the syncer's split start-up pair), its playback a small part of that.
        assert played[-1].host_time_s - played[0].host_time_s < 0.5
    else:
        # Real time is a camera: frames are lost, not queued, when the consumer or the start is
        # late (the SDK's real-time playback loses its first frame or two in about one start
        # out of ten here, before the first read); never the order, and frames come at the
        # recorded pace.
        assert indices == sorted(set(indices)) and indices[-1] == len(pairs) - 1
        assert len(indices) >= len(pairs) // 2
        # (over the whole run: one frame delivered late is followed by the next at once)
        first, last = played[0], played[-1]
        assert last.host_time_s - first.host_time_s > 0.5 * (last.device_time_s - first.device_time_s)
    by_index = {_index(f): f for f in live}
    for frame in played:
        rgb, depth = pairs[_index(frame)]
        np.testing.assert_array_equal(frame.rgb, rgb)
        _assert_aligned_like_source(frame.depth, depth)
        if _index(frame) in by_index:  # same input, same SDK alignment: the same pixels
            np.testing.assert_array_equal(frame.depth, by_index[_index(frame)].depth)
        assert frame.intrinsics == live[0].intrinsics
        assert frame.depth_scale == pytest.approx(SCALE, rel=1e-6)


def test_a_recording_plays_again_after_its_end(recording) -> None:
    path, _ = recording
    backend = FileBackend(FileConfig(path=path, rate="max"))
    first, second = _play(backend), _play(backend)
    assert [f.device_time_s for f in first] == [f.device_time_s for f in second]
    with pytest.raises(CameraError, match="before start"):
        backend.read(0.1)


def test_recording_errors_are_clear(tmp_path: Path) -> None:
    missing = FileBackend(FileConfig(path=tmp_path / "nope.db3"))
    with pytest.raises(CameraError, match="recording not found"):
        missing.start()
    for name in ("garbage.db3", "garbage.bag"):
        bad = tmp_path / name
        bad.write_bytes(b"not a recording\n")
        with pytest.raises(CameraError, match=f"cannot read recording .*{name}"):
            FileBackend(FileConfig(path=bad)).start()
    other = tmp_path / "frames.mp4"
    other.write_bytes(b"x")
    with pytest.raises(CameraError, match="not a RealSense recording"):
        FileBackend(FileConfig(path=other)).start()
    camera = SoftwareCamera(W, H, Intrinsics(fx=100, fy=100, cx=80, cy=60))
    with pytest.raises(CameraError, match=r"\.db3"):
        camera.start_recording(tmp_path / "out.bag")


def test_a_missing_camera_is_a_clear_error() -> None:
    """No RealSense is plugged in here: asking for one by serial says so, and names it."""
    backend = RealSenseBackend(RealSenseConfig(serial="123456789012"))
    with pytest.raises(CameraError, match="no RealSense device.*123456789012"):
        backend.start()
    with pytest.raises(CameraError, match="no RealSense device connected"):
        RealSenseBackend(RealSenseConfig()).start()
    backend.stop()  # nothing started: still fine


def test_a_missing_sdk_is_a_camera_error(monkeypatch, tmp_path: Path) -> None:
    """The configs and backends load without pyrealsense2 (ovamos and the core read them on
    machines without it); starting one says what to install."""
    monkeypatch.setitem(sys.modules, "pyrealsense2", None)  # `import pyrealsense2` fails
    recording = FileConfig(path=tmp_path / "x.db3")
    for backend in (RealSenseBackend(RealSenseConfig()), FileBackend(recording)):
        with pytest.raises(CameraError, match=r"pyrealsense2 is not usable.*ovamos\[camera\]"):
            backend.start()


def test_oakd_is_refused_with_the_reason() -> None:
    backend = OakdBackend(OakdConfig())
    with pytest.raises(CameraError, match="oakd backend is not implemented.*hardware-free"):
        backend.start()
    with pytest.raises(CameraError, match="not implemented"):
        backend.read(0.1)
    backend.stop()


def test_camera_benchmark_reports_its_keys() -> None:
    from ovamos.bench.camera import run_benchmark

    result = run_benchmark(frames=3, runs=1)
    assert result["fps_640x480"] > 0
    assert set(result["ms_per_frame"]) >= {"align", "encode", "publish"}
    assert all(v > 0 for k, v in result["ms_per_frame"].items() if k != "sync")
    assert result["ms_per_frame"]["sync"] >= 0
