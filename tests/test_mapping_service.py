"""The mapping service over real Zenoh sessions: matching by seq, timeouts, snapshots, checkpoints."""

from __future__ import annotations

import itertools
import math
import time
from collections.abc import Iterator

import numpy as np
import pytest
import zenoh

from ovamos.services.mapping.checkpoint import load_checkpoint
from ovamos.services.mapping.config import MappingServiceConfig
from ovamos.services.mapping.service import MappingService
from ovamos.shared import keys
from ovamos.shared.bus import Bus
from ovamos.shared.bus.status import live_services
from ovamos.shared.bus.zconfig import build_config
from ovamos.shared.messages import MapSnapshot, Odometry, PerceptionResult, RgbdFrame
from ovamos.world.render import SceneRenderer
from tests.polling import wait_for
from tests.service_helpers import Running
from tests.sim_scenes import two_rooms

pytestmark = pytest.mark.system  # processes, routers, browsers or real-time devices: make test-all

ROBOT = "r1"


@pytest.fixture(scope="module")
def frames() -> list[RgbdFrame]:
    with SceneRenderer(two_rooms(), 160, 120) as renderer:
        return [renderer.render(1.5, 2.0, i * math.pi / 3, seq=i) for i in range(6)]


@pytest.fixture
def service(inproc_router: str, tmp_path) -> Iterator[tuple[str, MappingServiceConfig]]:
    config = MappingServiceConfig(grid_cells=300, publish_hz=10, match_timeout_s=0.5,
                                  checkpoint_path=tmp_path / "map.ckpt", checkpoint_every_s=0.5)
    running = Running(MappingService, inproc_router, config)
    yield inproc_router, config
    running.close()


@pytest.fixture
def sender(inproc_router: str) -> Iterator[Bus]:
    with Bus.open(build_config(connect=[inproc_router]), ROBOT, "test-sender") as bus:
        yield bus


def query_snapshot(session: zenoh.Session) -> MapSnapshot | None:
    for reply in session.get(keys.map_snapshot(ROBOT), timeout=2.0):
        if reply.ok is not None:
            return MapSnapshot.from_bytes(reply.ok.payload.to_bytes())
    return None


def result_for(frame: RgbdFrame, scores: dict[str, float]) -> PerceptionResult:
    return PerceptionResult.build(frame.seq, frame.stamp, scores, [], frame.depth.shape)


def test_frames_and_results_are_matched_by_seq(service, sender, client, frames) -> None:
    pub_f = sender.publisher(keys.rgbd(ROBOT), RgbdFrame)
    pub_r = sender.publisher(keys.perception_result(ROBOT), PerceptionResult)
    wait_for(lambda: query_snapshot(client), what="the service answers")
    # result before its frame (repeated until both publishers know the service), then a frame
    # before its result
    first = result_for(frames[0], {"fridge": 0.6})
    wait_for(lambda: pub_r.put(first) or pub_f.put(frames[0]) or (s := query_snapshot(client))
             and s.seq == 0 and s.layers == ("fridge",), what="seq 0 with its result")
    pub_f.put(frames[1])
    pub_r.put(result_for(frames[1], {"fridge": 0.3, "cup": 0.2}))
    snap = wait_for(lambda: (s := query_snapshot(client)) and s.seq == 1 and s, what="seq 1")
    assert snap.layers == ("fridge", "cup")
    assert snap.confidence is None  # published snapshots leave them out
    assert snap.values[0].max() == pytest.approx(0.6) and snap.explored.any()
    # the target list shrinks: the layer goes
    pub_f.put(frames[2])
    pub_r.put(result_for(frames[2], {"cup": 0.2}))
    snap = wait_for(lambda: (s := query_snapshot(client)) and s.seq == 2 and s, what="seq 2")
    assert snap.layers == ("cup",)


