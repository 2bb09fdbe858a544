"""One perception service serving several robots, on the fake bus: fairness, targets and batches.

Time is the test's: frames are put on a 30 Hz / 5 Hz schedule and the service
takes its inbox (runs its model) only when the test pumps the network, as a
service busy with a model call would.
"""

from __future__ import annotations

import pytest

from ovamos.services.perception.config import PerceptionServiceConfig
from ovamos.services.perception.fleet import FrameSlots
from ovamos.services.perception.service import PerceptionService
from ovamos.services.perception.sim_backend import SimBackend
from ovamos.shared import keys
from ovamos.shared.fake_bus import FakeNetwork
from ovamos.shared.messages import RgbdFrame, TaskSpec
from tests.perception_helpers import Robot, render_frames
from tests.sim_scenes import two_rooms


@pytest.fixture(scope="module")
def frames() -> list[RgbdFrame]:
    return render_frames(2)


@pytest.fixture(scope="module")
def backend() -> SimBackend:
    return SimBackend(two_rooms())


def start(network: FakeNetwork, backend: SimBackend, **config: object) -> PerceptionService:
    service = PerceptionService(network.bus("fleet", "perception"), PerceptionServiceConfig(**config), backend)
    service.start()
    return service


def test_a_slow_robot_gets_every_frame_processed_beside_a_fast_one(frames, backend) -> None:
    """30 Hz and 5 Hz cameras, a service that gets to its inbox at 10 Hz: the 5 Hz robot's frames
    are all processed, the 30 Hz robot's newest at each turn (the others dropped and counted)."""
    network = FakeNetwork()
    service = start(network, backend, robots=["fast", "slow"])
    fast, slow = Robot(network, "fast"), Robot(network, "slow")
    network.pump()
    for tick in range(60):  # two seconds in 1/30 s steps
        fast.frames.put(frames[0].model_copy(update={"seq": tick}))
        if tick % 6 == 0:
            slow.frames.put(frames[1].model_copy(update={"seq": tick // 6}))
        if tick % 3 == 2:
            network.pump()
    network.pump()
    assert [r.seq for r in slow.results] == list(range(10))
    assert [r.seq for r in fast.results] == list(range(2, 60, 3))  # the newest at each turn
    counters = service.bus.counters.snapshot()
    assert counters[keys.rgbd("fast")].dropped == 40 and counters[keys.rgbd("slow")].dropped == 0
    assert service.info()["processed_by_robot"] == {"fast": 20, "slow": 10}


def test_every_robot_has_its_own_targets_and_its_results_on_its_own_key(frames, backend) -> None:
    network = FakeNetwork()
    start(network, backend, robots=["*"])
    robots = {name: Robot(network, name) for name in ("r1", "r2", "r3")}
    network.pump()
    robots["r1"].tasks.put(TaskSpec(task_id="a", targets=("fridge",), stamp=0.0))
    robots["r2"].tasks.put(TaskSpec(task_id="b", targets=("cup", "fridge"), stamp=0.0))
    for i, robot in enumerate(robots.values()):
        robot.frames.put(frames[0].model_copy(update={"seq": 100 + i}))
    network.pump()
    assert {n: [(r.seq, r.targets) for r in robot.results] for n, robot in robots.items()} == {
        "r1": [(100, ("fridge",))], "r2": [(101, ("cup", "fridge"))], "r3": [(102, ())]}


def test_frames_of_several_robots_wait_for_a_batch_and_go_together(frames, backend) -> None:
    network = FakeNetwork()
    service = start(network, backend, robots=["r1", "r2"], batch_size=2, batch_wait_ms=1000)
    r1, r2 = Robot(network, "r1"), Robot(network, "r2")
    network.pump()
    r1.frames.put(frames[0].model_copy(update={"seq": 7}))
    network.pump()
    assert r1.results == [] and len(service.core.slots) == 1  # waits for a second robot's frame
    r2.frames.put(frames[1].model_copy(update={"seq": 3}))
    network.pump()
    assert [r.seq for r in r1.results] == [7] and [r.seq for r in r2.results] == [3]
    assert service.info()["batches"] == 1 and service.info()["last_batch"] == 2


def test_batches_take_the_robots_in_turn() -> None:
    """A robot whose frame waits is served before one served in the previous batch, however
    often that one sends."""
    slots, frame = FrameSlots(), render_frames(1)[0]
    taken: list[str] = []
    for step in range(12):
        for robot in ("a", "b", "c"):
            if robot == "a" or step % 3 == 0:  # a sends at every step, b and c every third
                slots.put(robot, frame, float(step))
        taken += [robot for robot, _ in slots.take(1)]
    assert taken.count("b") == 4 and taken.count("c") == 4 and taken.count("a") == 4
    assert slots.replaced["a"] > 0 and slots.replaced["b"] == 0


def test_the_fleet_benchmark_times_a_step_from_capture_to_the_next_command() -> None:
    from ovamos.bench.fleet import StepClock
    from ovamos.shared.messages import PlanCommand
    clock, frame = StepClock(), render_frames(1)[0]
    clock.on_frame("r1", frame.model_copy(update={"after_action": 3, "stamp": 10.0}))
    clock.on_frame("r1", frame.model_copy(update={"after_action": 3, "stamp": 11.0}))  # re-published
    clock.on_command("r1", PlanCommand(action_id=4, stamp=10.25))  # before the window: not counted
    clock.open = True
    clock.on_frame("r1", frame.model_copy(update={"after_action": 4, "stamp": 12.0}))
    clock.on_command("r1", PlanCommand(action_id=5, stamp=12.5))
    clock.on_command("r1", PlanCommand(action_id=5, stamp=12.8))  # a re-sent copy
    clock.on_command("r2", PlanCommand(action_id=1, stamp=13.0))  # no frame seen before it
    assert clock.decisions == {"r1": 1} and clock.latencies == {"r1": [0.5]}


def test_new_targets_rescore_only_that_robots_latest_frame(frames, backend) -> None:
    network = FakeNetwork()
    service = start(network, backend, robots=["r1", "r2"])
    r1, r2 = Robot(network, "r1"), Robot(network, "r2")
    network.pump()
    r1.frames.put(frames[0].model_copy(update={"seq": 5}))
    r2.frames.put(frames[1].model_copy(update={"seq": 9}))
    network.pump()
    task = TaskSpec(task_id="a", targets=("fridge",), stamp=0.0)
    r1.tasks.put(task)
    r1.tasks.put(task)  # re-sent: nothing new to score
    network.pump()
    assert [(r.seq, r.targets) for r in r1.results] == [(5, ()), (5, ("fridge",))]
    assert [(r.seq, r.targets) for r in r2.results] == [(9, ())]
    assert service.info()["rescored"] == 1
