"""Recording, replay and live view against real processes, files read back with the ``mcap`` library.

One short demo run (the demo's processes, a 40-step task) is recorded, and watched through
``ovamos view`` by a WebSocket client, once for the module; the tests check that file against
what the publishers counted (their final stats) and what the client saw, replay it into a fresh
mapping service, and kill a recorder to read what it left.

The run's Zenoh sessions wait longer than Zenoh's defaults before dropping a message for a
subscriber that is not reading (:data:`PATIENT`): on a loaded 2-core CI machine any process is
now and then descheduled for tens of milliseconds, and the count comparison is about the
recorder, not the scheduler. The test's own subscriber, like the recorder's, takes samples from
a queue in Zenoh (a callback waiting for the GIL stalls the link, and the router drops).
"""

from __future__ import annotations

import asyncio
import json
import subprocess
import sys
import threading
import time
from collections import defaultdict
from dataclasses import dataclass, replace
from pathlib import Path

import foxglove
import numpy as np
import pytest
import websockets
import zenoh
from mcap.exceptions import McapError
from mcap.reader import NonSeekingReader, make_reader

from ovamos.demo import DEMO_EPISODE, DEMO_SEED, SERVICES, demo_entries, write_configs
from ovamos.record.channels import META_KEY, RawChannel, recorded_ports
from ovamos.record.live import LiveRobotError, replay
from ovamos.record.replay import RecordingError, read_raw
from ovamos.record.views import TOPICS
from ovamos.services.gateway.client import GatewayClient
from ovamos.services.mapping.checkpoint import load_checkpoint
from ovamos.services.mapping.config import MappingServiceConfig
from ovamos.shared import keys
from ovamos.shared.bus import Bus
from ovamos.shared.bus.zconfig import build_config, open_session
from ovamos.shared.messages import MapSnapshot, Odometry, ServiceStats
from ovamos.shared.procs import free_port, kill, loopback, start_cli, stop
from ovamos.supervisor import Entry, Supervisor, port_open
from ovamos.world.episodes import make_episode
from tests.polling import wait_for

pytestmark = pytest.mark.system  # processes, routers, browsers or real-time devices: make test-all

ROBOT = "sim"
STEPS = 40
PATIENT = {"scouting": {"multicast": {"enabled": False}},
           "transport": {"link": {"tx": {"queue": {"congestion_control": {"drop": {
               "wait_before_drop": 200_000, "max_wait_before_drop_fragments": 2_000_000}}}}}}}
"""Zenoh settings of the recorded run: wait up to 0.2 s for a message, 2 s for a frame (in
microseconds) before dropping it for a subscriber that is not reading (Zenoh's: 1 ms, 50 ms)."""


@dataclass
class Run:
    path: Path
    configs: dict[str, Path]
    published: dict[str, int]            # key -> messages its publishers counted (final stats)
    received: dict[str, int]             # key -> messages a subscriber of the test got
    task_events: list[bytes]             # payloads on task/events, as a subscriber got them
    advertised: set[str]                 # topics `ovamos view` advertised to a WebSocket client
    viewed: set[str]                     # topics the client got messages on (of VIEWED)


VIEWED = {"/camera/color", "/camera/depth", "/map/obstacle", "/map/explored", "/robot/pose", "/robot/path",
          "/planner/candidates", "/planner/goal", "/log"}


def _ready(session: zenoh.Session, robot: str, service: str) -> bool:
    return any(r.ok is not None for r in session.liveliness().get(keys.ready(robot, service), timeout=1.0))


def _alive(session: zenoh.Session, robot: str, service: str) -> bool:
    return any(r.ok is not None for r in session.liveliness().get(keys.alive(robot, service), timeout=1.0))