def test_a_frame_without_result_still_maps_after_the_timeout(service, sender, client, frames) -> None:
    pub_f = sender.publisher(keys.rgbd(ROBOT), RgbdFrame)
    wait_for(lambda: query_snapshot(client), what="the service answers")
    # repeated puts (a new publisher learns of subscribers asynchronously); a repeated frame
    # keeps its first arrival time, so the timeout still runs out
    wait_for(lambda: pub_f.put(frames[3]) or (s := query_snapshot(client)) and s.seq == 3,
             what="frame 3 fused without a result")
    snap = query_snapshot(client)
    assert snap.explored.any() and snap.obstacle.any() and snap.layers == ()


def test_snapshots_are_published_and_malformed_input_is_counted(service, sender, client,
                                                                 frames) -> None:
    got: list[MapSnapshot] = []
    sender.subscribe(keys.map_snapshot(ROBOT), MapSnapshot, got.append)
    pub_f = sender.publisher(keys.rgbd(ROBOT), RgbdFrame)
    wait_for(lambda: query_snapshot(client), what="the service answers")
    client.put(keys.perception_result(ROBOT), b"garbage")
    wait_for(lambda: pub_f.put(frames[4]) or any(s.seq == 4 for s in got), what="a published snapshot")

    def mapping_stats():
        (svc,) = [s for s in live_services(client, ROBOT) if s.service == "mapping"]
        return svc.stats

    assert mapping_stats().counters[keys.perception_result(ROBOT)].malformed == 1
    # the info is a snapshot the service's loop refreshes every 0.5 s
    wait_for(lambda: mapping_stats().info["seq"] == 4, what="the service's info shows frame 4")


SEQ = itertools.count(1)  # a driver's odometry seq, and a camera's frame seq, only ever grow


def in_session(frame: RgbdFrame, session: str) -> RgbdFrame:
    return frame.model_copy(update={"odom_session": session})


def streamed(frame: RgbdFrame, session: str) -> RgbdFrame:
    """``frame`` as the next of a camera's stream posed in ``session`` (a higher seq each call)."""
    return frame.model_copy(update={"odom_session": session, "seq": next(SEQ)})


def odometry(session: str) -> Odometry:
    """The next message of a driver's odometry stream in ``session``."""
    return Odometry(seq=next(SEQ), stamp=time.time(), odom_session=session, x=1.5, y=2.0, yaw=0.0)


def mapping_info(client: zenoh.Session) -> dict:
    (svc,) = [s for s in live_services(client, ROBOT) if s.service == "mapping"]
    return svc.stats.info


def test_a_restarted_service_resumes_its_checkpoint_only_in_the_same_odometry_session(
        inproc_router, tmp_path, sender, client, frames) -> None:
    config = MappingServiceConfig(grid_cells=300, publish_hz=10, match_timeout_s=0.2,
                                  checkpoint_path=tmp_path / "{robot_id}.ckpt", checkpoint_every_s=60)
    first = Running(MappingService, inproc_router, config)
    pub_f = sender.publisher(keys.rgbd(ROBOT), RgbdFrame)
    pub_o = sender.publisher(keys.odom(ROBOT), Odometry)
    wait_for(lambda: pub_f.put(in_session(frames[5], "A")) or (s := query_snapshot(client)) and s.seq == 5,
             what="seq 5")
    before = query_snapshot(client)
    assert before.odom_session == "A"
    first.close()  # writes the checkpoint on shutdown, named for the robot
    checkpoint = tmp_path / f"{ROBOT}.ckpt"
    assert checkpoint.exists()
    # the driver kept running (same session): the checkpoint is resumed
    second = Running(MappingService, inproc_router, config)
    try:
        after = wait_for(lambda: pub_o.put(odometry("A")) or (s := query_snapshot(client)) and s.seq == 5
                         and s, what="the restarted service resumes")
        assert after.odom_session == "A" and np.array_equal(after.explored, before.explored)
    finally:
        second.close()
    # the driver restarted meanwhile (session B): a fresh map; session A's is kept, not fused into
    third = Running(MappingService, inproc_router, config)
    try:
        fresh = wait_for(lambda: pub_o.put(odometry("B")) or (s := query_snapshot(client))
                         and s.odom_session == "B" and s, what="a fresh map of session B")
        assert fresh.seq == -1 and not fresh.explored.any()
        kept = load_checkpoint(tmp_path / f"{ROBOT}.A.ckpt", config)
        assert kept.odom_session == "A" and kept.seq == 5 and np.array_equal(kept.explored, before.explored)
        pub_f.put(in_session(frames[4], "A"))  # posed with session A's odometry: dropped, counted
        wait_for(lambda: mapping_info(client)["other_session_dropped"].get("frame", 0) >= 1,
                 what="the frame of session A counted")
        assert query_snapshot(client).seq == -1
        pub_f.put(in_session(frames[3], "B"))
        wait_for(lambda: query_snapshot(client).seq == 3, what="session B's frame fused")
    finally:
        third.close()
    assert load_checkpoint(checkpoint, config).odom_session == "B"
    checkpoint.write_bytes(b"not a checkpoint")
    fourth = Running(MappingService, inproc_router, config)
    try:
        fresh = wait_for(lambda: pub_o.put(odometry("B")) or (s := query_snapshot(client))
                         and s.odom_session == "B" and s, what="a fresh map after a corrupt checkpoint")
        assert fresh.seq == -1 and not fresh.explored.any()
    finally:
        fourth.close()


