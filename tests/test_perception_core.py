"""Perception without Zenoh or torch: the core driven message by message, replicas, checks, sim backend,
config, errors."""

from __future__ import annotations

import json
import logging
from collections.abc import Sequence

import numpy as np
import pytest
from pydantic import ValidationError

from ovamos.services.perception.backend import Job, Seen, load_backend
from ovamos.services.perception.config import (
    MODELS_ENV,
    FrameLimits,
    HfBackendConfig,
    PerceptionServiceConfig,
    SimBackendConfig,
)
from ovamos.services.perception.core import PerceptionCore
from ovamos.services.perception.errors import BackendError, FrameRejected
from ovamos.services.perception.frames import frame_problem
from ovamos.services.perception.hf.backend import HfBackend
from ovamos.services.perception.hf.loading import ModelFilesError
from ovamos.services.perception.hf.models import caption, pixel_boxes
from ovamos.services.perception.replicas import ReplicaSet
from ovamos.services.perception.sim_backend import SimBackend
from ovamos.shared.messages import PerceptionResult, RgbdFrame, TaskSpec
from tests.perception_helpers import render_frames
from tests.sim_scenes import two_rooms


@pytest.fixture(scope="module")
def frame():
    return render_frames(1)[0]


def test_replicas_split_every_seq_between_the_live_members_exactly_once() -> None:
    views = {name: ReplicaSet(name) for name in ("b", "a", "c")}
    for view in views.values():
        for other in views:
            view.join(other)
    for seq in range(60):
        assert sum(v.owns(seq) for v in views.values()) == 1
    assert [s for s in range(6) if views["a"].owns(s)] == [0, 3]  # sorted names: a, b, c
    views["a"].leave("c")
    views["a"].leave("a")  # a replica never forgets itself
    assert views["a"].members() == ["a", "b"]
    assert [s for s in range(6) if views["a"].owns(s)] == [0, 2, 4]
    alone = ReplicaSet("x")
    assert all(alone.owns(s) for s in range(5))


def test_frames_outside_the_limits_are_named(frame) -> None:
    assert frame_problem(frame, FrameLimits()) is None
    assert "160x120" in frame_problem(frame, FrameLimits(size=(640, 480)))
    assert "within 200..4096" in frame_problem(frame, FrameLimits(min_side=200))


def test_the_sim_backend_matches_the_simulators_perception_and_refuses_camera_frames(frame, tmp_path) -> None:
    scene_file = tmp_path / "scene.json"
    two_rooms().save(scene_file)
    backend = load_backend(PerceptionServiceConfig(sim=SimBackendConfig(scene_file=scene_file)))
    assert isinstance(backend, SimBackend)
    # the fridge is in view; a toilet is unrelated to a kitchen, so it scores far lower whatever
    # the noise (a cup, related to a fridge, is within the noise of it)
    scores = backend.score(frame, ["fridge", "toilet"])
    assert list(scores) == ["fridge", "toilet"] and scores["fridge"] > scores["toilet"] + 0.1
    assert scores == backend.perception.score(frame, ["fridge", "toilet"])
    camera_frame = frame.model_copy(update={"instance_ids": None})
    with pytest.raises(FrameRejected, match="instance ids"):
        backend.score(camera_frame, ["fridge"])
    with pytest.raises(FrameRejected, match="instance ids"):
        backend.detect(camera_frame, ["fridge"])
    with pytest.raises(BackendError, match="cannot load scene"):
        SimBackend.load(SimBackendConfig(scene_file=tmp_path / "missing.json"))


def test_the_sim_backend_can_take_an_episodes_scene() -> None:
    backend = SimBackend.load(SimBackendConfig(episode_seed=3, episode_index=1))
    from ovamos.world.episodes import make_episode
    _, scene, _ = make_episode(3, 1)
    assert dict(backend.perception.labels.classes) == {o.id: o.cls for o in scene.objects}


def test_the_config_rejects_unknown_keys() -> None:
    with pytest.raises(ValidationError):
        PerceptionServiceConfig.model_validate({"backend": "sim", "replica": 2})
    with pytest.raises(ValidationError):
        PerceptionServiceConfig.model_validate({"hf": {"itm_dir": "x", "box_thresh": 0.3}})
    with pytest.raises(ValidationError):
        HfBackendConfig(prompt="no placeholder")


def _write(directory, files: dict[str, str]) -> None:
    directory.mkdir(parents=True)
    for name, text in files.items():
        (directory / name).write_text(text)


