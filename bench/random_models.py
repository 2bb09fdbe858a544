"""Random-weight models of the real architectures, for tests and benchmarks (no download).

Not part of the service: the perception benchmark (:mod:`ovamos.bench.perception`) and the hf
tests use them.

``tiny`` models come from small configs (seconds to build and run) and exercise
the whole pipeline; ``full`` ones use the default configs, which are the
architectures the service runs (BLIP-base ITM at 384 px, GroundingDINO with a
Swin-T backbone, SAM ViT-B): random weights cost the same time as trained ones.
:func:`save_model_dirs` writes them as ``save_pretrained`` directories so that
tests load them through exactly the loader used for real weights.

Tokenizers get a small BERT word-piece vocabulary (special tokens, the prompt's
words, letters and ``##`` letters, so any lowercase word tokenizes to real
ids). It is passed as ``vocab=``: in transformers 5 ``BertTokenizer(vocab_file=)``
silently maps every word to [UNK].
"""

from __future__ import annotations

import string
from pathlib import Path
from typing import Any, Literal

from ovamos.services.perception.config import HfBackendConfig
from ovamos.services.perception.hf.loading import Loaded, Placement, torch_and_transformers

Size = Literal["tiny", "full"]
ItmKind = Literal["blip", "blip-2"]
_TINY_VOCAB = 128  # >= the vocabulary below


def vocabulary() -> dict[str, int]:
    words = ["[PAD]", "[UNK]", "[CLS]", "[SEP]", "[MASK]", "seems", "like", "there", "is", "a", "ahead", ".",
             *string.ascii_lowercase, *(f"##{c}" for c in string.ascii_lowercase)]
    return {w: i for i, w in enumerate(dict.fromkeys(words))}


def _tokenizer() -> Any:
    _, tf = torch_and_transformers()
    return tf.BertTokenizer(vocab=vocabulary())


def _tiny_text(**extra: Any) -> dict[str, Any]:
    """A tiny BERT-like text config whose special ids lie inside :func:`vocabulary`."""
    return {"vocab_size": _TINY_VOCAB, "hidden_size": 32, "num_hidden_layers": 1, "num_attention_heads": 2,
            "intermediate_size": 64, "pad_token_id": 0, "bos_token_id": 2, "sep_token_id": 3, **extra}


_TINY_VISION = {"hidden_size": 32, "num_hidden_layers": 1, "num_attention_heads": 2,
                "intermediate_size": 64, "image_size": 64, "patch_size": 16}


def _itm(size: Size, kind: ItmKind) -> tuple[Any, Any]:
    _, tf = torch_and_transformers()
    tiny = size == "tiny"
    side = 64 if tiny else 384 if kind == "blip" else 224
    images = tf.BlipImageProcessor(size={"height": side, "width": side})
    if kind == "blip":
        config = tf.BlipConfig(**({"text_config": _tiny_text(encoder_hidden_size=32),
                                   "vision_config": _TINY_VISION, "projection_dim": 16,
                                   "image_text_hidden_size": 16} if tiny else {}))
        return tf.BlipForImageTextRetrieval(config), tf.BlipProcessor(images, _tokenizer())
    # the ITM checkpoints feed text through the Q-Former, which needs its text-input layers
    qformer = {"use_qformer_text_input": True}
    if tiny:
        qformer.update(_tiny_text(encoder_hidden_size=32, cross_attention_frequency=1))
    config = tf.Blip2Config(qformer_config=qformer, **({"vision_config": _TINY_VISION, "num_query_tokens": 4,
                                                        "image_text_hidden_size": 16} if tiny else {}))
    return tf.Blip2ForImageTextRetrieval(config), tf.Blip2Processor(images, _tokenizer())