def test_a_new_odometry_session_starts_a_fresh_map_and_keeps_the_old_one(service, sender, client,
                                                                          frames, tmp_path) -> None:
    pub_f = sender.publisher(keys.rgbd(ROBOT), RgbdFrame)
    pub_o = sender.publisher(keys.odom(ROBOT), Odometry)
    old = wait_for(lambda: pub_o.put(odometry("A")) or pub_f.put(in_session(frames[2], "A"))
                   or (s := query_snapshot(client)) and s.seq == 2 and s, what="session A's map")
    assert old.odom_session == "A"
    new = wait_for(lambda: pub_o.put(odometry("B")) or (s := query_snapshot(client)) and s.odom_session == "B"
                   and s, what="the driver restarted: session B")
    assert new.seq == -1 and not new.explored.any()
    kept = load_checkpoint(tmp_path / "map.A.ckpt", service[1])
    assert kept.seq == 2 and np.array_equal(kept.explored, old.explored)
    # a restarted driver's first frames may come before its first odometry: a new session too
    newer = wait_for(lambda: pub_f.put(streamed(frames[1], "C")) or (s := query_snapshot(client))
                     and s.odom_session == "C" and s.seq >= 0 and s, what="session C's first frames")
    assert mapping_info(client)["sessions"]["switches"] == 3  # A (the first seen), B, C
    pub_o.put(odometry("B"))  # late, of a session left behind: changes nothing
    pub_f.put(in_session(frames[4], "A"))
    wait_for(lambda: mapping_info(client)["other_session_dropped"].get("frame", 0) >= 1,
             what="session A's frame dropped and counted")
    assert query_snapshot(client).odom_session == "C" and np.array_equal(query_snapshot(client).explored,
                                                                         newer.explored)


def test_a_re_published_frame_and_a_re_scored_result_add_no_update_counts(service, sender, client,
                                                                          frames) -> None:
    pub_f = sender.publisher(keys.rgbd(ROBOT), RgbdFrame)
    pub_r = sender.publisher(keys.perception_result(ROBOT), PerceptionResult)
    wait_for(lambda: pub_f.put(frames[0]) or pub_r.put(result_for(frames[0], {}))
             or (s := query_snapshot(client)) and s.seq == 0, what="frame 0 without targets")
    first = query_snapshot(client)
    # the task starts: perception scores the latest frame again, for the task's targets
    rescored = wait_for(lambda: pub_r.put(result_for(frames[0], {"cup": 0.7}))
                        or (s := query_snapshot(client)) and s.layers == ("cup",) and s, what="re-scored")
    assert rescored.values[0].max() == pytest.approx(0.7)
    # the robot stands still: the frame comes again, its result too
    for _ in range(3):
        pub_f.put(frames[0])
        pub_r.put(result_for(frames[0], {"cup": 0.7}))
    wait_for(lambda: mapping_info(client)["repeated_frames"] >= 1, what="the repeated frame counted")
    last = query_snapshot(client)
    # counts are the layer's own: none before the task, one view of each cell once scored for it
    assert first.counts.shape[0] == 0 and rescored.counts.max() == 1
    assert np.array_equal(last.counts, rescored.counts)


