"""Trajectory errors through evo: cases whose ATE and RPE are known by hand."""

from __future__ import annotations

import math
import statistics

import numpy as np
import pytest
from evo.tools.file_interface import read_tum_trajectory_file

from ovamos.bench.trajectory import Planar, trajectory_errors, write_tum

CURVE: list[Planar] = [(0.3 * i, math.sin(0.2 * i), 0.1 * i - 1.0) for i in range(31)]


def straight(n: int, step: float = 1.0) -> list[Planar]:
    return [(step * i, 0.0, 0.0) for i in range(n)]


def test_identical_trajectories_have_no_error() -> None:
    errors = trajectory_errors(CURVE, list(CURVE), rpe_delta=10)
    assert errors.model_dump() == {"ate_rmse_m": 0.0, "ate_median_m": 0.0, "ate_max_m": 0.0,
                                   "ate_aligned_median_m": 0.0, "rpe_trans_median_m": 0.0, "rpe_rot_median_deg": 0.0, "poses": 31}


def test_one_pose_has_no_error() -> None:
    errors = trajectory_errors([(1.0, 2.0, 0.5)], [(1.0, 2.0, 0.5)])
    assert errors.ate_max_m == errors.rpe_trans_median_m == errors.rpe_rot_median_deg == 0.0
    assert errors.poses == 1


def test_constant_offset_is_absolute_error_only() -> None:
    shifted = [(x, y + 0.1, yaw) for x, y, yaw in CURVE]
    errors = trajectory_errors(CURVE, shifted, rpe_delta=10)
    assert (errors.ate_rmse_m, errors.ate_median_m, errors.ate_max_m) == (0.1, 0.1, 0.1)
    # the relative motion is unchanged, in translation and in rotation
    assert errors.rpe_trans_median_m == pytest.approx(0.0, abs=1e-4)
    assert errors.rpe_rot_median_deg == pytest.approx(0.0, abs=1e-4)


def test_rotation_about_the_start_is_not_aligned_away() -> None:
    """The estimate turned 2 degrees about the start: pose i is off by i * 2 sin(1 deg); an
    Umeyama alignment would make this 0, so a non-zero ATE shows none is applied."""
    tilt = math.radians(2.0)
    true = straight(10)
    estimated = [(x * math.cos(tilt), x * math.sin(tilt), tilt) for x, _, _ in true]
    errors = trajectory_errors(true, estimated, rpe_delta=3)
    chord = 2 * math.sin(tilt / 2)
    assert errors.ate_max_m == pytest.approx(9 * chord, abs=1e-4)
    assert errors.ate_median_m == pytest.approx(4.5 * chord, abs=1e-4)
    assert errors.ate_rmse_m == pytest.approx(chord * math.sqrt(sum(i * i for i in range(10)) / 10), abs=1e-4)
    assert errors.ate_aligned_median_m == pytest.approx(0.0, abs=1e-4)  # its shape is the truth's
    # a constant rotation leaves every relative motion as it was
    assert errors.rpe_trans_median_m == pytest.approx(0.0, abs=1e-4)
    assert errors.rpe_rot_median_deg == pytest.approx(0.0, abs=1e-4)


def test_linear_yaw_drift_grows_the_error() -> None:
    """Dead reckoning with a yaw bias of 0.5 degrees per 1 m step along a straight line: the
    heading error grows linearly, so each stretch of d poses turns d * 0.5 degrees too far and
    ends sum(cos, sin of j * bias) away from where it should."""
    bias, delta, n = math.radians(0.5), 5, 41
    estimated: list[Planar] = [(0.0, 0.0, 0.0)]
    for _ in range(n - 1):
        x, y, yaw = estimated[-1]
        estimated.append((x + math.cos(yaw), y + math.sin(yaw), yaw + bias))
    true = straight(n)
    errors = trajectory_errors(true, estimated, rpe_delta=delta)
    drift = [math.hypot(x - i, y) for i, (x, y, _) in enumerate(estimated)]
    assert drift == sorted(drift)  # growing, so the last pose is the worst
    assert errors.ate_max_m == pytest.approx(drift[-1], abs=1e-4)
    assert errors.ate_median_m == pytest.approx(statistics.median(drift), abs=1e-4)
    assert errors.ate_rmse_m == pytest.approx(math.sqrt(statistics.fmean(d * d for d in drift)), abs=1e-4)
    # a curve is not a line, however it is turned: aligned, the error shrinks but stays
    assert 0.1 < errors.ate_aligned_median_m < errors.ate_median_m / 2
    stretch = (sum(math.cos(j * bias) for j in range(delta)) - delta, sum(math.sin(j * bias) for j in range(delta)))
    assert errors.rpe_trans_median_m == pytest.approx(math.hypot(*stretch), abs=1e-4)
    assert errors.rpe_rot_median_deg == pytest.approx(delta * 0.5, abs=1e-4)


def test_too_short_for_rpe_still_has_ate() -> None:
    errors = trajectory_errors(straight(10), [(x, y + 0.2, yaw) for x, y, yaw in straight(10)], rpe_delta=10)
    assert errors.ate_max_m == 0.2
    assert errors.rpe_trans_median_m == errors.rpe_rot_median_deg == 0.0


@pytest.mark.parametrize(("true", "estimated", "message"), [
    (straight(5), straight(4), "5 true vs 4 estimated"),
    ([], [], "needs poses"),
    (straight(3), [], "needs poses"),
])
def test_misaligned_or_empty_is_refused(true: list[Planar], estimated: list[Planar], message: str) -> None:
    with pytest.raises(ValueError, match=message):
        trajectory_errors(true, estimated)


def test_bad_poses_and_delta_are_refused() -> None:
    with pytest.raises(ValueError, match="finite"):
        trajectory_errors([(0.0, 0.0, 0.0), (math.nan, 0.0, 0.0)], straight(2))
    with pytest.raises(ValueError, match="rpe_delta"):
        trajectory_errors(straight(3), straight(3), rpe_delta=0)


def test_write_tum_round_trips_through_evo(tmp_path) -> None:
    path = tmp_path / "estimate.tum"
    write_tum(path, CURVE)
    back = read_tum_trajectory_file(path)
    assert np.allclose(back.timestamps, np.arange(len(CURVE)))
    assert np.allclose(back.positions_xyz, [(x, y, 0.0) for x, y, _ in CURVE])
    w, qx, qy, qz = back.orientations_quat_wxyz.T
    assert np.allclose(qx, 0) and np.allclose(qy, 0)
    assert np.allclose(2 * np.arctan2(qz, w), [yaw for _, _, yaw in CURVE])
    first = path.read_text().splitlines()[0].split(" ")
    assert len(first) == 8  # timestamp tx ty tz qx qy qz qw


def test_write_tum_keeps_given_stamps(tmp_path) -> None:
    path = tmp_path / "true.tum"
    stamps = [100.0, 100.25, 100.5]
    write_tum(path, straight(3), stamps)
    assert np.allclose(read_tum_trajectory_file(path).timestamps, stamps)
    with pytest.raises(ValueError, match="one stamp per pose"):
        write_tum(path, straight(3), stamps[:2])
