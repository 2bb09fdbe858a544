"""Every setting of the perception service (unknown keys are errors, as for every service)."""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import Field

from services.sim.perception import SimPerceptionConfig
from shared.config import ServiceConfig, StrictModel


class SimBackendConfig(StrictModel):
    """Where the simulated perception gets its scene: a scene file, else an episode's scene.

    The scene must be the one the simulated robot renders (same file, or the
    same episode seed and index), since the backend reads the classes of the
    instance ids it sees from it.
    """

    scene_file: Path | None = None
    episode_seed: int = 0
    episode_index: int = Field(default=0, ge=0)
    perception: SimPerceptionConfig = SimPerceptionConfig()


class HfBackendConfig(StrictModel):
    """Real models through transformers, from local directories only (never a download).

    Each directory holds what ``save_pretrained`` (or ``hf download --local-dir``)
    writes for the model: config, weights, and the processor/tokenizer files.
    Relative paths are taken from the working directory.
    """

    itm_dir: Path = Field(default=Path("models/blip-itm-base-coco"),
                          description="BLIP (BlipForImageTextRetrieval) or BLIP-2 ITM weights")
    detector_dir: Path = Field(default=Path("models/grounding-dino-tiny"),
                               description="GroundingDINO weights")
    segmenter_dir: Path = Field(default=Path("models/sam-vit-base"), description="SAM weights")
    device: Literal["auto", "cpu", "cuda"] = Field(default="auto", description="auto = cuda if present")
    fp16: bool = Field(default=True, description="half precision on cuda (ignored on the CPU)")
    score: Literal["itc", "itm"] = Field(
        default="itc", description="itc: image-text cosine (one image pass for all targets, as VLFM); "
                                   "itm: match probability of the ITM head (one image copy per target)")
    prompt: str = Field(default="Seems like there is a {target} ahead.", pattern=r"\{target\}")
    box_threshold: float = Field(default=0.35, ge=0, le=1)
    text_threshold: float = Field(default=0.25, ge=0, le=1)
    max_detections: int = Field(default=20, ge=1)


class FrameLimits(StrictModel):
    """Frames outside these limits are rejected (counted as malformed) before any model sees them."""

    min_side: int = Field(default=32, ge=1, description="pixels; smaller images break the detectors")
    max_side: int = Field(default=4096, ge=1)
    size: tuple[int, int] | None = Field(default=None, description="(width, height) the camera must send")


class PerceptionServiceConfig(ServiceConfig):
    backend: Literal["sim", "hf"] = "sim"
    sim: SimBackendConfig = SimBackendConfig()
    hf: HfBackendConfig = HfBackendConfig()
    frames: FrameLimits = FrameLimits()
    detect: bool = Field(default=True, description="run detection (object map) besides scoring")
    queue_frames: int = Field(
        default=1, ge=1, le=256,
        description="owned frames waiting for the backend; 1 = latest only (a newer frame replaces "
                    "the waiting one, counted as dropped)")
