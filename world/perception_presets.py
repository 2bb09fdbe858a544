"""Named settings of the simulated perception: ``ideal``, ``realistic`` and ``hard``.

The simulator's detector and value scores (:mod:`ovamos.world.perception`) have one
constant per effect. ``ideal`` is the defaults the benchmark tables were first made with;
``realistic`` and ``hard`` take each constant from a published, policy-independent figure
on the models the simulator stands in for (GroundingDINO Swin-T for detection, BLIP-2 ITM /
ITC for value scores) in the setting the paper uses (640x480 RGB-D, 79 deg field of view,
depth capped at 5 m). No value was chosen by looking at which search policy it favours.

Sources (short names used below):

* [GDINO] Liu et al., "Grounding DINO", arXiv 2303.05499; the Swin-T checkpoint's LVIS
  and COCO zero-shot figures from mmdetection's ``configs/mm_grounding_dino/README.md``:
  COCO 48.4 AP; LVIS val1.0 AP_rare / AP_common / AP_frequent = 10.1 / 15.3 / 29.9,
  minival 18.8 / 24.2 / 34.7.
* [GDINO-96] IDEA-Research/GroundingDINO issue 96: a COCO val2017 evaluation of that
  checkpoint by size: AP small / medium / large 0.23 / 0.44 / 0.59, AR@100 small / medium
  0.40 / 0.66 (COCO: small < 32^2 px, medium < 96^2 px, images about 640x480 like ours).
* [GDINO-84] IDEA-Research/GroundingDINO issue 84: confident boxes for prompted classes
  that are not in the image (confirmed by several users).
* [VLFM] Yokoyama et al., "VLFM", arXiv 2312.03275, and its code (bdaiinstitute/vlfm):
  detection thresholds 0.8 (COCO classes) and 0.4 (GroundingDINO), depth capped at 5 m,
  a frontier is kept unless its BLIP-2 value drops by more than 0.01.
* [ApexNav] Zhang et al., "ApexNav", arXiv 2504.14478, and its code
  (Robotics-STAR-Lab/ApexNav): 3-4 look-alike classes per HM3D target with per-class
  thresholds 0.35-0.65; an object needs 2 observations; observations only within 4 m;
  semantic exploration only when the frontier values' spread exceeds 0.015 (max/mean 1.10).
* [CompNet] Wang et al., "Robust Object Detection under Occlusion with Context-Aware
  CompositionalNets", CVPR 2020 (arXiv 2003.11500): +41 points over Faster R-CNN on
  60-80 % occluded objects, so the baseline detects at most ~59 % of those.
"""

from __future__ import annotations

from typing import Literal, get_args

from ovamos.world.perception import SimPerceptionConfig

PerceptionPreset = Literal["ideal", "realistic", "hard"]
PERCEPTION_PRESETS: tuple[str, ...] = get_args(PerceptionPreset)

IDEAL = SimPerceptionConfig()
"""The defaults: SNR of the value score ~12 (gain 0.35 / sd 0.03), 95 % peak recall, 5 % of
related objects per frame reported as the target."""


# Each setting as (realistic, hard), with the figure it comes from.
_SETTINGS: dict[str, tuple[float, float]] = {
    # Value score: [ApexNav] and [VLFM] treat a few hundredths of BLIP-2 cosine as the useful
    # spread between places and ~0.01 as frame-to-frame jitter: a per-frame signal-to-noise
    # ratio of roughly 2-5. Realistic takes 4, hard 2: sd = gain / SNR.
    "score_noise": (IDEAL.score_gain / 4, IDEAL.score_gain / 2),
    # Peak recall. Realistic: a frequent, COCO-like class seen whole and large. [GDINO-96]
    # gives AP_large 0.59 and AR@100 0.61 (all sizes), both averaged over IoU 0.5:0.95; a
    # detection only needs IoU ~0.5 to land on the map, where recall of large objects is
    # higher: 0.85 is our estimate between those figures and 1, not a published number.
    # Hard: open-vocabulary targets are mostly LVIS common/rare classes, [GDINO]
    # AP_common / AP_frequent = 0.5 (val1.0) to 0.7 (minival); 0.7 x 0.85 = 0.6.
    "p_max": (0.85, 0.6),
    # Size. Realistic: [GDINO-96] recall of small objects (< 1024 px) is 0.61 of medium ones;
    # a linear ramp saturating at 400 px gives the small bucket ~0.5 of medium: the ideal
    # value already fits. Hard: the COCO small/medium boundary (1024 px) as the knee, which
    # also lowers lower-medium objects as [GDINO-96]'s AP_medium / AP_large = 0.76 does.
    "full_size_pixels": (400, 1024),
    # Distance: size already enters through pixels, so this term stands for the depth limit
    # of the stacks the paper builds on ([VLFM], [ApexNav]: 5 m depth cap, 4 m observation
    # window). Realistic: full below 3 m, x0.37 at 4 m, x0.14 at 5 m; hard: full below 2 m,
    # x0.14 at 4 m.
    "reliable_distance_m": (3.0, 2.0),
    "distance_falloff_m": (1.0, 1.0),
    # Occlusion: [CompNet] puts a standard detector at <= ~59 % on 60-80 % occluded objects,
    # i.e. recall ~ visible_fraction^0.4 .. ^1.3; realistic takes 1, hard the pessimistic end.
    "occlusion_power": (1.0, 1.5),
    # False positives: no published per-frame rate was found, only that they are frequent
    # enough to need high thresholds and repeated observations ([GDINO-84], [VLFM],
    # [ApexNav]'s 3-4 look-alikes per target): two and four times the ideal rate. The least
    # certain setting.
    "fp_rate": (0.10, 0.20),
}


def _preset(which: int) -> SimPerceptionConfig:
    """``IDEAL`` with column ``which`` of the settings, validated (a typo in a name is an
    error, not a no-op)."""
    return SimPerceptionConfig.model_validate(
        {**IDEAL.model_dump(), **{name: values[which] for name, values in _SETTINGS.items()}})


REALISTIC = _preset(0)
"""What GroundingDINO and BLIP-2 are reported to do on frequent indoor classes."""

HARD = _preset(1)
"""Rare open-vocabulary classes with a pessimistic reading of every figure."""

_PRESETS: dict[str, SimPerceptionConfig] = {"ideal": IDEAL, "realistic": REALISTIC, "hard": HARD}


def perception_preset(name: str) -> SimPerceptionConfig:
    """The named preset; a clear error for an unknown name."""
    try:
        return _PRESETS[name]
    except KeyError:
        raise ValueError(f"unknown perception preset {name!r} (known: {', '.join(PERCEPTION_PRESETS)})") from None
