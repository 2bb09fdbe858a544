"""Simulated perception: value scores and detections computed from a rendered frame only.

It stands in for BLIP (value score) and GroundingDINO + SAM (detections) when
the robot is simulated. Its only inputs are what a camera delivers plus what
a real detector "knows": the frame's pixels of instance ids (which object or
room floor each pixel shows), their depth, the class of each *visible* id
and the object prior. Nothing hidden (objects out of view, their true poses)
is read, so a search cannot cheat through it.

Models, every constant in :class:`SimPerceptionConfig`:

* value score per target = ``base + gain * r + noise``, where ``r`` is the
  prior's relatedness of the target to the visible classes and room types (1
  when the target itself is visible), clipped to [0, 1]: BLIP ITM-like values.
* a visible target instance is detected with probability
  ``p_max * visible_fraction^occlusion_power * distance_term * size_term``;
  ``visible_fraction`` compares its visible pixels with what its class size
  would cover unoccluded at that depth; detection score rises with that probability.
* false positives: a visible instance of a class related to a target is
  reported as that target with probability ``fp_rate * cooccurrence``.
"""

from __future__ import annotations

import math
import zlib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from ovamos.shared.detections import Detection
from ovamos.shared.messages import RgbdFrame
from ovamos.world.prior import ObjectPrior
from ovamos.world.scene import Scene


class SimPerceptionConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")
    seed: int = 0
    min_pixels: int = Field(default=20, ge=1, description="fewer visible pixels = not seen at all")
    score_base: float = 0.15
    score_gain: float = 0.35
    score_noise: float = Field(default=0.03, ge=0)
    p_max: float = Field(default=0.95, ge=0, le=1)
    occlusion_power: float = Field(default=1.0, ge=0)
    reliable_distance_m: float = Field(default=2.5, gt=0, description="no distance penalty below")
    distance_falloff_m: float = Field(default=2.0, gt=0)
    full_size_pixels: int = Field(default=400, gt=0, description="size term saturates here")
    fp_rate: float = Field(default=0.05, ge=0, le=1)
    fp_min_cooccurrence: float = Field(default=0.3, ge=0, le=1)
    detection_score_range: tuple[float, float] = (0.35, 0.9)
    reference_image: tuple[int, int] = Field(
        default=(640, 480), description="pixel counts above are for this image size (the paper's "
                                        "camera); other sizes scale them, so the detector does not "
                                        "get worse on a smaller render of the same view")


@dataclass(frozen=True)
class FrameLabels:
    """What each id in an instance-id image is: the simulator's equivalent of pixel semantics."""

    classes: Mapping[int, str]  # object id -> class
    rooms: Mapping[int, str]    # floor id (-(room id + 1)) -> room type
    scene_seed: int = 0         # seeds the noise: episodes in other scenes must not share draws

    @classmethod
    def of(cls, scene: Scene) -> FrameLabels:
        return cls({o.id: o.cls for o in scene.objects}, {-(r.id + 1): r.type for r in scene.rooms},
                   scene.seed or 0)


@dataclass(frozen=True)
class _Visible:
    id: int
    cls: str
    pixels: int
    depth: float
    box: tuple[int, int, int, int]


