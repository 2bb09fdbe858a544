"""Trajectory errors of one search episode: the true path against the path the robot believed.

Computed with evo, the field's tool, so the numbers mean what they mean in SLAM and odometry
papers. Poses are planar (x, y, yaw) in metres and radians (REP-103), lifted to SE(3) with z = 0.
The two sequences are aligned pose by pose (index i is the same instant), so no time association
is needed; the timestamps handed to evo are the index in seconds.

- ATE: evo's APE on the translation part, with no alignment (no Umeyama): both paths start at the
  same known start pose, and the drift away from it is what is measured, so aligning the estimate
  onto the truth would hide it.
- aligned ATE: the same after aligning the estimate onto the truth (rotation and translation in
  the plane, no scale: Umeyama's), as the TUM RGB-D benchmark defines ATE: the shape of the believed
  path, whatever turn of the whole map was made early. A map consistent with itself but turned
  about the start serves the search as well as an unturned one (goals, objects and the robot are
  all in it), and only this figure says so.
- RPE: the relative pose error between poses ``rpe_delta`` apart (consecutive, non-overlapping
  pairs: 0..d, d..2d, ...), its translation in metres and its rotation angle in degrees: the drift
  per stretch, whatever happened before it.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from pydantic import BaseModel

if TYPE_CHECKING:  # evo (and the scipy it loads, ~0.8 s) is imported where an error is computed
    from evo.core.metrics import PoseRelation
    from evo.core.trajectory import PoseTrajectory3D

Planar = tuple[float, float, float]


class TrajectoryErrors(BaseModel):
    """The errors of one estimated trajectory against the true one, rounded to 4 decimals."""

    ate_rmse_m: float
    ate_median_m: float
    ate_max_m: float
    ate_aligned_median_m: float = 0.0  # after alignment (see the module); 0 in lines written before it
    rpe_trans_median_m: float  # per rpe_delta poses; 0 when the run has fewer than rpe_delta + 1
    rpe_rot_median_deg: float  # per rpe_delta poses; 0 when the run has fewer than rpe_delta + 1
    poses: int


def trajectory_errors(true: Sequence[Planar], estimated: Sequence[Planar], rpe_delta: int = 10) -> TrajectoryErrors:
    """ATE (without and with alignment) and RPE over ``rpe_delta`` poses of ``estimated`` against ``true``.

    Raises ValueError when the sequences are empty or differ in length (they must be the same
    instants), or when ``rpe_delta`` is below 1."""
    if len(true) == 0 or len(estimated) == 0:
        raise ValueError(f"trajectory_errors needs poses: got {len(true)} true and {len(estimated)} estimated")
    if len(true) != len(estimated):
        raise ValueError(f"trajectories must be aligned pose by pose: {len(true)} true vs {len(estimated)} estimated")
    if rpe_delta < 1:
        raise ValueError(f"rpe_delta must be at least 1 pose, got {rpe_delta}")
    from evo.core.metrics import APE, PoseRelation, StatisticsType
    ref, est = _trajectory(true), _trajectory(estimated)
    ate = APE(PoseRelation.translation_part)
    ate.process_data((ref, est))
    aligned = APE(PoseRelation.translation_part)
    aligned.process_data((ref, _trajectory(_aligned(true, estimated))))
    rpe_trans = rpe_rot = 0.0
    if len(true) > rpe_delta:  # evo refuses a run with no pair at all
        rpe_trans = _rpe_median(ref, est, PoseRelation.translation_part, rpe_delta)
        rpe_rot = _rpe_median(ref, est, PoseRelation.rotation_angle_deg, rpe_delta)
    return TrajectoryErrors(ate_rmse_m=_round(ate.get_statistic(StatisticsType.rmse)),
                            ate_median_m=_round(ate.get_statistic(StatisticsType.median)),
                            ate_max_m=_round(ate.get_statistic(StatisticsType.max)),
                            ate_aligned_median_m=_round(aligned.get_statistic(StatisticsType.median)),
                            rpe_trans_median_m=_round(rpe_trans), rpe_rot_median_deg=_round(rpe_rot),
                            poses=len(true))


def _aligned(true: Sequence[Planar], estimated: Sequence[Planar]) -> list[Planar]:
    """``estimated`` turned and shifted in the plane onto ``true`` (least squares on the positions:
    Umeyama's without scale, in 2D; evo's own refuses a straight path, whose 3D covariance is
    degenerate). A path that never moved keeps its heading and is only shifted."""
    t, e = np.asarray(true, dtype=float), np.asarray(estimated, dtype=float)
    mt, me = t[:, :2].mean(axis=0), e[:, :2].mean(axis=0)
    a, b = e[:, :2] - me, t[:, :2] - mt
    cross = float(np.sum(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]))
    dot = float(np.sum(a * b))
    theta = math.atan2(cross, dot) if abs(cross) + abs(dot) > 1e-12 else 0.0
    c, s = math.cos(theta), math.sin(theta)
    xy = np.stack([c * a[:, 0] - s * a[:, 1], s * a[:, 0] + c * a[:, 1]], axis=1) + mt
    return [(float(x), float(y), float(yaw + theta)) for (x, y), yaw in zip(xy, e[:, 2])]


def write_tum(path: Path, poses: Sequence[Planar], stamps: Sequence[float] | None = None) -> None:
    """Write ``poses`` as a TUM trajectory file (``timestamp tx ty tz qx qy qz qw``), which evo's
    command line and most SLAM tools read; ``stamps`` default to the index in seconds."""
    if stamps is not None and len(stamps) != len(poses):
        raise ValueError(f"one stamp per pose: {len(stamps)} stamps for {len(poses)} poses")
    from evo.tools.file_interface import write_tum_trajectory_file
    write_tum_trajectory_file(path, _trajectory(poses, stamps))


def _trajectory(poses: Sequence[Planar], stamps: Sequence[float] | None = None) -> PoseTrajectory3D:
    """Planar poses as evo's SE(3) trajectory: z = 0, yaw as a rotation about z. A NaN would come
    out as a NaN error that compares false with everything, so it is refused here."""
    from evo.core.trajectory import PoseTrajectory3D
    planar = np.asarray(poses, dtype=float)
    if planar.ndim != 2 or planar.shape[0] == 0 or planar.shape[1] != 3:
        raise ValueError(f"poses must be a non-empty sequence of (x, y, yaw), got shape {planar.shape}")
    if not np.isfinite(planar).all():
        raise ValueError("poses must be finite")
    zeros = np.zeros(len(planar))
    xyz = np.column_stack((planar[:, 0], planar[:, 1], zeros))
    half = planar[:, 2] / 2
    quat_wxyz = np.column_stack((np.cos(half), zeros, zeros, np.sin(half)))
    times = np.arange(len(planar), dtype=float) if stamps is None else np.asarray(stamps, dtype=float)
    return PoseTrajectory3D(positions_xyz=xyz, orientations_quat_wxyz=quat_wxyz, timestamps=times)


def _rpe_median(ref: PoseTrajectory3D, est: PoseTrajectory3D, relation: PoseRelation, delta: int) -> float:
    from evo.core.metrics import RPE, StatisticsType
    from evo.core.units import Unit
    rpe = RPE(relation, delta=delta, delta_unit=Unit.frames, all_pairs=False)
    rpe.process_data((ref, est))
    return float(rpe.get_statistic(StatisticsType.median))


def _round(value: float) -> float:
    """4 decimals, as a plain float (evo hands back numpy scalars)."""
    return round(float(value), 4)
