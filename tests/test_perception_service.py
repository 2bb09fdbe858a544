"""The perception service over real Zenoh on loopback, with the sim backend."""

from __future__ import annotations

import collections
import threading
import time
from collections.abc import Callable, Iterator, Sequence

import numpy as np
import pytest

from ovamos.services.perception.backend import Job, Seen
from ovamos.services.perception.config import PerceptionServiceConfig, SimBackendConfig
from ovamos.services.perception.service import PerceptionService
from ovamos.services.perception.sim_backend import SimBackend
from ovamos.shared import keys
from ovamos.shared.bus import Bus
from ovamos.shared.bus.status import live_services
from ovamos.shared.bus.zconfig import build_config
from ovamos.shared.codec import pack
from ovamos.shared.fake_bus import FakeNetwork
from ovamos.shared.messages import PerceptionResult, RgbdFrame, TaskSpec
from ovamos.shared.service import INFO_EVERY_S
from tests.perception_helpers import ROBOT, Robot, RunningPerception, render_frames
from tests.polling import wait_for
from tests.sim_scenes import two_rooms

pytestmark = pytest.mark.system  # processes, routers, browsers or real-time devices: make test-all


@pytest.fixture(scope="module")
def frames() -> list[RgbdFrame]:
    return render_frames(4)


@pytest.fixture
def sim_config(tmp_path) -> PerceptionServiceConfig:
    scene_file = tmp_path / "scene.json"
    two_rooms().save(scene_file)
    return PerceptionServiceConfig(sim=SimBackendConfig(scene_file=scene_file))


class Sender:
    """Publishes frames and tasks like the robot and the planner, and collects results."""

    def __init__(self, bus: Bus) -> None:
        self.frames = bus.publisher(keys.rgbd(ROBOT), RgbdFrame)
        self.tasks = bus.publisher(keys.task_current(ROBOT), TaskSpec)
        self._lock = threading.Lock()
        self._results: list[PerceptionResult] = []
        bus.subscribe(keys.perception_result(ROBOT), PerceptionResult, self._got)

    def _got(self, result: PerceptionResult) -> None:
        with self._lock:
            self._results.append(result)

    def results(self, seq: int | None = None) -> list[PerceptionResult]:
        with self._lock:
            return [r for r in self._results if seq is None or r.seq == seq]

    def until_result(self, frame: RgbdFrame, what: str, task: TaskSpec | None = None) -> PerceptionResult:
        """Re-send ``frame`` (and ``task``) until a result for it arrives (publishers learn of
        subscribers asynchronously, so a first put can be lost); with a task, until the result
        carries its targets."""
        def arrived() -> PerceptionResult | None:
            if task is not None:
                self.tasks.put(task)
            self.frames.put(frame)
            wanted = () if task is None or task.cancelled else task.targets
            return next((r for r in self.results(frame.seq) if r.targets == wanted), None)
        return wait_for(arrived, what=what)


@pytest.fixture
def sender(inproc_router: str) -> Iterator[Sender]:
    with Bus.open(build_config(connect=[inproc_router]), ROBOT, "test-sender") as bus:
        yield Sender(bus)


def stats(client, instance: str):
    found = [s for s in live_services(client, ROBOT) if s.service == "perception" and s.instance == instance]
    return found[0].stats if found and found[0].stats else None


def test_a_frame_gets_a_result_with_its_seq_for_the_current_targets(inproc_router, sim_config, sender,
                                                                     frames) -> None:
    service = RunningPerception(inproc_router, sim_config)
    try:
        # no task yet: a result without targets, so the map need not wait for one
        idle = sender.until_result(frames[1], "a result without a task")
        assert idle.targets == () and idle.scores == () and idle.labels == ()
        assert idle.stamp == frames[1].stamp
        task = TaskSpec(task_id="t1", targets=("fridge", "cup"), stamp=0.0)
        result = sender.until_result(frames[0], "a result for the task's targets", task)
        direct = SimBackend(two_rooms(), config=sim_config.sim.perception)
        assert result.score_map() == direct.score(frames[0], task.targets)
        expected = direct.detect(frames[0], task.targets)
        assert result.labels == tuple(d.label for d in expected)
        assert all(np.array_equal(a.mask, b.mask) for a, b in zip(result.detections(), expected))
        assert result.masks.shape[1:] == frames[0].depth.shape
        cancelled = task.model_copy(update={"cancelled": True})
        done = sender.until_result(frames[2], "a result after the task was cancelled", cancelled)
        assert done.targets == ()
    finally:
        service.close()