def test_missing_or_incomplete_model_directories_say_what_to_download(tmp_path) -> None:
    complete = {"config.json": json.dumps({"model_type": "sam"}), "model.safetensors": "",
                "preprocessor_config.json": "{}"}
    _write(tmp_path / "sam", complete)
    _write(tmp_path / "dino", {"config.json": json.dumps({"model_type": "grounding-dino"})})
    config = HfBackendConfig(itm_dir=tmp_path / "nowhere", detector_dir=tmp_path / "dino",
                             segmenter_dir=tmp_path / "sam")
    with pytest.raises(ModelFilesError) as err:
        HfBackend.load(config)
    message = str(err.value)
    assert f"{tmp_path / 'nowhere'} does not exist" in message
    assert "Salesforce/blip-itm-base-coco" in message and "hf.itm_dir" in message
    assert "GroundingDINO weights in" in message and "incomplete" in message
    assert "model.safetensors or pytorch_model.bin" in message and "tokenizer.json or vocab.txt" in message
    assert "IDEA-Research/grounding-dino-tiny" in message
    assert len(message.splitlines()) == 2  # SAM's directory is complete
    wrong = HfBackendConfig(itm_dir=tmp_path / "sam", detector_dir=tmp_path / "sam",
                            segmenter_dir=tmp_path / "sam")
    with pytest.raises(ModelFilesError, match="holds a 'sam' model, not BLIP ITM"):
        HfBackend.load(wrong)


def test_relative_model_folders_are_in_the_models_folder_never_the_working_directory(tmp_path, monkeypatch) -> None:
    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv(MODELS_ENV, raising=False)
    monkeypatch.setenv("XDG_DATA_HOME", str(tmp_path / "data"))
    config = HfBackendConfig()
    assert config.folder(config.itm_dir) == tmp_path / "data" / "ovamos" / "models" / "blip-itm-base-coco"
    monkeypatch.setenv(MODELS_ENV, str(tmp_path / "weights"))
    assert config.folder(config.segmenter_dir) == tmp_path / "weights" / "sam-vit-base"
    given = HfBackendConfig(models_dir=tmp_path / "mine", detector_dir=tmp_path / "elsewhere" / "dino")
    assert given.folder(given.itm_dir) == tmp_path / "mine" / "blip-itm-base-coco"
    assert given.folder(given.detector_dir) == tmp_path / "elsewhere" / "dino"  # absolute: as given
    with pytest.raises(ModelFilesError, match=f"{tmp_path / 'weights' / 'blip-itm-base-coco'} does not exist"):
        HfBackend.load(config)


def test_a_sharded_checkpoint_needs_every_shard(tmp_path) -> None:
    index = {"weight_map": {"a": "model-1.safetensors", "b": "model-2.safetensors"}}
    files = {"config.json": json.dumps({"model_type": "sam"}), "preprocessor_config.json": "{}",
             "model.safetensors.index.json": json.dumps(index), "model-1.safetensors": ""}
    _write(tmp_path / "sam", files)
    from ovamos.services.perception.hf.loading import SEGMENTER, model_type
    with pytest.raises(ModelFilesError, match="incomplete"):
        model_type(SEGMENTER, tmp_path / "sam")
    (tmp_path / "sam" / "model-2.safetensors").write_text("")
    assert model_type(SEGMENTER, tmp_path / "sam") == "sam"


def test_the_caption_and_its_target_spans() -> None:
    text, spans = caption(["Chair", "potted plant"])
    assert text == "chair . potted plant ."
    assert [text[a:b] for a, b in spans] == ["chair", "potted plant"]


def test_normalised_boxes_become_pixel_boxes_inside_the_image() -> None:
    normalised = np.array([[0.5, 0.5, 0.5, 0.5], [0.0, 1.0, 0.4, 0.4], [0.5, 0.5, 0.0, 0.0]])
    boxes = pixel_boxes(normalised, 160, 120)
    assert boxes.tolist() == [[40, 30, 120, 90], [0, 96, 32, 120], [80, 60, 81, 61]]


class Recording:
    """An open-vocabulary backend (mock) that scores every target 0.5 and records its calls."""

    name = "recording"

    def __init__(self) -> None:
        self.calls: list[list[tuple[str, int, tuple[str, ...]]]] = []

    def score(self, frame: RgbdFrame, targets: Sequence[str]) -> dict[str, float]:
        return {t: 0.5 for t in targets}

    def detect(self, frame: RgbdFrame, targets: Sequence[str]) -> list:
        return []

    def process(self, jobs: Sequence[Job], detect: bool) -> list[Seen]:
        self.calls.append([(job.robot_id, job.frame.seq, job.targets) for job in jobs])
        return [Seen(self.score(job.frame, job.targets)) for job in jobs]

    def unknown_targets(self, targets: Sequence[str]) -> tuple[tuple[str, ...], str]:
        return (), ""  # any word goes


def core(backend: Recording, robots: Sequence[str] = ("r1",), instance: str = "0",
         rejected: list[str] | None = None, **config: object) -> PerceptionCore:
    return PerceptionCore(PerceptionServiceConfig(**config), backend, robots, instance,
                          logging.getLogger("test"), (rejected if rejected is not None else []).append)


