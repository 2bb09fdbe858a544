"""The three model stages of the hf backend: ITM scores, grounded boxes, box-prompted masks.

Each stage takes an RGB image (H x W x 3 uint8) and runs one batched forward
pass: all targets at once for scoring and detection, all boxes at once for
masks. Scoring and detection also take several images, each with its own
targets (frames of several robots), in one forward pass (:meth:`ItmScorer.batch`,
:meth:`GroundingDetector.batch`). They hold a loaded model and its processor and
know nothing of frames or Zenoh.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from ovamos.services.perception.hf.loading import Loaded, Placement, torch_and_transformers


def _to(batch: Any, placement: Placement) -> dict[str, Any]:
    """A processor's batch on the model's device; floating tensors (pixels) in its dtype."""
    moved = {}
    for key, value in batch.items():
        if hasattr(value, "to"):
            value = value.to(placement.device, placement.dtype) if value.is_floating_point() \
                else value.to(placement.device)
        moved[key] = value
    return moved


class ItmScorer:
    """BLIP / BLIP-2 image-text score of ``prompt`` for each target.

    ``itc`` is the cosine of the image and text embeddings (one image pass for
    every target); ``itm`` the match probability of the ITM head, which
    attends to the image per text, so the image is batched once per target.
    """

    # model_type -> (forward flag selecting the ITM head, output field)
    _API = {"blip": ("use_itm_head", "itm_score"),
            "blip-2": ("use_image_text_matching_head", "logits_per_image")}

    def __init__(self, loaded: Loaded, placement: Placement, prompt: str, mode: str) -> None:
        self.loaded, self.placement, self.prompt, self.mode = loaded, placement, prompt, mode

    def __call__(self, rgb: np.ndarray, targets: Sequence[str]) -> dict[str, float]:
        return self.batch([rgb], [targets])[0]

    def batch(self, images: Sequence[np.ndarray], targets: Sequence[Sequence[str]]) -> list[dict[str, float]]:
        """Scores of each image's own targets, all images in one forward pass.

        ``itc``: every image against the union of the prompts (one text pass, cosines of every
        pair, each image reads its own); ``itm``: one (image, prompt) pair per target of each image.
        """
        pairs = [(i, t) for i, image_targets in enumerate(targets) for t in image_targets]
        if not pairs:
            return [{} for _ in images]
        torch, _ = torch_and_transformers()
        flag, field = self._API[self.loaded.model_type]
        itm = self.mode == "itm"
        texts = [self.prompt.format(target=t) for _, t in pairs] if itm else \
            list(dict.fromkeys(self.prompt.format(target=t) for _, t in pairs))
        batch = _to(self.loaded.processor(images=list(images), text=texts, return_tensors="pt", padding=True),
                    self.placement)
        if itm:
            batch["pixel_values"] = batch["pixel_values"][[i for i, _ in pairs]]
        with torch.inference_mode():
            out = getattr(self.loaded.model(**batch, **{flag: itm}), field).float()
        out = out.cpu()
        scores: list[dict[str, float]] = [{} for _ in images]
        column = {text: j for j, text in enumerate(texts)}
        for n, (i, t) in enumerate(pairs):
            scores[i][t] = float(out.softmax(dim=-1)[n, 1]) if itm else \
                float(out[i, column[self.prompt.format(target=t)]])
        return scores


@dataclass(frozen=True)
class Box:
    label: str
    score: float
    box: tuple[int, int, int, int]


def caption(targets: Sequence[str]) -> tuple[str, list[tuple[int, int]]]:
    """GroundingDINO's caption ("chair . fridge .") and each target's character span in it."""
    parts, spans, at = [], [], 0
    for target in targets:
        name = target.lower().strip()
        spans.append((at, at + len(name)))
        parts.append(f"{name} .")
        at += len(name) + 3
    return " ".join(parts), spans


def pixel_boxes(cxcywh: np.ndarray, width: int, height: int) -> np.ndarray:
    """Normalised (cx, cy, w, h) boxes as end-exclusive integer pixel boxes inside the image."""
    cx, cy, w, h = cxcywh.T
    x0 = np.clip(np.floor((cx - w / 2) * width), 0, width - 1)
    y0 = np.clip(np.floor((cy - h / 2) * height), 0, height - 1)
    x1 = np.clip(np.ceil((cx + w / 2) * width), x0 + 1, width)
    y1 = np.clip(np.ceil((cy + h / 2) * height), y0 + 1, height)
    return np.stack([x0, y0, x1, y1], axis=1).astype(np.int64)


class GroundingDetector:
    """GroundingDINO boxes for all targets from one caption.

    As in GroundingDINO, a query box is kept when its best token probability
    exceeds ``box_threshold``. Its label is the target whose tokens score
    highest, kept only above ``text_threshold``: every box gets exactly one of
    the targets as its label, never a merged or partial phrase.
    """

    def __init__(self, loaded: Loaded, placement: Placement, box_threshold: float,
                 text_threshold: float, max_detections: int) -> None:
        self.loaded, self.placement = loaded, placement
        self.box_threshold, self.text_threshold = box_threshold, text_threshold
        self.max_detections = max_detections

    def _target_tokens(self, text: str, spans: list[tuple[int, int]], input_ids: Any) -> list[list[int]]:
        """Each target's token positions in ``input_ids`` (one caption's row of the batch; a shorter
        caption than the batch's longest is padded after its own tokens)."""
        encoded = self.loaded.processor.tokenizer(text, return_offsets_mapping=True)
        if list(encoded["input_ids"]) != input_ids.tolist()[:len(encoded["input_ids"])]:
            raise RuntimeError("GroundingDINO tokenizer and processor disagree on the caption's tokens")
        tokens: list[list[int]] = [[] for _ in spans]
        for i, (start, end) in enumerate(encoded["offset_mapping"]):
            for t, (lo, hi) in enumerate(spans):
                if end > start and lo <= start and end <= hi:
                    tokens[t].append(i)
        return tokens

    def __call__(self, rgb: np.ndarray, targets: Sequence[str]) -> list[Box]:
        return self.batch([rgb], [targets])[0]

    def batch(self, images: Sequence[np.ndarray], targets: Sequence[Sequence[str]]) -> list[list[Box]]:
        """Boxes of each image's own targets (its own caption), images with targets in one pass."""
        todo = [i for i, image_targets in enumerate(targets) if image_targets]
        found: list[list[Box]] = [[] for _ in images]
        if not todo:
            return found
        torch, _ = torch_and_transformers()
        captions = [caption(targets[i]) for i in todo]
        batch = _to(self.loaded.processor(images=[images[i] for i in todo], text=[c for c, _ in captions],
                                          return_tensors="pt", padding=True), self.placement)
        with torch.inference_mode():
            out = self.loaded.model(**batch)
        for row, (i, (text, spans)) in enumerate(zip(todo, captions)):
            length = int(batch["attention_mask"][row].sum())  # this caption's text positions, no padding
            found[i] = self._boxes(out.logits[row][:, :length], out.pred_boxes[row],
                                   self._target_tokens(text, spans, batch["input_ids"][row]),
                                   targets[i], images[i].shape[:2])
        return found

    def _boxes(self, logits: Any, pred_boxes: Any, tokens: list[list[int]], targets: Sequence[str],
               size: tuple[int, ...]) -> list[Box]:
        torch, _ = torch_and_transformers()
        probs = logits.float().sigmoid()                                 # queries x text positions
        per_target = torch.stack([probs[:, idx].amax(dim=1) if idx else torch.zeros_like(probs[:, 0])
                                  for idx in tokens], 1)
        box_score = probs.amax(dim=1)
        label_score, label = per_target.max(dim=1)
        keep = (box_score > self.box_threshold) & (label_score > self.text_threshold)
        order = [i for i in torch.argsort(box_score, descending=True).tolist() if keep[i]]
        order = order[:self.max_detections]
        height, width = size[:2]
        boxes = pixel_boxes(pred_boxes.float().cpu().numpy()[order], width, height)
        return [Box(targets[int(label[i])], float(box_score[i]),
                    tuple(int(v) for v in b))  # type: ignore[arg-type]
                for i, b in zip(order, boxes)]


class SamSegmenter:
    """SAM masks (original image size) for boxes, sharing one image embedding."""

    def __init__(self, loaded: Loaded, placement: Placement) -> None:
        self.loaded, self.placement = loaded, placement

    def __call__(self, rgb: np.ndarray, boxes: Sequence[tuple[int, int, int, int]]) -> list[np.ndarray]:
        if not boxes:
            return []
        torch, _ = torch_and_transformers()
        processor = self.loaded.processor
        batch = processor(images=rgb, input_boxes=[[[float(v) for v in b] for b in boxes]],
                          return_tensors="pt")
        inputs = _to({k: batch[k] for k in ("pixel_values", "input_boxes")}, self.placement)
        with torch.inference_mode():
            embeddings = self.loaded.model.get_image_embeddings(inputs["pixel_values"])
            out = self.loaded.model(image_embeddings=embeddings, input_boxes=inputs["input_boxes"],
                                    multimask_output=False)
        masks = processor.post_process_masks(out.pred_masks.float().cpu(), batch["original_sizes"],
                                             batch["reshaped_input_sizes"])[0]  # boxes x 1 x H x W
        return [m[0].numpy().astype(bool) for m in masks]