@pytest.fixture(scope="module")
def recorded_run(tmp_path_factory: pytest.TempPathFactory) -> Run:
    tmp = tmp_path_factory.mktemp("run")
    http_port, zenoh_port = free_port(), free_port()
    configs = write_configs(tmp / "config", seed=DEMO_SEED, episode=DEMO_EPISODE, robot_id=ROBOT,
                            http_port=http_port)
    path = tmp / "run.mcap"
    zenoh_file = tmp / "patient.json5"
    zenoh_file.write_text(json.dumps(PATIENT))
    router, recorder, *services = [
        replace(e, argv=(*e.argv, "--config" if e.name == "router" else "--zenoh", str(zenoh_file)))
        for e in demo_entries(configs, robot_id=ROBOT, zenoh_port=zenoh_port, record=path)]
    ws_port = free_port()
    viewer = Entry("view", ("view", "--robot-id", ROBOT, "--port", str(ws_port), "--connect", loopback(zenoh_port),
                            "--zenoh", str(zenoh_file)))
    watched: dict[str, set[str]] = {}
    final: dict[str, ServiceStats] = {}
    events: list[bytes] = []
    received: dict[str, int] = defaultdict(int)
    with Supervisor([router, recorder, viewer], log_dir=tmp / "logs"):
        session = open_session(build_config(file=zenoh_file, connect=[loopback(zenoh_port)]))
        try:
            def on_sample(sample: zenoh.Sample) -> None:
                key = str(sample.key_expr)
                if key.split("/")[2] == "stats":  # the services' final counters, put as they close
                    stats = ServiceStats.from_bytes(sample.payload.to_bytes())
                    final[f"{stats.service}/{stats.instance}"] = stats
                    return
                received[key] += 1
                if key == keys.task_events(ROBOT):
                    events.append(sample.payload.to_bytes())

            sub = session.declare_subscriber(keys.robot_all(ROBOT), zenoh.handlers.FifoChannel(256))
            taker = threading.Thread(target=lambda: [on_sample(s) for s in sub])  # until undeclared
            taker.start()
            wait_for(lambda: _ready(session, ROBOT, "recorder"), timeout=60, what="the recorder subscribed")
            wait_for(lambda: _ready(session, ROBOT, "viewer"), timeout=60, what="the viewer subscribed")
            watcher = threading.Thread(target=lambda: watched.update(zip(("advertised", "viewed"), asyncio.run(
                _watch(f"ws://127.0.0.1:{ws_port}", VIEWED, timeout=120.0)))))
            watcher.start()
            with Supervisor(services, log_dir=tmp / "logs", stop_timeout_s=30) as supervisor, \
                    GatewayClient(f"http://127.0.0.1:{http_port}") as client:
                wait_for(lambda: port_open("127.0.0.1", http_port), timeout=60, what="the gateway")
                wait_for(lambda: all(_alive(session, ROBOT, s) for s in SERVICES), timeout=90,
                         what="every service")
                targets = list(make_episode(DEMO_SEED, DEMO_EPISODE)[0].targets)
                task = client.submit(targets, robot_id=ROBOT, max_steps=STEPS).id
                wait_for(lambda: client.get(task).final, timeout=120, what="the task ends")
                watcher.join()
            missing = lambda: set(SERVICES) - {k.split("/")[0] for k in final}  # noqa: E731
            wait_for(lambda: not missing(), timeout=20, what=lambda: "the final stats of " + "; ".join(
                f"{c.name} ({c.last_exit}; its log ends: {c.log_path.read_text()[-400:]!r})"
                for c in supervisor.status() if c.name in missing()))
            sub.undeclare()
            taker.join()
        finally:
            session.close()
    published: dict[str, int] = defaultdict(int)
    for stats in final.values():
        if stats.service in SERVICES:
            for key, counters in stats.counters.items():
                published[key] += counters.published
    return Run(path, configs, dict(published), dict(received), events, watched["advertised"], watched["viewed"])