def sent(results: list[tuple[str, PerceptionResult]]) -> list[tuple[str, int, tuple[str, ...]]]:
    return [(robot, r.seq, r.targets) for robot, r in results]


def test_without_a_task_a_frame_gets_an_empty_result_and_no_model_runs(frame) -> None:
    backend = Recording()
    perception = core(backend)
    perception.on_frame("r1", frame.model_copy(update={"seq": 4, "odom_session": "S"}), 0.0)
    [(robot, result)] = perception.poll(0.0)
    assert (robot, result.seq, result.targets, result.scores, result.labels) == ("r1", 4, (), (), ())
    assert result.odom_session == "S" and result.stamp == frame.stamp
    assert backend.calls == [] and perception.poll(0.0) == []  # answered once
    perception.on_task("r1", TaskSpec(task_id="t", targets=("cup",), stamp=0.0), 1.0)
    perception.poll(1.0)
    perception.on_task("r1", TaskSpec(task_id="t", targets=("cup",), stamp=0.0, cancelled=True), 2.0)
    perception.on_frame("r1", frame.model_copy(update={"seq": 5}), 2.0)
    assert sent(perception.poll(2.0)) == [("r1", 5, ())] and len(backend.calls) == 1


def test_a_batch_of_two_robots_runs_once_full_or_once_its_oldest_frame_waited(frame) -> None:
    backend = Recording()
    perception = core(backend, ["r1", "r2"], batch_size=2, batch_wait_ms=500)
    task = TaskSpec(task_id="t", targets=("cup",), stamp=0.0)
    for robot in ("r1", "r2"):
        perception.on_task(robot, task, 0.0)
    perception.on_frame("r1", frame.model_copy(update={"seq": 7}), 10.0)
    assert perception.poll(10.4) == [] and len(perception.slots) == 1  # waits for r2's frame
    perception.on_frame("r2", frame.model_copy(update={"seq": 3}), 10.4)
    assert sent(perception.poll(10.4)) == [("r1", 7, ("cup",)), ("r2", 3, ("cup",))]
    assert backend.calls == [[("r1", 7, ("cup",)), ("r2", 3, ("cup",))]]  # one model call
    assert perception.info()["batches"] == 1 and perception.info()["last_batch"] == 2
    perception.on_frame("r2", frame.model_copy(update={"seq": 4}), 20.0)
    assert perception.poll(20.499) == []
    assert sent(perception.poll(20.5)) == [("r2", 4, ("cup",))]  # alone, after batch_wait_ms


def test_targets_added_re_score_the_latest_frame_once(frame) -> None:
    backend = Recording()
    perception = core(backend, ["r1", "r2"])
    perception.on_frame("r1", frame.model_copy(update={"seq": 5}), 0.0)
    perception.on_frame("r2", frame.model_copy(update={"seq": 9}), 0.0)
    assert sent(perception.poll(0.0)) == [("r1", 5, ()), ("r2", 9, ())]
    task = TaskSpec(task_id="a", targets=("fridge",), stamp=0.0)
    perception.on_task("r1", task, 1.0)
    assert sent(perception.poll(1.0)) == [("r1", 5, ("fridge",))]  # r2's frame is not touched
    perception.on_task("r1", task, 2.0)  # re-sent: nothing new to score
    assert perception.poll(2.0) == []
    perception.on_task("r1", task.model_copy(update={"targets": ("fridge", "cup")}), 3.0)
    assert sent(perception.poll(3.0)) == [("r1", 5, ("fridge", "cup"))]
    assert perception.info()["rescored"] == 2


def test_a_rejected_frame_is_handed_to_the_callable_and_gets_no_result(frame) -> None:
    rejected: list[str] = []
    perception = core(Recording(), rejected=rejected, frames=FrameLimits(min_side=200))
    perception.on_frame("r1", frame, 0.0)
    assert perception.poll(0.0) == [] and rejected == ["r1"]
    info = perception.info()
    assert info["rejected"] == 1 and "within 200..4096" in info["last_rejection"] and info["processed"] == 0


def test_a_replica_takes_only_the_frames_it_owns(frame) -> None:
    perception = core(Recording(), instance="a")
    perception.on_replica("b", True)
    for seq in range(4):
        perception.on_frame("r1", frame.model_copy(update={"seq": seq}), 0.0)
        perception.poll(0.0)
    assert perception.info()["processed"] == 2 and perception.info()["last_seq"] == 2
    assert perception.info()["replicas"] == ["a", "b"] and perception.info()["replica_index"] == 0
    perception.on_replica("b", False)
    perception.on_frame("r1", frame.model_copy(update={"seq": 3}), 0.0)
    assert sent(perception.poll(0.0)) == [("r1", 3, ())]
