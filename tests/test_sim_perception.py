"""Simulated perception reads the rendered frame only, and is deterministic."""

from __future__ import annotations

import math

import numpy as np
import pytest

from ovamos.services.perception.backend import Job, Seen
from ovamos.services.perception.sim_backend import SimBackend
from ovamos.world.perception import FrameLabels, SimPerception, SimPerceptionConfig
from ovamos.world.perception_presets import PERCEPTION_PRESETS, perception_preset
from ovamos.world.prior import ObjectPrior
from ovamos.world.render import SceneRenderer
from ovamos.world.scene import Scene
from tests.sim_scenes import two_rooms

POSE = (1.6, 1.2, math.atan2(3.0 - 1.2, 0.4 - 1.6))  # kitchen, looking at the fridge
TARGETS = ["fridge", "cup", "toilet"]


@pytest.fixture(scope="module")
def prior() -> ObjectPrior:
    return ObjectPrior.load()


def render(scene: Scene):
    with SceneRenderer(scene, 160, 120) as renderer:
        return renderer.render(*POSE, seq=5)


def perceive(scene: Scene, prior: ObjectPrior, frame, **config):
    perception = SimPerception(FrameLabels.of(scene), prior, SimPerceptionConfig(**config))
    return perception.score(frame, TARGETS), perception.detect(frame, TARGETS)


def test_a_visible_target_scores_high_and_is_detected_with_its_mask(prior) -> None:
    scene = two_rooms()
    frame = render(scene)
    scores, detections = perceive(scene, prior, frame, score_noise=0.0, p_max=1.0, fp_rate=0.0,
                                  reliable_distance_m=10.0, full_size_pixels=1)
    assert scores["fridge"] == pytest.approx(0.5)  # base 0.15 + gain 0.35 * relatedness 1
    assert scores["toilet"] < scores["fridge"]
    (fridge,) = [d for d in detections if d.label == "fridge"]
    assert np.array_equal(fridge.mask, frame.instance_ids == 1)
    x0, y0, x1, y1 = fridge.box
    assert fridge.mask[y0:y1, x0:x1].sum() == fridge.mask.sum()
    assert not [d for d in detections if d.label == "cup"]  # the cup is in the other room


def test_output_is_deterministic_per_seed_scene_and_frame(prior) -> None:
    scene = two_rooms()
    frame = render(scene)
    first, again = perceive(scene, prior, frame), perceive(scene, prior, frame)
    assert first[0] == again[0]
    assert [(d.label, d.score, d.box) for d in first[1]] == [(d.label, d.score, d.box) for d in again[1]]
    assert perceive(scene, prior, frame, seed=1)[0] != first[0]
    # the same view in another episode's scene draws other noise (episodes share frame seqs)
    other_episode = scene.model_copy(update={"seed": (scene.seed or 0) + 1})
    assert perceive(other_episode, prior, frame)[0] != first[0]


def test_a_targets_output_does_not_depend_on_the_other_targets_asked_for(prior) -> None:
    """The services may still ask for a target found a moment ago, or list targets in another
    order: each target's score and detections must not change with it."""
    scene = two_rooms()
    frame = render(scene)
    config = SimPerceptionConfig(p_max=1.0, reliable_distance_m=10.0, full_size_pixels=1, fp_rate=1.0,
                                 fp_min_cooccurrence=0.0)
    perception = SimPerception(FrameLabels.of(scene), prior, config)
    together = perception.score(frame, TARGETS[::-1]), perception.detect(frame, TARGETS[::-1])
    assert together[1]
    for target in TARGETS:
        alone = perception.score(frame, [target]), perception.detect(frame, [target])
        assert alone[0][target] == together[0][target]
        assert [(d.score, d.box) for d in alone[1]] == [(d.score, d.box) for d in together[1] if d.label == target]


