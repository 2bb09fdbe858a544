"""The rosview service against a mock ROS 2 viewer (bench/ros2_peers/fake_viewer.py, real rclpy in its
own process): the OccupancyGrid agrees with our map (size, resolution, origin, cells), each value
layer has its grid, the path follows odometry, and markers show the goal and the found objects."""

from __future__ import annotations

import time

import numpy as np
import pytest

from ovamos.bench.ros2_peers.nodes import MockNode
from ovamos.services.rosview.config import RosViewConfig
from ovamos.services.rosview.service import RosViewService
from ovamos.shared import keys
from ovamos.shared.fake_bus import FakeBus, FakeNetwork
from ovamos.shared.messages import (
    DecisionTrace,
    Goal,
    MapSnapshot,
    ObjectInstance,
    Odometry,
    TaskEvent,
    TaskStatus,
    TraceOption,
)
from tests.polling import wait_for

H, W = 40, 60


def snapshot() -> MapSnapshot:
    obstacle = np.zeros((H, W), bool)
    obstacle[0, :] = True  # the wall at the map's bottom row (y = origin y)
    explored = np.zeros((H, W), bool)
    explored[:20, :] = True
    values = np.zeros((1, H, W), np.float32)
    values[0, 10, 30] = 0.8
    return MapSnapshot(seq=3, after_action=3, stamp=1.0, resolution=0.05, origin=(-1.0, 2.0), layers=("cup",),
                       objects=(ObjectInstance(label="cup", x=0.5, y=2.4, score=0.9, hits=3, confirmed=True),),
                       obstacle=obstacle, explored=explored, counts=np.ones((1, H, W), np.uint16), values=values,
                       frontiers=np.array([[0.2, 3.0]]))


TRACE = DecisionTrace(task_id="t1", step=4, stamp=1.0, map_seq=3, robot_x=0.0, robot_y=2.5, remaining=(),
                      options=(TraceOption(kind="candidate", x=0.4, y=2.6, value=0.5),),
                      goal=Goal(kind="object", x=0.5, y=2.4, label="cup"), reason="the cup")


def _rosview() -> tuple[FakeNetwork, RosViewService, FakeBus]:
    """The service started on a fake network, publishing at 10 Hz, and a bus to feed it."""
    net = FakeNetwork()
    service = RosViewService(net.bus("r1", "rosview"), RosViewConfig(publish_hz=10))
    service.start()
    return net, service, net.bus("r1", "tester")


def test_rviz_gets_the_map_the_path_and_the_marks() -> None:
    viewer = MockNode("fake_viewer.py", "--layer", "cup")
    net, service, tester = _rosview()
    maps, odom, traces = (tester.publisher(keys.map_snapshot("r1"), MapSnapshot),
                          tester.publisher(keys.odom("r1"), Odometry),
                          tester.publisher(keys.plan_trace("r1"), DecisionTrace))
    trace = TRACE

    def seen(topic: str) -> list[dict]:
        return [line for line in viewer.lines() if line["topic"] == topic]
    try:
        deadline, k = time.monotonic() + 30, 0
        topics = ("/ovamos/map", "/ovamos/value/cup", "/ovamos/path", "/ovamos/markers")
        while time.monotonic() < deadline and not (all(seen(t) for t in topics) and k >= 8
                                                   and seen("/ovamos/path")[-1]["poses"][-1] == [0.5, 2.5]):
            k += 1
            maps.put(snapshot())
            odom.put(Odometry(seq=k, stamp=float(k), x=0.1 * min(k, 5), y=2.5, yaw=0.0))
            traces.put(trace)
            net.pump()
            service.tick()
            time.sleep(0.1)  # the service's publish rate
    finally:
        service.stop()
        viewer.close()
    assert all(seen(t) for t in topics), ({t: len(seen(t)) for t in topics}, viewer.lines()[-3:])
    grid = seen("/ovamos/map")[-1]
    assert (grid["width"], grid["height"], grid["origin"]) == (W, H, [-1.0, 2.0])
    assert grid["resolution"] == pytest.approx(0.05)  # a float32 in the message
    assert grid["frame"] == "odom" and grid["first_row_occupied"] == W  # row 0 is y = origin: ours too
    assert (grid["occupied"], grid["free"], grid["unknown"]) == (W, 19 * W, 20 * W)
    value = seen("/ovamos/value/cup")[-1]
    assert value["max"] == 100 and value["unknown"] == 20 * W
    path = seen("/ovamos/path")[-1]["poses"]
    assert path[0] == [0.1, 2.5] and path[-1] == [0.5, 2.5] and len(path) == 5  # one pose a step
    marked = {(m[0], round(m[1], 2), round(m[2], 2), m[3]) for m in seen("/ovamos/markers")[-1]["marks"]}
    assert {("goal", 0.5, 2.4, ""), ("confirmed", 0.5, 2.4, ""), ("frontier", 0.2, 3.0, ""),
            ("candidate", 0.4, 2.6, "")} <= marked
    assert ("goal/label", 0.5, 2.4, "cup") in marked and ("confirmed/label", 0.5, 2.4, "cup") in marked
    assert service.info()["published"]["map"] >= 1


