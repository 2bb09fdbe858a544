"""The hf backend end to end with tiny random-weight models, loaded from disk like real weights.

The models are the real transformers classes built from small configs and
written with ``save_pretrained``; :meth:`HfBackend.load` reads them through the
same offline loader the service uses for downloaded weights.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

pytest.importorskip("torch")
pytest.importorskip("transformers")

from ovamos.bench.random_models import save_model_dirs
from ovamos.services.perception.config import PerceptionServiceConfig
from ovamos.services.perception.hf.backend import HfBackend
from ovamos.services.perception.hf.loading import Placement
from ovamos.services.perception.hf.models import GroundingDetector, ItmScorer
from ovamos.shared.messages import TaskSpec
from tests.perception_helpers import render_frames

pytestmark = pytest.mark.system  # processes, routers, browsers or real-time devices: make test-all

TARGETS = ("fridge", "cup", "chair")


@pytest.fixture(scope="module")
def frame():
    return render_frames(1)[0]


@pytest.fixture(scope="module")
def model_dirs(tmp_path_factory):
    root = tmp_path_factory.mktemp("models")
    return {kind: save_model_dirs(root / kind, itm=kind, seed=1) for kind in ("blip", "blip-2")}


@pytest.fixture(scope="module")
def backends(model_dirs):
    return {kind: HfBackend.load(config) for kind, config in model_dirs.items()}


@pytest.mark.parametrize("kind, score", [("blip", "itc"), ("blip", "itm"), ("blip-2", "itc"),
                                         ("blip-2", "itm")])
def test_every_target_gets_a_score(backends, frame, kind, score) -> None:
    backend = backends[kind]
    assert backend.placement.device == "cpu"
    scorer = ItmScorer(backend.scorer.loaded, backend.placement, backend.scorer.prompt, score)
    scores = scorer(frame.rgb, TARGETS)
    assert list(scores) == list(TARGETS)
    assert all(math.isfinite(v) for v in scores.values())
    low, high = (0.0, 1.0) if score == "itm" else (-1.0, 1.0)  # probability or cosine
    assert all(low <= v <= high for v in scores.values())
    # distinct prompts give distinct scores: all-[UNK] tokens would make them equal
    assert len(set(scores.values())) == len(TARGETS)


def test_detections_have_boxes_inside_the_image_and_masks_of_its_size(backends, frame) -> None:
    backend = backends["blip"]
    detections = backend.detect(frame, TARGETS)
    assert 1 <= len(detections) <= backend.detector.max_detections
    height, width = frame.depth.shape
    for det in detections:
        assert det.label in TARGETS and 0.35 < det.score <= 1.0
        x0, y0, x1, y1 = det.box
        assert 0 <= x0 < x1 <= width and 0 <= y0 < y1 <= height
        assert det.mask.shape == (height, width) and det.mask.dtype == np.bool_
    assert [d.score for d in detections] == sorted((d.score for d in detections), reverse=True)


def test_the_saved_tokenizers_know_the_prompt_words(backends) -> None:
    backend = backends["blip"]
    for processor in (backend.scorer.loaded.processor, backend.detector.loaded.processor):
        tokenizer = processor.tokenizer
        ids = tokenizer("Seems like there is a fridge ahead.")["input_ids"]
        assert tokenizer.unk_token_id not in ids


def test_no_box_passes_a_threshold_above_every_score(backends, frame) -> None:
    backend = backends["blip"]
    strict = GroundingDetector(backend.detector.loaded, backend.placement, 1.0, 0.25, 20)
    assert strict(frame.rgb, TARGETS) == []
    assert backend.score(frame, []) == {} and backend.detect(frame, []) == []


def test_the_cpu_gets_full_precision() -> None:
    import torch
    placement = Placement.resolve("auto", fp16=True)
    expected = "cuda" if torch.cuda.is_available() else "cpu"
    assert placement.device == expected
    assert placement.dtype == (torch.float16 if expected == "cuda" else torch.float32)


def test_the_service_runs_the_hf_backend_from_its_config(model_dirs, inproc_router, frame) -> None:
    from ovamos.shared import keys
    from ovamos.shared.bus import Bus
    from ovamos.shared.bus.zconfig import build_config
    from ovamos.shared.messages import PerceptionResult, RgbdFrame
    from tests.perception_helpers import ROBOT, RunningPerception
    from tests.polling import wait_for

    config = PerceptionServiceConfig(backend="hf", hf=model_dirs["blip"])
    got: list[PerceptionResult] = []
    with Bus.open(build_config(connect=[inproc_router]), ROBOT, "test-sender") as bus:
        bus.subscribe(keys.perception_result(ROBOT), PerceptionResult, got.append)
        frames = bus.publisher(keys.rgbd(ROBOT), RgbdFrame)
        tasks = bus.publisher(keys.task_current(ROBOT), TaskSpec)
        task = TaskSpec(task_id="t", targets=TARGETS, stamp=0.0)
        service = RunningPerception(inproc_router, config)
        try:
            result = wait_for(lambda: tasks.put(task) or frames.put(frame) or next(
                (r for r in list(got) if r.targets == TARGETS), None), what="an hf result")
        finally:
            service.close()
    assert result.seq == frame.seq and len(result.labels) >= 1
    assert result.masks.shape[1:] == frame.depth.shape


def test_frames_of_two_robots_go_through_each_model_in_one_call_and_back_to_their_robot(backends) -> None:
    """One ITM pass and one GroundingDINO pass for two robots' frames, each with its own targets;
    each result goes to its robot's key with its frame's seq and that robot's targets."""
    from ovamos.services.perception.service import PerceptionService
    from ovamos.shared.fake_bus import FakeNetwork
    from tests.perception_helpers import Robot

    backend = backends["blip"]
    calls = {"itm": 0, "detector": 0}
    hooks = [model.register_forward_hook(lambda *_, role=role: calls.__setitem__(role, calls[role] + 1))
             for role, model in (("itm", backend.scorer.loaded.model), ("detector", backend.detector.loaded.model))]
    try:
        network = FakeNetwork()
        service = PerceptionService(network.bus("fleet", "perception"), PerceptionServiceConfig(
            backend="hf", robots=["r1", "r2"], batch_size=2, batch_wait_ms=1000), backend)
        service.start()
        r1, r2 = Robot(network, "r1"), Robot(network, "r2")
        network.pump()
        r1.tasks.put(TaskSpec(task_id="a", targets=("fridge", "cup"), stamp=0.0))
        r2.tasks.put(TaskSpec(task_id="b", targets=("chair",), stamp=0.0))
        frames = render_frames(2)
        r1.frames.put(frames[0].model_copy(update={"seq": 11}))
        r2.frames.put(frames[1].model_copy(update={"seq": 22}))
        network.pump()
    finally:
        for hook in hooks:
            hook.remove()
    assert calls == {"itm": 1, "detector": 1}
    assert [(r.seq, r.targets) for r in r1.results] == [(11, ("fridge", "cup"))]
    assert [(r.seq, r.targets) for r in r2.results] == [(22, ("chair",))]
    # the same scores as each frame alone: no robot's frame or targets leaked into the other's
    alone = backend.scorer(frames[1].rgb, ("chair",))
    assert r2.results[0].score_map() == pytest.approx(alone, abs=1e-5)