def _detector(size: Size) -> tuple[Any, Any]:
    _, tf = torch_and_transformers()
    common = {"use_pretrained_backbone": False, "use_timm_backbone": False}
    if size == "tiny":
        config = tf.GroundingDinoConfig(
            backbone_config={"model_type": "swin", "embed_dim": 16, "depths": [1, 1, 1, 1],
                             "num_heads": [1, 1, 1, 1], "window_size": 4, "image_size": 64,
                             "out_indices": [2, 3, 4]},
            text_config={"model_type": "bert", **_tiny_text()}, d_model=32, num_queries=20,
            encoder_layers=1, decoder_layers=2, encoder_ffn_dim=64, decoder_ffn_dim=64,
            encoder_attention_heads=2, decoder_attention_heads=2, encoder_n_points=2, decoder_n_points=2,
            max_text_len=32, **common)
        images = tf.GroundingDinoImageProcessor(size={"shortest_edge": 64, "longest_edge": 96})
    else:
        config = tf.GroundingDinoConfig(**common)
        images = tf.GroundingDinoImageProcessor()
    return tf.GroundingDinoForObjectDetection(config), tf.GroundingDinoProcessor(images, _tokenizer())


def _segmenter(size: Size) -> tuple[Any, Any]:
    _, tf = torch_and_transformers()
    if size == "full":
        return tf.SamModel(tf.SamConfig()), tf.SamProcessor(tf.SamImageProcessor())
    config = tf.SamConfig(
        vision_config={"hidden_size": 32, "output_channels": 16, "num_hidden_layers": 2,
                       "num_attention_heads": 2, "image_size": 64, "patch_size": 16, "window_size": 2,
                       "global_attn_indexes": [1], "mlp_dim": 64, "num_pos_feats": 8},
        prompt_encoder_config={"hidden_size": 16, "image_size": 64, "patch_size": 16,
                               "mask_input_channels": 4},
        mask_decoder_config={"hidden_size": 16, "mlp_dim": 32, "num_hidden_layers": 1,
                             "num_attention_heads": 2, "iou_head_hidden_dim": 16})
    images = tf.SamImageProcessor(size={"longest_edge": 64}, pad_size={"height": 64, "width": 64},
                                  mask_size={"longest_edge": 16})
    return tf.SamModel(config), tf.SamProcessor(images)


def build(role: Literal["itm", "detector", "segmenter"], size: Size, *, itm: ItmKind = "blip",
          seed: int = 0) -> tuple[Any, Any]:
    """A seeded random (model, processor) pair for one role."""
    torch, _ = torch_and_transformers()
    torch.manual_seed(seed)
    if role == "itm":
        return _itm(size, itm)
    return _detector(size) if role == "detector" else _segmenter(size)


def loaded(size: Size, placement: Placement, *, itm: ItmKind = "blip", seed: int = 0
           ) -> tuple[Loaded, Loaded, Loaded]:
    """The three roles in memory, placed as
    :func:`ovamos.services.perception.hf.loading.load_model` places real ones."""
    out = []
    for role, kind in (("itm", itm), ("detector", "grounding-dino"), ("segmenter", "sam")):
        model, processor = build(role, size, itm=itm, seed=seed)  # type: ignore[arg-type]
        out.append(Loaded(model.to(placement.device, placement.dtype).eval(), processor, kind))
    return out[0], out[1], out[2]


def save_model_dirs(root: Path, size: Size = "tiny", *, itm: ItmKind = "blip", seed: int = 0,
                    **settings: Any) -> HfBackendConfig:
    """Write the three models under ``root`` and return a config that points at them."""
    dirs = {"itm": root / f"itm-{itm}", "detector": root / "detector", "segmenter": root / "segmenter"}
    for role, directory in dirs.items():
        model, processor = build(role, size, itm=itm, seed=seed)  # type: ignore[arg-type]
        model.save_pretrained(directory)
        processor.save_pretrained(directory)
    return HfBackendConfig(itm_dir=dirs["itm"], detector_dir=dirs["detector"],
                           segmenter_dir=dirs["segmenter"], **settings)