def test_a_late_viewer_gets_the_marks_and_what_the_task_drops_goes_from_ros_too() -> None:
    net, service, tester = _rosview()
    maps, traces, events = (tester.publisher(keys.map_snapshot("r1"), MapSnapshot),
                            tester.publisher(keys.plan_trace("r1"), DecisionTrace),
                            tester.publisher(keys.task_events("r1"), TaskEvent))
    viewer = None
    try:
        maps.put(snapshot())
        traces.put(TRACE)
        net.pump()
        service.tick()  # published once, before any viewer
        assert service.published["markers"] == 1
        viewer = MockNode("fake_viewer.py", "--layer", "cup")

        def latest(topic: str) -> dict | None:
            return next((line for line in reversed(viewer.lines()) if line["topic"] == topic), None)

        marks = wait_for(lambda: (m := latest("/ovamos/markers")) and m["marks"], 30, "the marks, joining late")
        shown = {m[0] for m in marks}
        assert shown >= {"goal", "candidate", "confirmed"}
        assert wait_for(lambda: latest("/ovamos/value/cup"), 30, "the value layer")["width"] == W
        events.put(TaskEvent(task_id="t1", status=TaskStatus.DONE, targets=("cup",), steps=5, distance_m=1.0,
                             stamp=2.0))
        empty = np.zeros((0, H, W), np.float32)
        maps.put(snapshot().model_copy(update={"layers": (), "values": empty, "counts": empty.astype(np.uint16)}))
        net.pump()
        service.tick()
        kinds = wait_for(lambda: (m := latest("/ovamos/markers")) and (k := {x[0] for x in m["marks"]}) != shown and k,
                         30, "the marks without the decision")
        assert "goal" not in kinds and "candidate" not in kinds and "confirmed" in kinds  # found objects stay
        assert wait_for(lambda: (v := latest("/ovamos/value/cup")) and v["width"] == 0 and v, 30,
                        "the dropped layer published empty")["height"] == 0
    finally:
        service.stop()
        if viewer is not None:
            viewer.close()


def test_the_path_follows_the_drivers_odometry_session_and_a_forged_stream_is_not_drawn() -> None:
    """Issue 49: odometry of another session cleared the path and drew its poses. Now a forged stream
    while the driver talks is counted and leaves the path as it was; a restart (the old session
    quiet, a new one streaming) starts a path of the new session."""
    clock = [0.0]
    service = RosViewService(FakeNetwork().bus("r1", "rosview"), RosViewConfig())
    service.sessions = type(service.sessions)(service.config.session_switch, clock=lambda: clock[0])
    for k in range(1, 6):
        clock[0] += 0.1
        service._on_odom(Odometry(seq=k, stamp=clock[0], x=0.1 * k, y=0.0, yaw=0.0, odom_session="A"))
        service._on_odom(Odometry(seq=k, stamp=clock[0], x=9.0, y=9.0, yaw=0.0, odom_session="forged"))
    assert [round(o.x, 1) for o in service._path] == [0.1, 0.2, 0.3, 0.4, 0.5]
    assert service.info()["sessions"]["stray"] == {"odom": 5}
    clock[0] += 1.0  # A quiet: B streams
    for k in range(1, 6):
        clock[0] += 0.1
        service._on_odom(Odometry(seq=k, stamp=clock[0], x=0.1 * k, y=1.0, yaw=0.0, odom_session="B"))
    assert {o.odom_session for o in service._path} == {"B"} and service.sessions.current == "B"
