"""The perception service's adapter on the fake bus (no router, no Zenoh): its logic step by step.

Messages are encoded, validated and counted as in production; the handlers
run when the test pumps the network, so each step's effect is checked exactly.
"""

from __future__ import annotations

import numpy as np
import pytest

from ovamos.services.perception.config import PerceptionServiceConfig
from ovamos.services.perception.service import PerceptionService
from ovamos.services.perception.sim_backend import SimBackend
from ovamos.shared import keys
from ovamos.shared.fake_bus import FakeNetwork
from ovamos.shared.messages import FoundObject, RgbdFrame, TaskEvent, TaskSpec, TaskStatus
from tests.perception_helpers import ROBOT, Robot, render_frames
from tests.sim_scenes import two_rooms

FRAME_KEY = keys.rgbd(ROBOT)


@pytest.fixture(scope="module")
def frames() -> list[RgbdFrame]:
    return render_frames(4)


@pytest.fixture(scope="module")
def backend() -> SimBackend:
    return SimBackend(two_rooms())


def start(network: FakeNetwork, backend: SimBackend, instance: str = "0",
          **config: object) -> PerceptionService:
    service = PerceptionService(network.bus(ROBOT, "perception", instance),
                                PerceptionServiceConfig(**config), backend)
    service.start()
    return service


def event(task: TaskSpec, found: tuple[str, ...]) -> TaskEvent:
    return TaskEvent(task_id=task.task_id, status=TaskStatus.SEARCHING, targets=task.targets, steps=1,
                     distance_m=0.0, stamp=1.0,
                     found=tuple(FoundObject(label=label, x=0.0, y=0.0, step=1) for label in found))


def test_results_follow_the_task_and_bad_frames_are_counted(frames, backend) -> None:
    network = FakeNetwork()
    service = start(network, backend)
    robot = Robot(network)
    network.pump()

    # before any task: a result with no scores, so the map need not wait for one
    robot.frames.put(frames[0])
    network.pump()
    [idle] = robot.results
    assert (idle.seq, idle.stamp, idle.targets, idle.labels) == (0, frames[0].stamp, (), ())

    task = TaskSpec(task_id="t1", targets=("fridge", "cup"), stamp=0.0)
    robot.tasks.put(task)
    robot.frames.put(frames[1])
    network.pump()
    # the task re-scores the latest frame (the robot's view when it starts), then the next frame
    rescored, result = robot.results[-2:]
    assert rescored.seq == 0 and rescored.score_map() == backend.score(frames[0], task.targets)
    assert result.seq == 1 and result.score_map() == backend.score(frames[1], task.targets)
    expected = backend.detect(frames[1], task.targets)
    assert result.labels == tuple(d.label for d in expected)
    assert all(np.array_equal(a.mask, b.mask) for a, b in zip(result.detections(), expected))

    # a found target is not scored any more; another task's event changes nothing
    robot.events.put(event(task, ("fridge",)))
    robot.events.put(event(task.model_copy(update={"task_id": "other"}), ("cup",)))
    robot.frames.put(frames[2])
    network.pump()
    assert robot.results[-1].seq == 2 and robot.results[-1].targets == ("cup",)
    assert service.info()["targets"] == {"r1": ["cup"]}

    # an undecodable payload (not a frame at all) and a frame too small for the models
    wrong = network.bus(ROBOT, "confused").publisher(FRAME_KEY, TaskSpec)
    wrong.put(task)
    network.pump()
    tiny = RgbdFrame(seq=50, stamp=0.0, intrinsics=frames[0].intrinsics, rgb=np.zeros((8, 8, 3), np.uint8),
                     depth=np.ones((8, 8), np.float32), instance_ids=np.zeros((8, 8), np.int32))
    robot.frames.put(tiny)
    network.pump()
    assert robot.results[-1].seq == 2  # neither was answered
    robot.frames.put(frames[3])
    network.pump()
    assert robot.results[-1].seq == 3 and robot.results[-1].targets == ("cup",)
    assert service.bus.counters.snapshot()[FRAME_KEY].malformed == 2
    info = service.info()
    assert info["rejected"] == 1 and "8x8" in info["last_rejection"]
    assert info["processed"] == 5 and info["rescored"] == 1 and info["last_seq"] == 3

    # a cancelled task: results without targets again
    robot.tasks.put(task.model_copy(update={"cancelled": True}))
    robot.frames.put(frames[0].model_copy(update={"seq": 4}))
    network.pump()
    assert robot.results[-1].seq == 4 and robot.results[-1].targets == ()


def test_a_busy_service_keeps_its_newest_frame_and_every_task_message(frames, backend) -> None:
    network = FakeNetwork()
    service = start(network, backend)
    robot = Robot(network)
    network.pump()
    task = TaskSpec(task_id="t1", targets=("fridge", "cup"), stamp=0.0)
    robot.tasks.put(task)
    for seq in range(3):  # nothing is taken meanwhile, as while a model call runs
        robot.frames.put(frames[seq].model_copy(update={"seq": 10 + seq}))
    robot.events.put(event(task, ("cup",)))
    network.pump()
    assert [r.seq for r in robot.results] == [12]
    assert service.bus.counters.snapshot()[FRAME_KEY].dropped == 2
    assert service.info()["targets"] == {"r1": ["fridge"]}  # the event was not dropped


def test_replicas_share_the_frames_and_take_over_when_one_stops(frames, backend) -> None:
    network = FakeNetwork()
    replicas = {name: start(network, backend, name) for name in ("b", "a")}
    robot = Robot(network)
    network.pump()
    assert all(s.info()["replicas"] == ["a", "b"] for s in replicas.values())
    for seq in range(6):
        robot.frames.put(frames[seq % len(frames)].model_copy(update={"seq": seq}))
        network.pump()
    assert [r.seq for r in robot.results] == list(range(6))  # each exactly once
    assert {n: s.info()["processed"] for n, s in replicas.items()} == {"a": 3, "b": 3}

    replicas["b"].stop()  # its ready token goes first: a takes every frame at once
    network.pump()
    replicas["b"].bus.close()  # then its bus, as run_service does
    assert replicas["a"].info()["replicas"] == ["a"]
    for seq in (7, 9):
        robot.frames.put(frames[0].model_copy(update={"seq": seq}))
        network.pump()
    assert [r.seq for r in robot.results][-2:] == [7, 9]
    assert replicas["a"].info()["processed"] == 5