def test_new_targets_re_score_the_latest_frame(inproc_router, sim_config, sender, frames) -> None:
    """The robot stands still when a task starts: the frame in front of it gets a second result,
    for the task's targets, without a new frame; the same targets again do not re-score it."""
    service = RunningPerception(inproc_router, sim_config)
    try:
        latest = frames[3].model_copy(update={"odom_session": "S"})
        idle = sender.until_result(latest, "a result without a task")
        assert idle.targets == () and idle.odom_session == "S"
        # until_result may have sent the frame more than once: let every copy get its result first,
        # or a late copy is scored for the task's targets too and looks like a second re-score
        settled(lambda: len(sender.results(latest.seq)), "every copy of the frame answered")
        task = TaskSpec(task_id="t1", targets=("fridge",), stamp=0.0)

        def rescored(targets: tuple[str, ...]) -> PerceptionResult | None:
            sender.tasks.put(task)  # no frame: only the target list changes
            return next((r for r in sender.results(latest.seq) if r.targets == targets), None)
        result = wait_for(lambda: rescored(("fridge",)), what="the latest frame re-scored for the task")
        direct = SimBackend(two_rooms(), config=sim_config.sim.perception)
        assert result.score_map() == direct.score(latest, task.targets) and result.odom_session == "S"
        assert result.stamp == latest.stamp
        for _ in range(3):
            sender.tasks.put(task)  # re-published: the same targets
        task = task.model_copy(update={"targets": ("fridge", "cup")})
        wait_for(lambda: rescored(("fridge", "cup")), what="re-scored for an added target")
        assert [r.targets for r in sender.results(latest.seq) if r.targets] == [("fridge",), ("fridge", "cup")]
    finally:
        service.close()


def settled(read: Callable[[], object], what: str = "the services' info settled") -> object:
    """``read()`` once it gave the same value twice a refresh of the services' info apart (the
    info in their stats is a snapshot, refreshed every INFO_EVERY_S while they are idle; results
    still in flight arrive well within that)."""
    last: list[object] = [read()]

    def same() -> bool:
        time.sleep(INFO_EVERY_S + 0.1)
        now = read()
        if now == last[0]:
            return True
        last[0] = now
        return False
    wait_for(same, what=what)
    return last[0]


def test_two_replicas_process_every_frame_of_a_burst_exactly_once(inproc_router, sim_config, sender,
                                                                   client, frames) -> None:
    # room for the whole burst: this test is about the split, not about dropping stale frames
    config = sim_config.model_copy(update={"queue_frames": 64})
    replicas = [RunningPerception(inproc_router, config, name) for name in ("a", "b")]
    try:
        wait_for(lambda: all((s := stats(client, n)) and s.info.get("replicas") == ["a", "b"]
                             for n in ("a", "b")), what="both replicas see each other")
        sender.until_result(frames[0], "replica a answers")        # seq 0: a
        sender.until_result(frames[1], "replica b answers")        # seq 1: b
        before = settled(lambda: {n: stats(client, n).info["processed"] for n in ("a", "b")})
        burst = range(2, 42)
        for seq in burst:
            sender.frames.put(frames[seq % len(frames)].model_copy(update={"seq": seq}))

        def processed() -> dict[str, int]:
            return {n: stats(client, n).info["processed"] - before[n] for n in ("a", "b")}
        wait_for(lambda: sum(processed().values()) >= len(burst), what="the burst processed")
        wait_for(lambda: {r.seq for r in sender.results()} >= set(burst), what="every result received")
        assert processed() == {"a": 20, "b": 20}
        counts = collections.Counter(r.seq for r in sender.results() if r.seq in burst)
        assert counts == {seq: 1 for seq in burst}
    finally:
        for replica in replicas:
            replica.close()


def test_a_replica_still_loading_its_models_gets_no_frames(inproc_router, sim_config, sender,
                                                          client, frames) -> None:
    """A replica's session (and ``alive`` token) is up before its backend loads; until it is
    started, the running replica keeps every frame instead of skipping the loading one's share."""
    running = RunningPerception(inproc_router, sim_config, "a")
    try:
        with Bus.open(build_config(connect=[inproc_router]), ROBOT, "perception", "b"):  # loading
            wait_for(lambda: {(s.service, s.instance) for s in live_services(client, ROBOT)}
                     >= {("perception", "a"), ("perception", "b")}, what="both perception sessions")
            for seq in range(4):
                sender.until_result(frames[seq], f"frame {seq} answered by the ready replica")
            assert stats(client, "a").info["replicas"] == ["a"]
    finally:
        running.close()


