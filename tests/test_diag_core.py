"""The diag services' cores: the synthetic camera and the traffic statistics.

The test pattern is how a user checks a deployment before a real camera is
attached, so it must be reproducible and geometrically plausible (the mapping
service projects its depth with its pose). The monitor's numbers are what
``ovamos status`` shows, so they are checked on hand-fed arrivals.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from ovamos.services.diag import testpattern as tp
from ovamos.services.diag.monitor import TrafficStats
from ovamos.shared.messages import RgbdFrame

SETTINGS = settings(max_examples=50, deadline=None)


def frame(seq: int = 0, *, seed: int = 0, width: int = 64, height: int = 48) -> RgbdFrame:
    return tp.pattern_frame(seq, 1.25, width=width, height=height, seed=seed)


# ---------------------------------------------------------------------------------------------
# Test pattern
# ---------------------------------------------------------------------------------------------


def test_same_seed_and_seq_give_the_same_frame() -> None:
    a, b = frame(5, seed=3), frame(5, seed=3)
    assert np.array_equal(a.rgb, b.rgb)
    assert a.depth.tobytes() == b.depth.tobytes()
    assert a.camera_pose == b.camera_pose and a.intrinsics == b.intrinsics
    assert a.rgb is not b.rgb  # separate buffers: publishing one cannot change the other


def test_another_seed_gives_other_noise() -> None:
    a, b = frame(5, seed=3), frame(5, seed=4)
    assert not np.array_equal(a.depth, b.depth)
    assert np.array_equal(a.rgb, b.rgb)  # the seed only drives the depth noise


def test_another_seq_moves_the_square_and_turns_the_camera() -> None:
    a, b = frame(0), frame(1)
    assert not np.array_equal(a.rgb, b.rgb)
    assert not np.array_equal(a.depth, b.depth)
    assert a.camera_pose != b.camera_pose
    assert (a.seq, b.seq) == (0, 1)


@SETTINGS
@given(st.integers(8, 96), st.integers(8, 96), st.integers(0, 10**6), st.integers(0, 2**32))
def test_frame_has_the_requested_shape_and_depth_range(width: int, height: int, seq: int, seed: int) -> None:
    f = tp.pattern_frame(seq, 2.5, width=width, height=height, seed=seed)
    assert f.rgb.shape == (height, width, 3) and f.rgb.dtype == np.uint8
    assert f.depth.shape == (height, width) and f.depth.dtype == np.float32
    assert f.instance_ids is None
    assert (f.seq, f.stamp) == (seq, 2.5)
    near, far = tp.DEPTH_RANGE_M
    assert (near, far) == (0.5, 5.0)
    noise = 0.1  # 10 sigma of the 1 cm noise
    assert f.depth.min() >= near - noise and f.depth.max() <= far + noise
    # A ramp: far at the top row, near at the bottom.
    rows = f.depth.mean(axis=1)
    assert rows[0] > far - noise and rows[-1] < near + noise
    # And it survives the wire.
    back = RgbdFrame.from_bytes(bytes(f.to_bytes()))
    assert back.depth.tobytes() == f.depth.tobytes() and np.array_equal(back.rgb, f.rgb)


@pytest.mark.parametrize("width,height", [(640, 480), (64, 48), (100, 10)])
def test_intrinsics_give_a_79_degree_horizontal_fov(width: int, height: int) -> None:
    k = frame(width=width, height=height).intrinsics
    assert math.degrees(2 * math.atan(width / 2 / k.fx)) == pytest.approx(79.0)
    assert k.fy == pytest.approx(k.fx)  # square pixels
    assert (k.cx, k.cy) == pytest.approx(((width - 1) / 2, (height - 1) / 2))


@pytest.mark.parametrize("seq", [0, 1, 17, 72, 500])
def test_camera_pose_is_a_level_camera_turning_in_place(seq: int) -> None:
    """world_T_camera: rotation orthonormal, optical axis along (cos yaw, sin yaw, 0), at 0.88 m."""
    pose = frame(seq).pose_matrix
    yaw = seq * math.radians(5.0)
    r, t = pose[:3, :3], pose[:3, 3]
    assert np.allclose(r @ r.T, np.eye(3)) and np.linalg.det(r) == pytest.approx(1.0)
    assert np.array_equal(pose[3], [0.0, 0.0, 0.0, 1.0])
    assert np.allclose(t, [0.0, 0.0, 0.88])
    z_cam = r @ [0.0, 0.0, 1.0]  # optical axis
    assert np.allclose(z_cam, [math.cos(yaw), math.sin(yaw), 0.0])
    assert np.allclose(r @ [0.0, 1.0, 0.0], [0.0, 0.0, -1.0])  # image down is world down
    assert np.allclose(r @ [1.0, 0.0, 0.0], [math.sin(yaw), -math.cos(yaw), 0.0])  # image right


def test_pixel_at_the_image_centre_projects_ahead_of_the_camera() -> None:
    """Back-projecting the centre pixel with the frame's own depth/pose lands in front, at camera height."""
    f = frame(0, width=65, height=49)
    k = f.intrinsics
    v, u = 24, 32
    assert (u, v) == (k.cx, k.cy)
    d = float(f.depth[v, u])
    point = f.pose_matrix @ [(u - k.cx) / k.fx * d, (v - k.cy) / k.fy * d, d, 1.0]
    assert point[:3] == pytest.approx([d, 0.0, 0.88])


