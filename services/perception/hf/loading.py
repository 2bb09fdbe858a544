"""Loading model directories offline, with errors that say what to download and where.

Weights come only from local directories (``local_files_only=True`` and
``HF_HUB_OFFLINE=1``): a robot must never stall on, or depend on, a hub
download at start-up, and tests load tiny models through this same path.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType
from typing import Any

from ovamos.services.perception.config import MODELS_ENV
from ovamos.services.perception.errors import BackendError

_INSTALL_HINT = "pip install 'ovamos[perception]' (install torch==2.13.0 first for the CPU build)"
_WEIGHTS = ("model.safetensors", "pytorch_model.bin")
_WEIGHT_INDEXES = ("model.safetensors.index.json", "pytorch_model.bin.index.json")
_PROCESSOR_FILES = ("processor_config.json", "preprocessor_config.json")
_TOKENIZER_FILES = ("tokenizer.json", "vocab.txt")


class ModelFilesError(BackendError):
    """A model directory that is missing or incomplete."""


@dataclass(frozen=True)
class ModelRole:
    """One model the backend needs: what it is called, where to get it, which classes load it."""

    what: str
    config_key: str
    repo: str                       # the hub repository to download (the paper's choice)
    classes: dict[str, str]         # config.json model_type -> transformers model class
    needs_tokenizer: bool


ITM = ModelRole("BLIP ITM", "hf.itm_dir", "Salesforce/blip-itm-base-coco",
                {"blip": "BlipForImageTextRetrieval", "blip-2": "Blip2ForImageTextRetrieval"}, True)
DETECTOR = ModelRole("GroundingDINO", "hf.detector_dir", "IDEA-Research/grounding-dino-tiny",
                     {"grounding-dino": "GroundingDinoForObjectDetection"}, True)
SEGMENTER = ModelRole("SAM", "hf.segmenter_dir", "facebook/sam-vit-base", {"sam": "SamModel"}, False)


def torch_and_transformers() -> tuple[ModuleType, ModuleType]:
    """Import torch and transformers on first use, offline."""
    os.environ["HF_HUB_OFFLINE"] = "1"  # read by huggingface_hub at import: set before it
    try:
        import torch
        import transformers
    except ImportError as exc:
        raise BackendError(f"the hf perception backend needs torch and transformers ({exc.name} is "
                           f"missing): {_INSTALL_HINT}") from None
    transformers.utils.logging.disable_progress_bar()  # a service logs lines, not progress bars
    return torch, transformers


def _download_hint(role: ModelRole, directory: Path) -> str:
    return (f"download {role.repo} on a machine with internet access (e.g. `hf download {role.repo} "
            f"--local-dir {directory}`) and copy it to {directory}, or set {role.config_key} (or "
            f"hf.models_dir, or ${MODELS_ENV}) to where it is")


def model_type(role: ModelRole, directory: Path) -> str:
    """The directory's model type, after checking every file a load needs is there."""
    directory = directory.expanduser().resolve()
    if not directory.is_dir():
        raise ModelFilesError(f"{role.what} weights not found: {directory} does not exist; "
                              f"{_download_hint(role, directory)}")
    kind = _declared_type(role, directory)
    missing = [] if kind is not None else ["config.json"]
    if not _weights_present(directory):
        missing.append(" or ".join(_WEIGHTS) + " (or a complete sharded index)")
    if not any((directory / f).is_file() for f in _PROCESSOR_FILES):
        missing.append(" or ".join(_PROCESSOR_FILES))
    if role.needs_tokenizer and not any((directory / f).is_file() for f in _TOKENIZER_FILES):
        missing.append(" or ".join(_TOKENIZER_FILES))
    if missing or kind is None:
        raise ModelFilesError(f"{role.what} weights in {directory} are incomplete (missing "
                              f"{'; '.join(missing)}); {_download_hint(role, directory)}")
    return kind


def _declared_type(role: ModelRole, directory: Path) -> str | None:
    """The model_type in config.json (None without one); a model of another kind is an error."""
    path = directory / "config.json"
    if not path.is_file():
        return None
    try:
        kind = json.loads(path.read_text()).get("model_type")
    except (OSError, ValueError, AttributeError) as exc:
        raise ModelFilesError(f"{role.what}: cannot read {path}: {exc}; "
                              f"{_download_hint(role, directory)}") from None
    if kind not in role.classes:
        raise ModelFilesError(f"{directory} holds a {kind!r} model, not {role.what} "
                              f"(expected model_type {' or '.join(role.classes)}); "
                              f"{_download_hint(role, directory)}")
    return kind


def _weights_present(directory: Path) -> bool:
    if any((directory / f).is_file() for f in _WEIGHTS):
        return True
    for name in _WEIGHT_INDEXES:
        index = directory / name
        if index.is_file():
            try:
                shards = set(json.loads(index.read_text())["weight_map"].values())
            except (OSError, ValueError, KeyError, AttributeError):
                return False
            return all((directory / shard).is_file() for shard in shards)
    return False


@dataclass(frozen=True)
class Placement:
    """Where a model runs: torch device and dtype (fp16 on cuda when asked)."""

    device: str
    dtype: Any  # a torch.dtype; Any keeps this module importable without torch

    @classmethod
    def resolve(cls, device: str, fp16: bool) -> Placement:
        torch, _ = torch_and_transformers()
        if device == "auto":
            device = "cuda" if torch.cuda.is_available() else "cpu"
        if device == "cuda" and not torch.cuda.is_available():
            raise BackendError("device = \"cuda\" but torch sees no CUDA device "
                               f"(torch {torch.__version__}); use device = \"auto\" or \"cpu\"")
        return cls(device, torch.float16 if fp16 and device == "cuda" else torch.float32)


@dataclass(frozen=True)
class Loaded:
    model: Any
    processor: Any
    model_type: str


def load_model(role: ModelRole, directory: Path, placement: Placement) -> Loaded:
    """Model and processor of ``role`` from ``directory``, on ``placement``, in eval mode."""
    kind = model_type(role, directory)
    _, transformers = torch_and_transformers()
    model_class = getattr(transformers, role.classes[kind])
    try:
        processor = transformers.AutoProcessor.from_pretrained(directory, local_files_only=True)
        model = model_class.from_pretrained(directory, local_files_only=True, dtype=placement.dtype)
    except (OSError, ValueError) as exc:
        raise ModelFilesError(f"{role.what}: cannot load {directory}: {exc}; "
                              f"{_download_hint(role, directory)}") from None
    return Loaded(model.to(placement.device).eval(), processor, kind)