def test_hidden_objects_do_not_change_the_output(prior) -> None:
    scene = two_rooms()
    frame = render(scene)
    before = perceive(scene, prior, frame)
    # move the out-of-view cup and turn the out-of-view table into a toilet
    objects = tuple(o.model_copy(update={"x": 4.0}) if o.cls == "cup" else
                    o.model_copy(update={"cls": "toilet"}) if o.cls == "table" else o
                    for o in scene.objects)
    moved = scene.model_copy(update={"objects": objects})
    frame_after = render(moved)
    assert np.array_equal(frame_after.rgb, frame.rgb)
    assert np.array_equal(frame_after.instance_ids, frame.instance_ids)
    after = perceive(moved, prior, frame_after)
    assert after[0] == before[0]
    assert [(d.label, d.box) for d in after[1]] == [(d.label, d.box) for d in before[1]]


def test_occluded_and_far_objects_are_detected_less(prior) -> None:
    scene = two_rooms()
    frame = render(scene)
    perception = SimPerception(FrameLabels.of(scene), prior)
    objects, _ = perception._visible(frame)
    (fridge,) = [o for o in objects if o.cls == "fridge"]
    p = perception.detect_probability(frame, fridge)
    half = fridge.__class__(fridge.id, fridge.cls, fridge.pixels // 2, fridge.depth, fridge.box)
    far = fridge.__class__(fridge.id, fridge.cls, fridge.pixels, fridge.depth + 3.0, fridge.box)
    assert perception.detect_probability(frame, half) < p
    assert perception.detect_probability(frame, far) < p


def test_frames_without_instance_ids_are_refused(prior) -> None:
    scene = two_rooms()
    frame = render(scene).model_copy(update={"instance_ids": None})
    with pytest.raises(ValueError, match="simulated frames"):
        SimPerception(FrameLabels.of(scene), prior).score(frame, TARGETS)


def test_an_unknown_target_is_named_with_the_closest_class_and_the_rest_scored(prior) -> None:
    """A typo (``candel``) names no class a simulated house can hold: the backend says so, with
    the closest class, and scores the other targets (it raised on every frame, and the task sat
    at step 0 for ever)."""
    scene = two_rooms()
    frame = render(scene)
    backend = SimBackend(scene, prior)
    unknown, why = backend.unknown_targets(["fridge", "candel"])
    assert unknown == ("candel",)
    assert why.startswith("unknown target 'candel' for the simulated house: did you mean 'candle'? "
                          "it can have: alarm_clock, apple, ")
    assert why.endswith(", ".join(prior.classes[-2:]))
    assert backend.unknown_targets(TARGETS) == ((), "")
    (seen,) = backend.process([Job("r1", frame, ("fridge", "candel"))], detect=True)
    assert isinstance(seen, Seen) and seen.scores == backend.score(frame, ["fridge"])
    assert {d.label for d in seen.detections} <= {"fridge"}


def test_presets_get_worse_in_every_figure_from_ideal_to_hard() -> None:
    """Each preset is a validated config; realistic and hard are noisier, miss more, see less far
    and confuse more than the one before (the figures behind them: perception_presets.py)."""
    ideal, realistic, hard = (perception_preset(n) for n in PERCEPTION_PRESETS)
    assert ideal == SimPerceptionConfig()
    for better, worse in ((ideal, realistic), (realistic, hard)):
        assert worse.score_noise > better.score_noise
        assert worse.p_max < better.p_max
        assert worse.fp_rate > better.fp_rate
        assert worse.full_size_pixels >= better.full_size_pixels
        assert worse.occlusion_power >= better.occlusion_power
    with pytest.raises(ValueError, match="unknown perception preset 'perfect'"):
        perception_preset("perfect")


def test_a_harder_preset_detects_less_often_from_the_same_views(prior) -> None:
    """Over a walk of views past the fridge, the share of frames in which it is detected falls
    from preset to preset: the config is what the detector reads."""
    scene = two_rooms()
    with SceneRenderer(scene, 160, 120) as renderer:
        frames = [renderer.render(1.0 + 0.1 * i, 1.2, POSE[2], seq=i) for i in range(12)]
    rates = []
    for name in PERCEPTION_PRESETS:
        perception = SimPerception(FrameLabels.of(scene), prior, perception_preset(name))
        hits = [any(d.label == "fridge" for d in perception.detect(f, ["fridge"])) for f in frames]
        rates.append(sum(hits) / len(frames))
    assert rates[0] > rates[2] and rates == sorted(rates, reverse=True)