def test_a_recorded_demo_run_holds_every_message_its_publishers_counted(recorded_run: Run) -> None:
    with recorded_run.path.open("rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None and summary.chunk_indexes
        counts = {summary.channels[c].topic: n for c, n in summary.statistics.channel_message_counts.items()}
        assert all(i.compression == "zstd" for i in summary.chunk_indexes)
        raw = {ch.topic: ch for ch in summary.channels.values() if META_KEY in ch.metadata}
        events = [m.data for _, ch, m in reader.iter_messages(topics=[keys.task_events(ROBOT)])]
    published = {k: n for k, n in recorded_run.published.items() if n}
    for name in ("odom", "driver_state", "rgbd", "perception_result", "map_snapshot", "plan_command",
                 "task_events", "plan_trace", "task_current"):
        assert published.get(getattr(keys, name)(ROBOT), 0) > 0, name
    # Everything a subscriber got; and everything published but the simulator's very first odometry
    # and driver state, put as its session opened: Zenoh had not yet told it of any subscriber
    # (the test's own subscriber misses them too)
    assert {k: counts.get(k, 0) for k in published} == {k: recorded_run.received.get(k, 0) for k in published}
    startup = {keys.odom(ROBOT), keys.driver_state(ROBOT)}
    assert {k: n for k, n in published.items() if k not in startup} == \
        {k: counts.get(k, 0) for k in published if k not in startup}
    assert all(0 <= published[k] - counts.get(k, 0) <= 1 for k in startup)
    for topic, channel in raw.items():
        meta = channel.metadata
        message = recorded_ports()[meta[META_KEY]]
        assert (meta["ovamos.message"], meta["ovamos.version"]) == (message.__name__, str(message.VERSION))
    # bit for bit: the recorded payloads are the ones a subscriber got, in the same order
    assert events == recorded_run.task_events
    targets = make_episode(DEMO_SEED, DEMO_EPISODE)[0].targets
    views = [*TOPICS, *(f"/map/value/{t}" for t in targets)]
    assert {t: counts.get(t, 0) > 0 for t in views} == {t: True for t in views}


def test_replaying_frames_odometry_and_perception_into_a_fresh_mapping_rebuilds_the_same_map(
        recorded_run: Run, tmp_path: Path) -> None:
    original_config = MappingServiceConfig.model_validate_json(recorded_run.configs["mapping"].read_text())
    original = load_checkpoint(original_config.checkpoint_path, original_config)
    config = original_config.model_copy(update={"checkpoint_path": tmp_path / "replayed.ckpt"})
    (tmp_path / "mapping.json").write_text(config.model_dump_json())
    port = free_port()
    robot = "replayed"  # --robot-id: the recording goes out on another robot's keys
    procs = [start_cli(["router", "--listen", loopback(port), "--log-level", "WARNING"])]
    try:
        wait_for(lambda: port_open("127.0.0.1", port), what="the router")
        procs.append(start_cli(["run", "mapping", "--robot-id", robot, "--config", str(tmp_path / "mapping.json"),
                                "--connect", loopback(port)]))
        zcfg = build_config(connect=[loopback(port)])
        with Bus.open(zcfg, robot, "test") as bus:
            def snapshot() -> MapSnapshot | None:
                return bus.get(keys.map_snapshot(robot), MapSnapshot, 1.0)
            wait_for(lambda: _alive(bus.session, robot, "mapping"), timeout=60, what="the mapping service")
            # it answers once it has wired itself, and its subscriptions are declared before its queryable
            # answers: a frame replayed now is not lost
            wait_for(snapshot, 30, "the mapping service's first answer")
            report = replay(zcfg, recorded_run.path, rate=1.0, names=["rgbd", "odom", "perception_result"],
                            robot_id=robot, stop=threading.Event())
            assert report.read["rgbd"] > STEPS and not report.truncated
            wait_for(lambda: (now := snapshot()) is not None and now.seq == original.seq, 30, "the last frame fused")
        stop(procs.pop())
        replayed = load_checkpoint(tmp_path / "replayed.ckpt", config)
    finally:
        for proc in procs:
            stop(proc)
    a, b = original.snapshot(0.0, with_confidence=False), replayed.snapshot(0.0, with_confidence=False)
    assert b.seq == a.seq and b.layers == a.layers
    assert np.array_equal(b.obstacle, a.obstacle) and np.array_equal(b.explored, a.explored)
    np.testing.assert_allclose(b.values, a.values, atol=1e-6)


def _publish_odometry(bus: Bus, first: int, n: int) -> list[bytes]:
    pub = bus.publisher(keys.odom(ROBOT), Odometry)
    payloads = []
    for seq in range(first, first + n):
        msg = Odometry(seq=seq, stamp=time.time(), x=seq * 0.01, y=0.0, yaw=0.0)
        pub.put(msg)
        payloads.append(msg.to_bytes())
        time.sleep(0.002)
    return payloads


def _readable_odometry(path: Path) -> list[bytes]:
    """The odometry payloads a reader gets from a recording that may end in a torn chunk."""
    got = []
    with path.open("rb") as f:
        try:
            for _, channel, message in NonSeekingReader(f).iter_messages(log_time_order=False):
                if channel.topic == keys.odom(ROBOT):
                    got.append(message.data)
        except McapError:
            pass  # the truncated tail
    return got


def test_a_killed_recorder_leaves_a_file_readable_up_to_its_last_chunk(tmp_path: Path) -> None:
    port = free_port()
    path = tmp_path / "killed.mcap"
    procs = [start_cli(["router", "--listen", loopback(port), "--log-level", "WARNING"])]
    try:
        wait_for(lambda: port_open("127.0.0.1", port), what="the router")
        recorder = start_cli(["record", "--robot-id", ROBOT, "--out", str(path), "--connect", loopback(port)])
        procs.append(recorder)
        with Bus.open(build_config(connect=[loopback(port)]), ROBOT, "test") as bus:
            wait_for(lambda: _ready(bus.session, ROBOT, "recorder"), timeout=60, what="the recorder")
            flushed = _publish_odometry(bus, 0, 200)
            # past a flush: these are in complete chunks on disk
            wait_for(lambda: len(_readable_odometry(path)) >= len(flushed), 30, "the first messages flushed")
            unflushed = _publish_odometry(bus, 200, 200)
            kill(recorder)
    finally:
        for proc in procs:
            stop(proc)
    assert not path.read_bytes().endswith(b"\x89MCAP0\r\n")  # killed: no summary, no closing magic
    got = _readable_odometry(path)
    assert got[:len(flushed)] == flushed
    assert got == (flushed + unflushed)[:len(got)]  # a prefix: nothing lost before the break, nothing torn
    # our own reader says where it stopped instead of failing
    assert [m.payload for m in read_raw(path, ["odom"])] == got


def test_a_file_that_is_not_a_recording_is_a_clear_error(tmp_path: Path) -> None:
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(b"not an mcap file" * 100)
    with pytest.raises(RecordingError, match="not a readable MCAP"):
        list(read_raw(bad))


async def _watch(url: str, wanted: set[str], timeout: float) -> tuple[set[str], set[str]]:
    """Connect with the Foxglove protocol, subscribe to ``wanted`` once advertised; the topics
    advertised and the topics a message arrived on."""
    advertised: dict[int, str] = {}      # channel id -> topic
    received: set[str] = set()
    subscribed: dict[int, str] = {}      # our subscription id -> topic
    async with websockets.connect(url, subprotocols=["foxglove.sdk.v1"]) as ws:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline and received < wanted:
            try:
                frame = await asyncio.wait_for(ws.recv(), timeout=1.0)
            except TimeoutError:
                continue
            if isinstance(frame, str):
                msg = json.loads(frame)
                if msg.get("op") == "advertise":
                    advertised.update({c["id"]: c["topic"] for c in msg["channels"]})
                    fresh = [{"id": len(subscribed) + 1 + i, "channelId": c["id"]}
                             for i, c in enumerate(c for c in msg["channels"] if c["topic"] in wanted)]
                    if fresh:
                        subscribed.update({s["id"]: advertised[s["channelId"]] for s in fresh})
                        await ws.send(json.dumps({"op": "subscribe", "subscriptions": fresh}))
            elif frame[0] == 1:  # message data: opcode, subscription id (u32 LE), time, payload
                received.add(subscribed[int.from_bytes(frame[1:5], "little")])
    return set(advertised.values()), received


def test_a_websocket_client_of_the_live_view_gets_every_view_of_a_running_demo(recorded_run: Run) -> None:
    targets = make_episode(DEMO_SEED, DEMO_EPISODE)[0].targets
    assert set(TOPICS) | {f"/map/value/{t}" for t in targets} <= recorded_run.advertised
    assert recorded_run.viewed == VIEWED


def test_replay_at_max_speed_ignores_the_recorded_gaps_and_loses_nothing(tmp_path: Path, inproc_router: str) -> None:
    path = tmp_path / "slow.mcap"
    context = foxglove.Context()
    writer = foxglove.open_mcap(path, context=context)
    channel = RawChannel("odom", Odometry, ROBOT).open(context)
    payloads = [Odometry(seq=i, stamp=float(i), x=0.0, y=0.0, yaw=0.0).to_bytes() for i in range(300)]
    for i, payload in enumerate(payloads):
        channel.log(payload, log_time=(1_000 + 60 * i) * 10**9)  # a minute apart: five hours at rate 1
    writer.close()
    zcfg = build_config(connect=[inproc_router])
    got: list[bytes] = []
    with Bus.open(zcfg, "desk", "test") as bus:
        bus.tap(keys.odom("desk"), lambda key, payload: got.append(payload))
        report = replay(zcfg, path, rate=None, names=None, robot_id="desk", stop=threading.Event())
        wait_for(lambda: len(got) == len(payloads), timeout=20, what="every replayed message")
    assert report.read == {"odom": 300} and got == payloads


def test_a_replay_onto_a_live_robot_is_refused_unless_forced(tmp_path: Path, inproc_router: str) -> None:
    """Issue 33, finding 1: a recording replayed onto the live robot id mixed its odometry session
    and frames with the robot's own. A driver's liveliness token makes the robot id live."""
    path = tmp_path / "odom.mcap"
    context = foxglove.Context()
    writer = foxglove.open_mcap(path, context=context)
    channel = RawChannel("odom", Odometry, "desk").open(context)
    payloads = [Odometry(seq=i, stamp=float(i), x=0.0, y=0.0, yaw=0.0).to_bytes() for i in range(5)]
    for i, payload in enumerate(payloads):
        channel.log(payload, log_time=(1_000 + i) * 10**9)
    writer.close()
    zcfg = build_config(connect=[inproc_router])
    got: list[bytes] = []
    with Bus.open(zcfg, "desk", "sim", "7") as live, Bus.open(zcfg, "desk", "test") as bus:
        assert live.robot_id == "desk"
        bus.tap(keys.odom("desk"), lambda key, payload: got.append(payload))
        with pytest.raises(LiveRobotError, match=r"robot 'desk' is live \(sim/7 alive\).*--robot-id "
                                                 r"desk-replay.*--force"):
            replay(zcfg, path, rate=None, names=None, robot_id=None, stop=threading.Event())
        # the CLI says the same and exits non-zero; nothing was published
        proc = subprocess.run([sys.executable, "-m", "ovamos.cli", "replay", str(path), "--max",
                               "--connect", inproc_router], capture_output=True, text=True, timeout=60)
        assert proc.returncode != 0 and "robot 'desk' is live (sim/7 alive)" in proc.stderr
        report = replay(zcfg, path, rate=None, names=None, robot_id=None, stop=threading.Event(), force=True)
        wait_for(lambda: len(got) == len(payloads), what="the forced replay's messages")
    assert report.read == {"odom": 5} and got == payloads  # none came before the forced replay