# ---------------------------------------------------------------------------------------------
# Traffic statistics
# ---------------------------------------------------------------------------------------------


def test_rate_bandwidth_and_latency_of_a_steady_stream() -> None:
    stats = TrafficStats(window_s=5.0)
    for i in range(31):  # 10 Hz for 3 s, 1000 bytes each, latency 10..40 ms
        stats.observe("k", 1000, now=100.0 + i * 0.1, latency_s=0.010 + (i % 4) * 0.010)
    (row,) = stats.report(now=103.0)
    assert row.key == "k"
    assert row.messages == 31
    assert row.rate_hz == pytest.approx(10.0)
    assert row.mbytes_per_s == pytest.approx(1000 * 10 / 1e6)
    assert row.median_latency_ms == pytest.approx(20.0)


def test_only_the_window_counts_for_rates() -> None:
    """A burst long ago does not inflate today's rate; the message total keeps it."""
    stats = TrafficStats(window_s=2.0)
    for i in range(100):
        stats.observe("k", 50, now=i * 0.001)  # 1 kHz burst at t = 0
    for i in range(5):
        stats.observe("k", 200, now=10.0 + i * 0.5)  # 2 Hz later
    (row,) = stats.report(now=12.0)
    assert row.messages == 105
    assert row.rate_hz == pytest.approx(2.0)
    assert row.mbytes_per_s == pytest.approx(4 * 200 / 2.0 / 1e6)


def test_a_single_or_stale_arrival_has_no_rate() -> None:
    stats = TrafficStats(window_s=1.0)
    stats.observe("one", 10, now=5.0)
    stats.observe("old", 10, now=0.0)
    stats.observe("old", 10, now=0.5)
    rows = {r.key: r for r in stats.report(now=5.0)}
    assert set(rows) == {"one", "old"}
    for row in rows.values():
        assert row.rate_hz == 0.0 and row.mbytes_per_s == 0.0
        assert row.median_latency_ms is None
    assert rows["old"].messages == 2


def test_streams_are_reported_per_key_in_order() -> None:
    stats = TrafficStats()
    stats.observe("b", 1, now=0.0)
    stats.observe("a", 1, now=0.0, latency_s=0.5)
    stats.observe("b", 1, now=1.0)
    rows = stats.report(now=1.0)
    assert [r.key for r in rows] == ["a", "b"]
    assert rows[0].median_latency_ms == pytest.approx(500.0)
    assert rows[1].rate_hz == pytest.approx(1.0)
    assert TrafficStats().report(now=0.0) == []


def test_a_slow_stream_reads_its_rate_between_messages() -> None:
    stats = TrafficStats(window_s=5.0)
    for t in (0.0, 2.0, 4.0):
        stats.observe("slow", 10, now=t, latency_s=9.0 if t == 0.0 else 0.1)
    (row,) = stats.report(now=5.9)
    assert row.rate_hz == pytest.approx(0.5)


def test_latency_only_counts_the_window() -> None:
    stats = TrafficStats(window_s=1.0)
    stats.observe("k", 10, now=0.0, latency_s=9.0)
    stats.observe("k", 10, now=5.0, latency_s=0.1)
    stats.observe("k", 10, now=5.5, latency_s=0.3)
    (row,) = stats.report(now=5.5)
    assert row.median_latency_ms == pytest.approx(200.0)


def test_a_latency_below_zero_says_the_clocks_disagree() -> None:
    """A robot whose clock is 30 s ahead: the stamps are not a latency, and the report says so."""
    stats = TrafficStats(window_s=5.0)
    for i in range(5):
        stats.observe("k", 10, now=float(i), latency_s=-29.998)
    (row,) = stats.report(now=4.0)
    assert row.median_latency_ms == pytest.approx(-29998.0)
    assert "at least 29998 ms ahead" in row.latency_note and "ovamos doctor" in row.latency_note
    stats.observe("j", 10, now=4.0, latency_s=0.02)
    assert next(r for r in stats.report(now=4.0) if r.key == "j").latency_note == ""
