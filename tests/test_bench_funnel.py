"""The per-target funnel of the search benchmark (bench/funnel.py): stages are first steps, only
true detections and true map objects count, and a miss is the first stage never reached."""

from __future__ import annotations

import numpy as np

from ovamos.bench.funnel import FunnelRecorder, StopRecord, TargetFunnel
from ovamos.bench.jobs import Job, run_job
from ovamos.shared.detections import Detection
from ovamos.shared.messages import Intrinsics, Miss, ObjectInstance, RgbdFrame
from tests.sim_scenes import two_rooms


def frame_showing(ids: dict[int, slice]) -> RgbdFrame:
    """A 20 x 20 frame whose columns ``ids[k]`` show instance k (the rest: room 0's floor)."""
    instance_ids = np.full((20, 20), -1, np.int32)
    for instance, cols in ids.items():
        instance_ids[:, cols] = instance
    return RgbdFrame(seq=0, stamp=0.0, intrinsics=Intrinsics(fx=10, fy=10, cx=10, cy=10),
                     rgb=np.zeros((20, 20, 3), np.uint8), depth=np.ones((20, 20), np.float32),
                     instance_ids=instance_ids)


def detection(label: str, frame: RgbdFrame, instance: int) -> Detection:
    return Detection(label, 0.8, (0, 0, 20, 20), frame.instance_ids == instance)


def test_a_miss_is_the_first_stage_never_reached() -> None:
    assert TargetFunnel(label="cup").miss is Miss.NEVER_SEEN
    assert TargetFunnel(label="cup", seen=3).miss is Miss.NOT_DETECTED
    assert TargetFunnel(label="cup", seen=3, detected=5).miss is Miss.NOT_CONFIRMED
    assert TargetFunnel(label="cup", seen=3, detected=5, confirmed=9).miss is Miss.NOT_REACHED
    assert TargetFunnel(label="cup", seen=3, wrong_stops=1).miss is Miss.WRONG_STOP
    assert TargetFunnel(label="cup", seen=3, detected=5, confirmed=9, stopped=20).miss is None


def test_only_true_detections_and_true_map_objects_count() -> None:
    scene = two_rooms()  # 1 fridge (0.4, 3.0), 2 table, 3 cup on the table, 4 fridge (5.6, 3.4)
    recorder = FunnelRecorder(scene, ["cup", "fridge"])
    frame = frame_showing({2: slice(0, 10), 1: slice(10, 20)})
    # The table is reported as a cup (a false detection); the cup itself is not in view.
    recorder.frame(4, frame, {"table", "fridge"}, [detection("cup", frame, 2), detection("fridge", frame, 1)])
    recorder.map(4, [ObjectInstance(label="cup", x=2.0, y=3.0, score=0.9, hits=3, confirmed=True),
                     ObjectInstance(label="fridge", x=0.8, y=3.0, score=0.9, hits=1, confirmed=False)])
    recorder.map(6, [ObjectInstance(label="fridge", x=0.8, y=3.0, score=0.9, hits=2, confirmed=True)])
    recorder.frame(7, frame, {"fridge"}, [detection("fridge", frame, 1)])  # later steps keep the first
    wrong = StopRecord(step=9, label="cup", x=0.0, y=0.0, success=False, distance_m=4.0)
    cup, fridge = recorder.result([wrong])
    assert (cup.seen, cup.detected, cup.confirmed, cup.wrong_stops) == (None, None, None, 1)
    assert (fridge.seen, fridge.detected, fridge.confirmed, fridge.stopped) == (4, 4, 6, None)
    assert (cup.miss, fridge.miss) == (Miss.WRONG_STOP, Miss.NOT_REACHED)


def test_an_episode_records_each_found_targets_stages_in_order() -> None:
    result = run_job(Job("ovamos", 0, 2))  # all three targets found in under 200 steps
    assert result.success and [f.label for f in result.funnel] == list(result.targets)
    for f in result.funnel:
        assert f.seen is not None and f.detected is not None and f.confirmed is not None
        assert f.seen <= f.detected <= f.confirmed < f.stopped and f.miss is None
    assert sorted(f.stopped for f in result.funnel) == [s.step for s in result.stops]
