"""The Zenoh side of ``ovamos record``, ``replay`` and ``view``: the cores wired to a robot's keys.

Each runs as a tool on a :class:`~ovamos.shared.bus.Bus` of its own (service ``recorder``,
``replay`` or ``viewer``, instance = its process id), so ``ovamos status`` lists it with its
counters: a recorder's ``received`` and ``dropped`` per key, a replay's ``published``.
Payloads are taken on Zenoh's threads straight into the recorder's byte-bounded queue
(:meth:`~ovamos.shared.bus.BusCore.tap`), never decoded there.

The recorder and the viewer declare a ``ready`` liveliness token once their subscriptions
are in place: a test or a launcher that waits for it knows nothing published after it is lost.

A replay refuses a robot id whose driver is alive (:class:`LiveRobotError`) unless forced: the
recording's odometry and driver states would mix with the live ones (another odometry session,
poses of another run) and its frames would be fused into the live map.
"""

from __future__ import annotations

import itertools
import os
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import foxglove
import zenoh

from ovamos.record.channels import RawChannel
from ovamos.record.recorder import Recorder, RecorderConfig
from ovamos.record.replay import ReadReport, paced, read_raw
from ovamos.record.views import ViewPump
from ovamos.shared import keys
from ovamos.shared.bus import Bus
from ovamos.shared.service import install_signal_handlers
from ovamos.shared.topology import DRIVERS

__all__ = ["record", "replay", "view", "STATUS_EVERY_S", "LiveRobotError"]

STATUS_EVERY_S = 1.0
LIVE_CHECK_S = 2.0  # how long a replay asks who is alive before it publishes (a liveliness query)


class LiveRobotError(RuntimeError):
    """A replay onto a robot id whose driver is alive, not forced."""


def _tool_bus(zenoh_config: zenoh.Config, robot_id: str, service: str, stop: threading.Event) -> Bus:
    """The tool's bus; from then on SIGINT / SIGTERM set ``stop`` (in the main thread). Before, while
    the session waits for a router, they end the process at once: there is nothing to finish yet."""
    bus = Bus.open(zenoh_config, robot_id, service, str(os.getpid()), dispatch="thread")
    install_signal_handlers(stop)
    return bus


def _tap_all(bus: Bus, ports: Mapping[str, type], take: Callable[[str, bytes], bool]) -> None:
    """Every port's key into ``take(name, payload)``; False from it counts a drop on the key."""
    for name in ports:
        def on_sample(key: str, payload: bytes, name: str = name) -> None:
            if not take(name, payload):
                bus.counters.bump(key, "dropped")

        bus.tap(RawChannel(name, ports[name], bus.robot_id).key, on_sample)
    bus.declare_token(keys.ready(bus.robot_id, bus.service, bus.instance))


def record(zenoh_config: zenoh.Config, robot_id: str, ports: Mapping[str, type], path: Path,
           config: RecorderConfig, stop: threading.Event,
           on_status: Callable[[dict[str, Any]], None] | None = None) -> dict[str, Any]:
    """Record ``ports`` of ``robot_id`` to ``path`` until ``stop``; the recorder's final stats.

    The file is created before Zenoh is opened, so a bad path fails at once."""
    recorder = Recorder(path, ports, robot_id, config)
    try:
        bus = _tool_bus(zenoh_config, robot_id, "recorder", stop)
        try:
            _tap_all(bus, ports, recorder.offer)
            while not stop.wait(STATUS_EVERY_S):
                bus.info = recorder.stats()
                if on_status is not None:
                    on_status(bus.info)
        finally:
            bus.close()
    finally:
        recorder.close()
    return recorder.stats()


def replay(zenoh_config: zenoh.Config, path: Path, *, rate: float | None, names: Sequence[str] | None,
           robot_id: str | None, stop: threading.Event, force: bool = False) -> ReadReport:
    """Publish the raw channels of ``path`` (those in ``names``) on ``robot_id``'s keys (the
    recorded robot's when None) at ``rate`` times their recorded pace; None: as fast as the
    subscribers' links take them (puts wait while one is congested instead of dropping).
    :class:`LiveRobotError` before anything is published when that robot's driver is alive,
    unless ``force``."""
    report = ReadReport()
    messages = read_raw(path, names, report)
    first = next(messages, None)  # a file that is not a recording fails before Zenoh is opened
    if first is None:
        return report
    robot = robot_id or first.channel.robot_id
    bus = _tool_bus(zenoh_config, robot, "replay", stop)
    try:
        live = _live_drivers(bus)
        if live and not force:
            raise LiveRobotError(
                f"robot {robot!r} is live ({', '.join(live)} alive): replaying onto it would mix the "
                f"recording's odometry, driver states and frames with the robot's own. Replay onto "
                f"another robot id (--robot-id {robot}-replay), or pass --force if that is meant")
        publishers: dict[str, Any] = {}
        for msg in paced(itertools.chain((first,), messages), rate, stopped=stop.is_set):
            pub = publishers.get(msg.channel.name)
            if pub is None:
                key = RawChannel(msg.channel.name, msg.channel.message, robot).key
                pub = publishers[msg.channel.name] = bus.publisher(key, msg.channel.message, block=rate is None)
            pub.put_bytes(msg.payload)
    finally:
        bus.close()
    return report


def _live_drivers(bus: Bus) -> list[str]:
    """The driver instances alive on the bus's robot (``sim/0``, ``base_driver/1234``)."""
    alive = []
    for service in DRIVERS:
        for reply in bus.session.liveliness().get(keys.alive(bus.robot_id, service), timeout=LIVE_CHECK_S):
            if reply.ok is not None:
                key = keys.parse_service_key(str(reply.ok.key_expr))
                alive.append(f"{key.service}/{key.instance}")
    return sorted(alive)


def view(zenoh_config: zenoh.Config, robot_id: str, ports: Mapping[str, type], *, host: str, port: int,
         stop: threading.Event, on_started: Callable[[int], None] | None = None) -> dict[str, int]:
    """A Foxglove WebSocket server on ``host:port`` drawing ``robot_id``'s live traffic until
    ``stop``; ``on_started(port)`` once it listens (port 0: a free one). Returns the view counters."""
    context = foxglove.Context()
    pump = ViewPump(context, ports)
    server = foxglove.start_server(name=f"ovamos {robot_id}", host=host, port=port, context=context)
    try:
        bus = _tool_bus(zenoh_config, robot_id, "viewer", stop)
        try:
            def take(name: str, payload: bytes) -> bool:
                pump.offer(name, payload, time.time_ns())
                return True

            _tap_all(bus, ports, take)
            if on_started is not None:
                on_started(server.port)
            while not stop.wait(STATUS_EVERY_S):
                bus.info = dict(pump.counters)
        finally:
            bus.close()
    finally:
        pump.close()
        server.stop()
    return dict(pump.counters)
