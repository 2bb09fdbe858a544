"""The real-model backend: BLIP / BLIP-2 scores, GroundingDINO boxes, SAM masks."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from ovamos.services.perception.backend import Job, Outcome, Seen
from ovamos.services.perception.config import HfBackendConfig
from ovamos.services.perception.hf.loading import (
    DETECTOR,
    ITM,
    SEGMENTER,
    Loaded,
    ModelFilesError,
    Placement,
    load_model,
    model_type,
)
from ovamos.services.perception.hf.models import Box, GroundingDetector, ItmScorer, SamSegmenter
from ovamos.shared.detections import Detection
from ovamos.shared.messages import RgbdFrame


class HfBackend:
    """Runs on loaded models; :meth:`load` is the one way service and tests get them from disk."""

    name = "hf"

    def __init__(self, itm: Loaded, detector: Loaded, segmenter: Loaded, placement: Placement,
                 config: HfBackendConfig) -> None:
        self.placement = placement
        self.scorer = ItmScorer(itm, placement, config.prompt, config.score)
        self.detector = GroundingDetector(detector, placement, config.box_threshold,
                                          config.text_threshold, config.max_detections)
        self.segmenter = SamSegmenter(segmenter, placement)

    def unknown_targets(self, targets: Sequence[str]) -> tuple[tuple[str, ...], str]:
        """An open vocabulary: any word is a target the models may see."""
        return (), ""

    @classmethod
    def load(cls, config: HfBackendConfig) -> HfBackend:
        """All three models from their local directories. Every directory is checked before
        any is loaded, so one start-up names every model that is missing."""
        roles = ((ITM, config.folder(config.itm_dir)), (DETECTOR, config.folder(config.detector_dir)),
                 (SEGMENTER, config.folder(config.segmenter_dir)))
        problems = []
        for role, directory in roles:
            try:
                model_type(role, directory)
            except ModelFilesError as exc:
                problems.append(str(exc))
        if problems:
            raise ModelFilesError("\n".join(problems))
        placement = Placement.resolve(config.device, config.fp16)
        itm, detector, segmenter = (load_model(role, directory, placement) for role, directory in roles)
        return cls(itm, detector, segmenter, placement, config)

    def score(self, frame: RgbdFrame, targets: Sequence[str]) -> dict[str, float]:
        return self.scorer(frame.rgb, targets)

    def detect(self, frame: RgbdFrame, targets: Sequence[str]) -> list[Detection]:
        return self._masked(frame.rgb, self.detector(frame.rgb, targets))

    def _masked(self, rgb: np.ndarray, boxes: list[Box]) -> list[Detection]:
        masks = self.segmenter(rgb, [b.box for b in boxes])
        return [Detection(b.label, b.score, b.box, m) for b, m in zip(boxes, masks)]

    def process(self, jobs: Sequence[Job], detect: bool) -> list[Outcome]:
        """Scores of every frame in one ITM pass and boxes in one GroundingDINO pass; masks per
        frame (SAM prompts each image with its own boxes, a different number per frame)."""
        images, targets = [j.frame.rgb for j in jobs], [j.targets for j in jobs]
        scores = self.scorer.batch(images, targets)
        boxes = self.detector.batch(images, targets) if detect else [[] for _ in jobs]
        return [Seen(s, self._masked(rgb, b) if b else []) for s, rgb, b in zip(scores, images, boxes)]
