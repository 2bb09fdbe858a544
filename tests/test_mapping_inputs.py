"""The mapping core without a bus: frames meet their results by seq, wait ``match_timeout_s`` on
the caller's clock, and the checkpoint is written every ``checkpoint_every_s`` and resumed only in
its own odometry session. (tests/test_mapping_service.py covers the same over Zenoh.)"""

from __future__ import annotations

import logging
import math
from pathlib import Path

import pytest

from ovamos.services.mapping.checkpoint import load_checkpoint, session_path
from ovamos.services.mapping.config import MappingServiceConfig
from ovamos.services.mapping.core import MappingCore
from ovamos.shared.messages import Odometry, PerceptionResult, RgbdFrame
from ovamos.shared.sessions import SessionSwitch
from ovamos.world.render import SceneRenderer
from tests.sim_scenes import two_rooms

LOG = logging.getLogger("test.mapping")
SESSION = "A"


@pytest.fixture(scope="module")
def frames() -> list[RgbdFrame]:
    with SceneRenderer(two_rooms(), 160, 120) as renderer:
        return [renderer.render(1.5, 2.0, i * math.pi / 3, seq=i, odom_session=SESSION) for i in range(4)]


def config(**kw: object) -> MappingServiceConfig:
    return MappingServiceConfig.model_validate({"grid_cells": 300, "match_timeout_s": 1.0, **kw})


def odometry(session: str, seq: int = 1) -> Odometry:
    return Odometry(seq=seq, stamp=0.0, odom_session=session, x=1.5, y=2.0, yaw=0.0)


def result_for(frame: RgbdFrame, scores: dict[str, float]) -> PerceptionResult:
    return PerceptionResult.build(frame.seq, frame.stamp, scores, [], frame.depth.shape, frame.odom_session)


def test_a_frame_waits_for_its_result_until_the_match_timeout(frames: list[RgbdFrame]) -> None:
    core = MappingCore(config(), LOG, now=0.0)
    assert core.poll(0.0) is None, "nothing is published before the odometry session is known"
    core.on_odom(odometry(SESSION), now=0.0)
    core.on_frame(frames[0], now=0.0)
    first = core.poll(0.5)
    assert first is not None and first.seq == -1 and core.info()["pending_frames"] == 1
    assert core.poll(1.0) is None, "still waiting (the timeout is not over) and nothing changed"
    fused = core.poll(1.01)
    assert fused is not None and fused.seq == 0 and fused.layers == () and fused.explored.any()
    assert core.poll(2.0) is None and core.info()["pending_frames"] == 0


def test_a_result_is_fused_with_its_frame_whichever_comes_first(frames: list[RgbdFrame]) -> None:
    core = MappingCore(config(), LOG, now=0.0)
    core.on_odom(odometry(SESSION), now=0.0)
    core.on_result(result_for(frames[0], {"fridge": 0.6}))
    core.on_frame(frames[0], now=0.0)
    core.on_frame(frames[1], now=0.0)
    core.on_result(result_for(frames[1], {"fridge": 0.3, "cup": 0.2}))
    snapshot = core.poll(0.1)  # before any timeout: both were fused when their pair came
    assert snapshot is not None and snapshot.seq == 1 and snapshot.layers == ("fridge", "cup")
    assert snapshot.values[0].max() == pytest.approx(0.6)
    assert core.info()["pending_frames"] == core.info()["pending_results"] == 0


def test_at_most_max_pending_results_wait_for_their_frames_the_newest(frames: list[RgbdFrame]) -> None:
    core = MappingCore(config(max_pending=2), LOG, now=0.0)
    core.on_odom(odometry(SESSION), now=0.0)
    for frame in frames[1:4]:
        core.on_result(result_for(frame, {"cup": 0.5}))
    assert core.info()["pending_results"] == 2
    core.on_frame(frames[1], now=0.0)  # its result was the oldest: dropped, so the frame waits
    assert core.info()["pending_frames"] == 1
    core.on_frame(frames[3], now=0.0)
    assert core.state.seq == 3 and core.state.layers == ("cup",)


def test_the_checkpoint_is_written_on_the_period_and_resumed_only_in_its_session(
        frames: list[RgbdFrame], tmp_path: Path) -> None:
    path = tmp_path / "map.ckpt"
    settings = config(checkpoint_path=path, checkpoint_every_s=5.0,
                      session_switch=SessionSwitch(messages=1, min_span_s=0.0, quiet_s=0.0))
    core = MappingCore(settings, LOG, now=0.0)
    core.on_odom(odometry(SESSION), now=0.0)  # the session is known: its (empty) map is the file's
    assert load_checkpoint(path, settings).seq == -1
    core.on_frame(frames[2], now=0.0)
    core.on_result(result_for(frames[2], {}))
    core.poll(4.9)
    assert load_checkpoint(path, settings).seq == -1, "not yet due"
    core.poll(5.0)
    assert load_checkpoint(path, settings).seq == 2

    resumed = MappingCore(settings, LOG, now=10.0)
    resumed.on_odom(odometry(SESSION), now=10.0)
    assert resumed.state.seq == 2 and resumed.state.odom_session == SESSION

    restarted = MappingCore(settings, LOG, now=20.0)
    restarted.on_odom(odometry("B"), now=20.0)  # the driver restarted while mapping was down
    assert restarted.state.seq == -1 and restarted.state.odom_session == "B"
    kept = load_checkpoint(session_path(path, SESSION), settings)
    assert kept.seq == 2 and kept.odom_session == SESSION
    restarted.on_frame(frames[3], now=20.0)  # of session A, left behind: dropped and counted
    assert restarted.info()["other_session_dropped"] == {"frame": 1} and restarted.state.seq == -1