def test_a_target_the_simulated_house_cannot_hold_is_named_in_the_info_and_the_rest_scored(
        inproc_router, sim_config, sender, client, frames) -> None:
    """``candel`` is no class of the simulated house: the info names it and the closest class (the
    planner fails the task with it), and the frames are scored for the other targets (the backend
    raised on every frame before, so no result came at all)."""
    service = RunningPerception(inproc_router, sim_config)
    try:
        task = TaskSpec(task_id="t1", targets=("fridge", "candel"), stamp=0.0)

        def scored() -> PerceptionResult | None:
            sender.tasks.put(task)
            sender.frames.put(frames[0])
            return next((r for r in sender.results(frames[0].seq) if r.targets), None)
        assert wait_for(scored, what="a result for the known target").targets == ("fridge",)
        s = wait_for(lambda: (s := stats(client, "0")) and s.info["unknown_targets"] and s,
                     what="the unknown target in the info")
        (entry,) = s.info["unknown_targets"].values()
        assert list(s.info["unknown_targets"]) == [ROBOT] and entry["targets"] == ["candel"]
        assert entry["reason"].startswith("unknown target 'candel' for the simulated house: "
                                          "did you mean 'candle'? it can have: ")
        sender.tasks.put(task.model_copy(update={"cancelled": True}))
        wait_for(lambda: not stats(client, "0").info["unknown_targets"], what="forgotten with the task")
    finally:
        service.close()


class OpenVocabulary:
    """A stand-in (mock) for a real model: any word is a target it may see, so it names none."""

    name = "open"

    def score(self, frame: RgbdFrame, targets: tuple[str, ...]) -> dict[str, float]:
        return {t: 0.5 for t in targets}

    def detect(self, frame: RgbdFrame, targets: tuple[str, ...]) -> list:
        return []

    def process(self, jobs: list[Job], detect: bool) -> list[Seen]:
        return [Seen(self.score(job.frame, job.targets)) for job in jobs]

    def unknown_targets(self, targets: Sequence[str]) -> tuple[tuple[str, ...], str]:
        return (), ""  # any word goes


def test_an_open_vocabulary_backend_takes_any_word(frames) -> None:
    network = FakeNetwork()
    service = PerceptionService(network.bus(ROBOT, "perception"), PerceptionServiceConfig(), OpenVocabulary())
    service.start()
    robot = Robot(network)
    network.pump()
    robot.tasks.put(TaskSpec(task_id="t1", targets=("candel",), stamp=0.0))
    robot.frames.put(frames[0])
    network.pump()
    assert service.info()["unknown_targets"] == {}
    assert [r.score_map() for r in robot.results] == [{"candel": 0.5}]


def test_unusable_frames_are_rejected_and_counted_and_the_service_goes_on(inproc_router, sim_config,
                                                                          sender, client, frames) -> None:
    service = RunningPerception(inproc_router, sim_config.model_copy(update={"queue_frames": 8}))
    try:
        # with targets, so that the backend runs (without any, no model looks at a frame)
        task = TaskSpec(task_id="t1", targets=("fridge",), stamp=0.0)
        sender.until_result(frames[0], "the service answers", task)
        good = frames[1]
        # undecodable: float rgb (the bus drops it before the service sees it)
        bad_dtype = pack(RgbdFrame.KIND, RgbdFrame.VERSION,
                         good.model_dump_json(exclude=set(RgbdFrame.ARRAYS)).encode(),
                         {"rgb": good.rgb.astype(np.float32), "depth": good.depth})
        client.put(keys.rgbd(ROBOT), bytes(bad_dtype))
        # decodable but too small for the models, and a camera frame for the sim backend
        tiny = RgbdFrame(seq=50, stamp=0.0, intrinsics=good.intrinsics, rgb=np.zeros((8, 8, 3), np.uint8),
                         depth=np.ones((8, 8), np.float32), instance_ids=np.zeros((8, 8), np.int32))
        sender.frames.put(tiny)
        sender.frames.put(good.model_copy(update={"seq": 51, "instance_ids": None}))
        after = sender.until_result(good.model_copy(update={"seq": 52}), "a result after the bad frames",
                                    task)
        assert after.seq == 52 and after.targets == ("fridge",)
        # the counters are live, the info a snapshot the service refreshes between events
        s = wait_for(lambda: (s := stats(client, "0")) and s.counters[keys.rgbd(ROBOT)].malformed == 3
                     and s.info["rejected"] == 2 and s, what="three frames counted as malformed")
        assert "instance ids" in s.info["last_rejection"]
        assert not sender.results(50) and not sender.results(51)
    finally:
        service.close()
