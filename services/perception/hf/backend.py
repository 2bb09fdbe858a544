"""The real-model backend: BLIP / BLIP-2 scores, GroundingDINO boxes, SAM masks."""

from __future__ import annotations

from collections.abc import Sequence

from services.perception.config import HfBackendConfig
from services.perception.hf.loading import DETECTOR, ITM, SEGMENTER, Placement, load_model
from services.perception.hf.models import GroundingDetector, ItmScorer, SamSegmenter
from shared.detections import Detection
from shared.messages import RgbdFrame


class HfBackend:
    name = "hf"

    def __init__(self, scorer: ItmScorer, detector: GroundingDetector, segmenter: SamSegmenter,
                 placement: Placement) -> None:
        self.scorer, self.detector, self.segmenter = scorer, detector, segmenter
        self.placement = placement

    @classmethod
    def load(cls, config: HfBackendConfig) -> HfBackend:
        """All three models from their local directories (every directory is checked first,
        so one start-up names every missing model rather than one per attempt)."""
        from services.perception.hf.loading import ModelFilesError, model_type

        problems = []
        for role, directory in ((ITM, config.itm_dir), (DETECTOR, config.detector_dir),
                                (SEGMENTER, config.segmenter_dir)):
            try:
                model_type(role, directory)
            except ModelFilesError as exc:
                problems.append(str(exc))
        if problems:
            raise ModelFilesError("\n".join(problems))
        placement = Placement.resolve(config.device, config.fp16)
        return cls(ItmScorer(load_model(ITM, config.itm_dir, placement), placement, config.prompt,
                             config.score),
                   GroundingDetector(load_model(DETECTOR, config.detector_dir, placement), placement,
                                     config.box_threshold, config.text_threshold, config.max_detections),
                   SamSegmenter(load_model(SEGMENTER, config.segmenter_dir, placement), placement),
                   placement)

    def score(self, frame: RgbdFrame, targets: Sequence[str]) -> dict[str, float]:
        return self.scorer(frame.rgb, targets)

    def detect(self, frame: RgbdFrame, targets: Sequence[str]) -> list[Detection]:
        boxes = self.detector(frame.rgb, targets)
        masks = self.segmenter(frame.rgb, [b.box for b in boxes])
        return [Detection(b.label, b.score, b.box, m) for b, m in zip(boxes, masks)]