def test_the_map_command_draws_the_current_map(service, sender, client, frames, tmp_path) -> None:
    import subprocess
    import sys

    import cv2
    pub_f = sender.publisher(keys.rgbd(ROBOT), RgbdFrame)
    wait_for(lambda: query_snapshot(client), what="the service answers")
    wait_for(lambda: pub_f.put(frames[0]) or (s := query_snapshot(client)) and s.seq == 0,
             what="frame 0 fused")
    endpoint = service[0]
    out = subprocess.run([sys.executable, "-m", "ovamos.cli", "map", "--robot-id", ROBOT,
                          "--connect", endpoint, "--out", str(tmp_path / "map.png")],
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert cv2.imread(str(tmp_path / "map.png")) is not None
    missing = subprocess.run([sys.executable, "-m", "ovamos.cli", "map", "--robot-id", "nobody",
                              "--connect", endpoint, "--timeout", "1", "--out", str(tmp_path / "x.png")],
                             capture_output=True, text=True, timeout=60)
    assert missing.returncode == 2 and "no mapping service" in missing.stderr


@pytest.mark.parametrize("forged", ["20991231T235959Z-ffffff", ""])
def test_a_forged_odometry_session_mid_task_is_counted_and_ignored(service, sender, client, frames,
                                                                   forged: str) -> None:
    """Issue 33, finding 1: one odometry message of a session mapping had not seen (a made-up one,
    or none) used to become the current session for good, every real frame after it dropped."""
    pub_f = sender.publisher(keys.rgbd(ROBOT), RgbdFrame)
    pub_o = sender.publisher(keys.odom(ROBOT), Odometry)
    wait_for(lambda: pub_o.put(odometry("A")) or pub_f.put(in_session(frames[0], "A"))
             or (s := query_snapshot(client)) and s.seq == 0, what="session A's map")
    forger = Odometry(seq=10**6, stamp=time.time() + 10**6, odom_session=forged, x=0.0, y=0.0, yaw=0.0)
    pub_o.put(forger)  # one message, mid-task
    wait_for(lambda: mapping_info(client)["sessions"]["stray"].get("odom", 0) >= 1,
             what="the forged message counted")
    # a forged stream while the real driver still talks is no restart either
    for k in range(20):
        pub_o.put(forger.model_copy(update={"seq": 10**6 + 1 + k}))
        pub_o.put(odometry("A"))
        time.sleep(0.02)  # paces a stream of 50 Hz, as a driver's
    pub_f.put(in_session(frames[1], "A"))  # the real camera's next frame is still fused
    fused = wait_for(lambda: (s := query_snapshot(client)) and s.seq == 1 and s, what="frame 1 fused")
    assert fused.odom_session == "A"
    # odometry is a newest-only input: a forged message right before a real one may never be read;
    # one that is the newest (the real driver still talking just before it) is
    more = iter(range(10**6 + 21, 10**7))
    info = wait_for(lambda: pub_o.put(odometry("A"))
                    or pub_o.put(forger.model_copy(update={"seq": next(more)}))
                    or (i := mapping_info(client)["sessions"])["stray"]["odom"] >= 2 and i,
                    what="the forged stream counted")  # the info is refreshed every 0.5 s
    assert info["session"] == "A" and info["switches"] == 1
    # a real restart still switches: the old session goes quiet and the new one streams
    fresh = wait_for(lambda: pub_o.put(odometry("B")) or (s := query_snapshot(client))
                     and s.odom_session == "B" and s, what="the driver's real restart followed")
    assert fresh.seq == -1
