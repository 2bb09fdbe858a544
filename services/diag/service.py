"""Diagnostic services: ``testpattern`` (a synthetic camera) and ``monitor`` (traffic stats)."""

from __future__ import annotations

import dataclasses
import time
from typing import Any

from ovamos.services.diag.config import MonitorConfig, TestPatternConfig
from ovamos.services.diag.monitor import TrafficStats
from ovamos.services.diag.testpattern import pattern_frame
from ovamos.shared import keys
from ovamos.shared.bus import BusCore
from ovamos.shared.messages import RgbdFrame
from ovamos.shared.service import Service


class TestPatternService(Service):
    """Publishes test-pattern RGB-D frames on ``sensors/rgbd`` at ``rate_hz``."""

    name = "testpattern"
    Config = TestPatternConfig
    config: TestPatternConfig

    def __init__(self, bus: BusCore, config: TestPatternConfig) -> None:
        super().__init__(bus, config)
        self.tick_hz = config.rate_hz
        self.seq = 0

    def start(self) -> None:
        self.wire({})

    def tick(self) -> None:
        c = self.config
        frame = pattern_frame(self.seq, 0.0, width=c.width, height=c.height, seed=c.seed)
        # Stamp when the frame is complete, as a camera driver stamps at capture.
        self.out["rgbd"].put(frame.model_copy(update={"stamp": time.time()}))
        self.seq += 1

    def info(self) -> dict[str, Any]:
        return {"frames_sent": self.seq}


class MonitorService(Service):
    """Watches every key of its robot; validates frames and measures their latency."""

    name = "monitor"
    Config = MonitorConfig
    config: MonitorConfig

    def __init__(self, bus: BusCore, config: MonitorConfig) -> None:
        super().__init__(bus, config)
        self.tick_hz = 1.0 / config.report_s
        self.traffic = TrafficStats(config.window_s)
        self._rgbd = keys.rgbd(bus.robot_id)

    def start(self) -> None:
        self.wire({"robot_all": self._on_payload})

    def _on_payload(self, key: str, payload: bytes) -> None:
        latency = None
        if key == self._rgbd:
            frame = self.bus.decode(key, RgbdFrame, payload)
            # capture stamp vs this host's wall clock: meaningful when both hosts' clocks agree
            latency = None if frame is None else time.time() - frame.stamp
        self.traffic.observe(key, len(payload), time.monotonic(), latency)

    def _report(self) -> list[dict[str, Any]]:
        return [dataclasses.asdict(r) for r in self.traffic.report(time.monotonic())]

    def tick(self) -> None:
        for row in self._report():
            self.log.info("%(key)s: %(messages)d msgs, %(rate_hz).1f Hz, %(mbytes_per_s).2f MB/s", row)

    def info(self) -> dict[str, Any]:
        return {"streams": self._report()}