class SimPerception:
    """Deterministic per (seed, scene, frame seq): replaying a frame gives the same output."""

    def __init__(self, labels: FrameLabels, prior: ObjectPrior,
                 config: SimPerceptionConfig | None = None) -> None:
        self.labels, self.prior = labels, prior
        self.config = config or SimPerceptionConfig()
        self._last: tuple[RgbdFrame, tuple[list[_Visible], list[str]]] | None = None

    def _require_ids(self, frame: RgbdFrame) -> np.ndarray:
        if frame.instance_ids is None:
            raise ValueError("the sim perception backend needs simulated frames (with instance ids); "
                             "this frame has none, use a real-model backend for camera frames")
        return frame.instance_ids

    def _visible(self, frame: RgbdFrame) -> tuple[list[_Visible], list[str]]:
        """Kept for the last frame: ``score`` and ``detect`` of one frame both need it, and the scan
        is most of their cost."""
        if self._last is None or self._last[0] is not frame:
            self._last = (frame, self._scan(frame))
        return self._last[1]

    def _scan(self, frame: RgbdFrame) -> tuple[list[_Visible], list[str]]:
        ids = self._require_ids(frame)
        values, counts = np.unique(ids, return_counts=True)
        depth = frame.depth.astype(np.float32) * np.float32(frame.depth_scale)
        objects, rooms = [], []
        scale = self._pixel_scale(frame)
        for value, count in zip(values.tolist(), counts.tolist()):
            if count < self.config.min_pixels * scale:
                continue
            if value < 0 and value in self.labels.rooms:
                rooms.append(self.labels.rooms[value])
            elif value > 0 and value in self.labels.classes:
                rows, cols = np.nonzero(ids == value)
                d = depth[rows, cols]
                d = d[d > 0]
                objects.append(_Visible(value, self.labels.classes[value], count,
                                        float(np.median(d)) if d.size else math.inf,
                                        (int(cols.min()), int(rows.min()),
                                         int(cols.max()) + 1, int(rows.max()) + 1)))
        return objects, rooms

    def visible_classes(self, frame: RgbdFrame) -> set[str]:
        """The object classes in view with enough pixels to be seen at all: what a benchmark
        compares with the detections to tell an unseen target from a missed one."""
        return {o.cls for o in self._visible(frame)[0]}

    def _pixel_scale(self, frame: RgbdFrame) -> float:
        w, h = self.config.reference_image
        return frame.rgb.shape[0] * frame.rgb.shape[1] / (w * h)

    def _rng(self, frame: RgbdFrame, target: str, stream: int) -> np.random.Generator:
        """Per (seed, scene, frame, target, score or detect). A target's outputs do not depend on
        which other targets are asked for (the services may still ask for a target found a moment
        ago). The scene is in the seed because the frame seq alone would give every episode that
        searches for a target the same false detections at the same step."""
        return np.random.default_rng([self.config.seed, self.labels.scene_seed, frame.seq,
                                      zlib.crc32(target.encode()), stream])

    def score(self, frame: RgbdFrame, targets: Sequence[str]) -> dict[str, float]:
        """Value score per target, in a BLIP-like range."""
        objects, rooms = self._visible(frame)
        classes = [o.cls for o in objects]
        c = self.config
        return {t: float(np.clip(c.score_base + c.score_gain * self.prior.relatedness(t, classes, rooms)
                                 + self._rng(frame, t, 0).normal(0.0, c.score_noise), 0.0, 1.0))
                for t in targets}

    def detect_probability(self, frame: RgbdFrame, obj: _Visible) -> float:
        c = self.config
        k = frame.intrinsics
        sx, sy, sz = self.prior[obj.cls].size
        expected = (k.fx * max(sx, sy) / obj.depth) * (k.fy * sz / obj.depth) if math.isfinite(
            obj.depth) else obj.pixels
        visible_fraction = min(1.0, obj.pixels / max(expected, 1.0))
        distance = math.exp(-max(0.0, obj.depth - c.reliable_distance_m) / c.distance_falloff_m)
        size = min(1.0, obj.pixels / (c.full_size_pixels * self._pixel_scale(frame)))
        return c.p_max * visible_fraction ** c.occlusion_power * distance * size

    def detect(self, frame: RgbdFrame, targets: Sequence[str]) -> list[Detection]:
        """Detections of the targets (true ones and some false positives), with masks."""
        objects, _ = self._visible(frame)
        ids = self._require_ids(frame)
        c = self.config
        lo, hi = c.detection_score_range
        found: list[Detection] = []
        for target in targets:
            rng = self._rng(frame, target, 1)
            for obj in objects:
                if obj.cls == target:
                    p = self.detect_probability(frame, obj)
                    score = lo + (hi - lo) * p
                else:
                    related = self.prior.cooccurrence(target, obj.cls) if obj.cls in self.prior else 0.0
                    if related < c.fp_min_cooccurrence:
                        continue
                    p = c.fp_rate * related
                    score = lo + (hi - lo) * 0.3 * rng.random()
                if rng.random() < p:
                    found.append(Detection(target, float(score), obj.box, ids == obj.id))
        return found
