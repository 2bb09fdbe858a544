"""Every setting of the perception service (unknown keys are errors, as for every service)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Literal

from pydantic import Field, field_validator

from ovamos.shared.config import ServiceConfig, StrictModel
from ovamos.shared.keys import check_chunk
from ovamos.shared.messages import MAX_DETECTIONS
from ovamos.world.perception import SimPerceptionConfig


class SceneChoice(StrictModel):
    """A simulated robot's scene: a scene file, else an episode's scene.

    It must be the one the simulated robot renders (same file, or the same
    episode seed and index), since the backend reads the classes of the
    instance ids it sees from it.
    """

    scene_file: Path | None = None
    episode_seed: int = 0
    episode_index: int = Field(default=0, ge=0)


class SimBackendConfig(SceneChoice):
    """The simulated perception: the scene of every robot not in ``robots`` (a fleet of simulated
    robots, each in its own home, names each robot's)."""

    robots: dict[str, SceneChoice] = Field(default_factory=dict, description="robot id -> its scene")
    perception: SimPerceptionConfig = SimPerceptionConfig()


MODELS_ENV = "OVAMOS_MODELS"
"""The environment variable naming the folder the weights are in (``HfBackendConfig.models_dir``)."""


def default_models_dir() -> Path:
    """``$OVAMOS_MODELS``, else ``$XDG_DATA_HOME/ovamos/models`` (``~/.local/share/ovamos/models``):
    where the weights are unless the config says, the same from whatever folder a service starts."""
    if os.environ.get(MODELS_ENV):
        return Path(os.environ[MODELS_ENV]).expanduser()
    data = os.environ.get("XDG_DATA_HOME") or Path.home() / ".local" / "share"
    return Path(data).expanduser() / "ovamos" / "models"


class HfBackendConfig(StrictModel):
    """Real models through transformers, from local directories only (never a download).

    Each directory holds what ``save_pretrained`` (or ``hf download --local-dir``)
    writes for the model: config, weights, and the processor/tokenizer files. A relative
    directory is in ``models_dir`` (:meth:`folder`), never the working directory: a service
    started by a supervisor, a unit or another shell finds the same weights.
    """

    models_dir: Path | None = Field(default=None, description="the folder relative *_dir are in; default: "
                                    f"${MODELS_ENV}, else $XDG_DATA_HOME/ovamos/models (~/.local/share/ovamos/models)")
    itm_dir: Path = Field(default=Path("blip-itm-base-coco"),
                          description="BLIP (BlipForImageTextRetrieval) or BLIP-2 ITM weights")
    detector_dir: Path = Field(default=Path("grounding-dino-tiny"), description="GroundingDINO weights")
    segmenter_dir: Path = Field(default=Path("sam-vit-base"), description="SAM weights")
    device: Literal["auto", "cpu", "cuda"] = Field(default="auto", description="auto = cuda if present")
    fp16: bool = Field(default=True, description="half precision on cuda (ignored on the CPU)")
    score: Literal["itc", "itm"] = Field(
        default="itc", description="itc: image-text cosine (one image pass for all targets, as VLFM); "
                                   "itm: match probability of the ITM head (one image copy per target)")
    prompt: str = Field(default="Seems like there is a {target} ahead.", pattern=r"\{target\}")
    box_threshold: float = Field(default=0.35, ge=0, le=1)
    text_threshold: float = Field(default=0.25, ge=0, le=1)
    max_detections: int = Field(default=20, ge=1, le=MAX_DETECTIONS,
                                description="a result with more could not be sent (ovamos.shared.messages.MAX_DETECTIONS)")

    def folder(self, directory: Path) -> Path:
        """Where one of the ``*_dir`` settings points: as given when absolute, else in ``models_dir``."""
        directory = directory.expanduser()
        return directory if directory.is_absolute() else (self.models_dir or default_models_dir()).expanduser() / directory


class FrameLimits(StrictModel):
    """Frames outside these limits are rejected (counted as malformed) before any model sees them."""

    min_side: int = Field(default=32, ge=1, description="pixels; smaller images break the detectors")
    max_side: int = Field(default=4096, ge=1)
    size: tuple[int, int] | None = Field(default=None, description="(width, height) the camera must send")


class PerceptionServiceConfig(ServiceConfig):
    robots: list[str] = Field(
        default_factory=list,
        description="robots whose frames this service serves; empty: its own (--robot-id); "
                    "[\"*\"]: every robot on the network (ovamos/*/sensors/rgbd)")
    batch_size: int = Field(default=1, ge=1, le=64,
                            description="frames (of different robots) per model call, at most")
    batch_wait_ms: float = Field(
        default=0.0, ge=0, le=1000,
        description="how long a waiting frame may wait for other robots' frames to fill a batch")
    backend: Literal["sim", "hf"] = "sim"
    sim: SimBackendConfig = SimBackendConfig()
    hf: HfBackendConfig = HfBackendConfig()
    frames: FrameLimits = FrameLimits()
    detect: bool = Field(default=True, description="run detection (object map) besides scoring")
    queue_frames: int = Field(
        default=1, ge=1, le=256,
        description="frames per robot waiting in the inbox while the backend works; 1 = latest "
                    "only (a newer frame replaces the waiting one, counted as dropped)")

    @field_validator("robots")
    @classmethod
    def _robot_ids(cls, robots: list[str]) -> list[str]:
        if "*" in robots and robots != ["*"]:
            raise ValueError('"*" (every robot) stands alone')
        for robot in robots:
            if robot != "*":
                check_chunk(robot, "robot id")
        if len(set(robots)) != len(robots):
            raise ValueError("a robot is named twice")
        return robots
