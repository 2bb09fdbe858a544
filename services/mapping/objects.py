"""The object map: where the detector has seen each target class, as a set of instances.

Every detection's mask is projected with the frame's depth into world points;
the median point is the detection's position (the median, not the mean, because
a mask's edge pixels often miss the object and hit the wall behind it). A
detection joins the nearest instance of its label within ``merge_distance_m``,
otherwise it starts a new one. The planner stops at an instance only once it is
*confirmed*: seen ``confirm_hits`` times with a best score of at least
``decision_threshold`` (one lucky frame is not enough).

Decisions (docs/design.md, "The object map"):

* Detections scoring below ``decision_threshold`` are ignored entirely: they do
  not create instances and do not count as hits, so the detector's low-score
  false positives never reach the map, however often they repeat.
* Association uses the distance in the floor plane (x, y): the map is top down,
  and the height of the median point depends on how much of an object a view
  shows (a fridge seen whole from afar vs. its lower half from close by).
* An instance's position is the hit-weighted running mean of its detections'
  positions; its score the best one seen.
* Negative evidence (an addition to the paper): every frame in which an
  instance's position is in view (inside the image, within ``view_range_m``,
  not behind something nearer in the depth image) counts as a *view* of it,
  whether or not the detector fired. Confirmation also needs
  ``hits >= min_hit_ratio * views``. A false positive that recurs now and then
  over hundreds of frames (the detector's rare confusions of related objects)
  would otherwise reach ``confirm_hits`` sooner or later and be stopped at,
  which costs the target; a real object is detected in most frames that see it
  up close. ``min_hit_ratio`` 0 switches this off.

This module knows nothing of Zenoh: the mapping service feeds it frames and
detections and publishes :meth:`ObjectMap.instances` in its snapshots.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Self

import numpy as np

from ovamos.services.mapping.config import MappingConfig
from ovamos.shared.detections import Detection, often_detected
from ovamos.shared.messages import ObjectInstance, RgbdFrame

__all__ = ["ObjectMap", "mask_points", "detection_position"]

_DEFAULTS = MappingConfig()  # the defaults live in the mapping config, and only there


def mask_points(mask: np.ndarray, frame: RgbdFrame, max_points: int = 2000) -> np.ndarray:
    """World points (N x 3) of the mask's pixels that have a valid depth reading.

    At most ``max_points`` pixels are used, evenly spaced in row-major order, so
    the same mask always gives the same points (and a large mask costs no more
    than a small one). Pixels with no reading (0, NaN, inf) are dropped first.
    """
    if mask.shape != frame.depth.shape:
        raise ValueError(f"mask shape {mask.shape} does not match the frame's depth "
                         f"{frame.depth.shape}")
    if max_points < 1:
        raise ValueError(f"max_points must be >= 1, got {max_points}")
    v, u = np.nonzero(mask)
    if v.size == 0:
        return np.empty((0, 3))
    # Metres as the rest of the map reads them: depth * depth_scale (1.0 on float32 frames).
    z = frame.depth[v, u].astype(np.float64) * frame.depth_scale
    ok = np.isfinite(z) & (z > 0)
    v, u, z = v[ok], u[ok], z[ok]
    if z.size > max_points:
        keep = np.linspace(0, z.size - 1, max_points).round().astype(np.int64)
        v, u, z = v[keep], u[keep], z[keep]
    k = frame.intrinsics
    cam = np.stack([(u - k.cx) / k.fx * z, (v - k.cy) / k.fy * z, z])  # optical frame, 3 x N
    pose = frame.pose_matrix
    return (pose[:3, :3] @ cam + pose[:3, 3:4]).T


def detection_position(detection: Detection, frame: RgbdFrame, max_points: int = 2000
                       ) -> np.ndarray | None:
    """The detection's world position (x, y, z): component-wise median of its mask's points.

    ``None`` when no mask pixel has a valid depth (nothing to place it with).
    The median of each coordinate lies within the range of the object's points
    when most of the mask is on the object, whatever a few edge pixels hit.
    """
    points = mask_points(np.asarray(detection.mask, dtype=bool), frame, max_points)
    if len(points) == 0:
        return None
    return np.median(points, axis=0)


@dataclass
class _Track:
    """One instance while it is being updated (``ObjectInstance`` is frozen)."""

    label: str
    position: np.ndarray  # x, y, z
    score: float
    hits: int
    views: int = 0


class ObjectMap:
    """Object instances per label, built from detections projected with depth (see module doc).

    ``merge_distance_m``: a detection within this floor-plane distance of an
    instance of its label is the same object. ``confirm_hits`` and
    ``decision_threshold``: when an instance counts as found; the threshold also
    filters detections (lower scores are ignored). ``max_points``: mask pixels
    projected per detection (evenly subsampled). ``min_hit_ratio`` and
    ``view_range_m``: the negative evidence (see the module doc). Every default is the
    mapping service's (:class:`~ovamos.services.mapping.config.MappingConfig`).
    """

    def __init__(self, merge_distance_m: float = _DEFAULTS.object_merge_distance_m,
                 confirm_hits: int = _DEFAULTS.object_confirm_hits,
                 decision_threshold: float = _DEFAULTS.decision_threshold, *, max_points: int = 2000,
                 min_hit_ratio: float = _DEFAULTS.object_min_hit_ratio,
                 view_range_m: float = _DEFAULTS.object_view_range_m,
                 occlusion_margin_m: float = 0.3) -> None:
        if not merge_distance_m > 0:
            raise ValueError(f"merge_distance_m must be > 0, got {merge_distance_m}")
        if confirm_hits < 1:
            raise ValueError(f"confirm_hits must be >= 1, got {confirm_hits}")
        if max_points < 1:
            raise ValueError(f"max_points must be >= 1, got {max_points}")
        self.merge_distance_m = float(merge_distance_m)
        self.confirm_hits = int(confirm_hits)
        self.decision_threshold = float(decision_threshold)
        self.max_points = int(max_points)
        self.min_hit_ratio = float(min_hit_ratio)
        self.view_range_m = float(view_range_m)
        self.occlusion_margin_m = float(occlusion_margin_m)
        self._tracks: list[_Track] = []  # creation order: the order instances() reports

    # -- updating ----------------------------------------------------------------------------

    def observe(self, frame: RgbdFrame, labels: Iterable[str]) -> None:
        """Count a view of every instance of ``labels`` (the classes the frame was searched
        for) whose position the frame sees: in the image, in range, not occluded."""
        wanted = set(labels)
        tracks = [t for t in self._tracks if t.label in wanted]
        if not tracks:
            return
        pose = frame.pose_matrix
        world = np.array([t.position for t in tracks])
        cam = (world - pose[:3, 3]) @ pose[:3, :3]  # rows: optical-frame points
        z = cam[:, 2]
        k = frame.intrinsics
        h, w = frame.depth.shape
        with np.errstate(divide="ignore", invalid="ignore"):
            u = np.floor(k.fx * cam[:, 0] / z + k.cx)
            v = np.floor(k.fy * cam[:, 1] / z + k.cy)
        inside = (z > 0) & (z <= self.view_range_m) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
        for track, ok, ui, vi, zi in zip(tracks, inside, u, v, z):
            if not ok:
                continue
            seen = float(frame.depth[int(vi), int(ui)]) * frame.depth_scale
            if seen <= 0 or seen >= zi - self.occlusion_margin_m:  # nothing nearer in the way
                track.views += 1

    def add(self, detections: Iterable[Detection], frame: RgbdFrame) -> list[ObjectInstance]:
        """Fuse one frame's detections; returns the instances they created or updated.

        One entry per detection that was used, in the detections' order, each
        as it stands after that detection. Detections below the decision
        threshold, with a non-finite score, or whose mask has no valid depth
        are skipped (and have no entry).
        """
        updated: list[ObjectInstance] = []
        for det in detections:
            score = float(det.score)
            if not math.isfinite(score) or score < self.decision_threshold:
                continue
            position = detection_position(det, frame, self.max_points)
            if position is None:
                continue
            track = self._nearest(det.label, position)
            if track is None:
                track = _Track(det.label, position, score, 1, 1)
                self._tracks.append(track)
            else:
                track.position = (track.position * track.hits + position) / (track.hits + 1)
                track.hits += 1
                track.score = max(track.score, score)
                track.views = max(track.views, track.hits)  # a hit is a view, seen or not by observe
            updated.append(self._instance(track))
        return updated

    def _nearest(self, label: str, position: np.ndarray) -> _Track | None:
        """The closest instance of ``label`` within the merge distance (floor plane), if any."""
        best, best_d = None, math.inf
        for track in self._tracks:  # creation order: ties go to the older instance
            if track.label != label:
                continue
            d = math.hypot(track.position[0] - position[0], track.position[1] - position[1])
            if d <= self.merge_distance_m and d < best_d:
                best, best_d = track, d
        return best

    # -- reading -----------------------------------------------------------------------------

    def _instance(self, track: _Track) -> ObjectInstance:
        x, y, z = (float(c) for c in track.position)
        confirmed = (often_detected(track.hits, track.views, self.confirm_hits, self.min_hit_ratio)
                     and track.score >= self.decision_threshold)
        return ObjectInstance(label=track.label, x=x, y=y, z=z, score=track.score,
                              hits=track.hits, views=track.views, confirmed=confirmed)

    def instances(self) -> tuple[ObjectInstance, ...]:
        """Every instance, in creation order (deterministic for the same inputs)."""
        return tuple(self._instance(t) for t in self._tracks)

    def confirmed(self, label: str) -> list[ObjectInstance]:
        """Confirmed instances of ``label``, most hits first (then best score, then oldest)."""
        found = [i for i in self.instances() if i.label == label and i.confirmed]
        return sorted(found, key=lambda i: (-i.hits, -i.score))  # stable: oldest first on ties

    def __len__(self) -> int:
        return len(self._tracks)

    # -- checkpoints -------------------------------------------------------------------------

    @classmethod
    def from_instances(cls, instances: Sequence[ObjectInstance],
                       merge_distance_m: float = _DEFAULTS.object_merge_distance_m,
                       confirm_hits: int = _DEFAULTS.object_confirm_hits,
                       decision_threshold: float = _DEFAULTS.decision_threshold, *,
                       max_points: int = 2000, **evidence: float) -> Self:
        """A map holding ``instances`` (e.g. a snapshot's ``objects``), in their order.

        ``confirmed`` is recomputed with this map's rule, not copied: the
        thresholds may have changed since the checkpoint was written.
        """
        obj_map = cls(merge_distance_m, confirm_hits, decision_threshold, max_points=max_points,
                      **evidence)
        for inst in instances:
            obj_map._tracks.append(_Track(inst.label, np.array([inst.x, inst.y, inst.z], float),
                                          float(inst.score), int(inst.hits), int(inst.views)))
        return obj_map
