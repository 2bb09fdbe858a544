"""ROS 2 benchmark: the ros2 camera backend's frame path and the ros2 base's command latency.

Run in a loopback-only network namespace (``ovamos bench ros2`` enters one itself). Each run:

- frames: the mock camera (``bench/ros2_peers/fake_camera.py``, its own process) publishes
  ``width`` x ``height`` rgb8 + 16UC1 + CameraInfo at ``hz``, reliable, as ``realsense2_camera``
  does; this process, pinned to one core, runs the camera service with the ``ros2`` backend on
  the fake bus (the in-process stand-in for Zenoh), free-running, with odometry at 50 Hz, for
  ``seconds``. Reported: frames/s out on ``sensors/rgbd``, and the latency from a frame's ROS
  header stamp (its capture) to the backend handing it to the camera core (DDS transport,
  pairing, conversion; both on this host's wall clock).
- commands: the base controller with the ``ros2`` hardware against the mock base
  (``fake_base.py``); a velocity command is submitted (what ``plan/command`` does) and the time
  until the mock base receives the non-zero ``cmd_vel`` is taken on this host's monotonic clock,
  ``commands`` times (the controller's 50 Hz loop is most of it).
"""

from __future__ import annotations

import os
import statistics
import time
from typing import Any, Callable

import numpy as np
from rich.console import Console
from rich.table import Table

from ovamos.bench.ros2_peers.nodes import MockNode
from ovamos.shared.dds import check_loopback_only

ODOM_HZ = 50.0
WARMUP_S = 1.0


def _frames(width: int, height: int, hz: float, seconds: float) -> dict[str, float]:
    """One run of the frame path (see the module)."""
    from ovamos.services.camera.config import CameraConfig
    from ovamos.services.camera.ros2 import Ros2Backend, Ros2CameraConfig
    from ovamos.services.camera.service import CameraService
    from ovamos.shared import keys
    from ovamos.shared.fake_bus import FakeNetwork
    from ovamos.shared.messages import Odometry, RgbdFrame

    camera = MockNode("fake_camera.py", "--width", str(width), "--height", str(height), "--hz", str(hz))
    backend = Ros2Backend(Ros2CameraConfig())
    delays: list[float] = []
    read = backend.read

    def timed_read(timeout_s: float) -> Any:
        frame = read(timeout_s)
        if frame is not None:
            delays.append(time.time() - frame.device_time_s)
        return frame

    backend.read = timed_read  # type: ignore[method-assign]  # the bench's instrument
    net = FakeNetwork()
    service = CameraService(net.bus("bench", "camera"), CameraConfig(backend="ros2", lock_step=False, max_hz=hz * 2),
                            backend=backend)
    tester = net.bus("bench", "tester")
    arrived: list[float] = []
    tester.subscribe(keys.rgbd("bench"), RgbdFrame, lambda f: arrived.append(time.monotonic()))
    odom = tester.publisher(keys.odom("bench"), Odometry)
    service.start()
    try:
        start, seq = time.monotonic(), 0
        while time.monotonic() - start < WARMUP_S + seconds:
            seq += 1
            odom.put(Odometry(seq=seq, stamp=time.time(), x=0.0, y=0.0, yaw=0.0))
            net.pump()
            service.tick()
            net.pump()
            time.sleep(1 / ODOM_HZ)
    finally:
        service.stop()
        camera.close()
    measured = [t for t in arrived if t >= start + WARMUP_S]
    if len(measured) < 2 or not delays:
        raise RuntimeError(f"the frame path delivered {len(measured)} frames in {seconds} s: {service.info()}")
    ms = np.array(delays[len(delays) // 4:]) * 1e3  # past the warm-up
    return {"fps": (len(measured) - 1) / (measured[-1] - measured[0]),
            "latency_ms_median": float(np.median(ms)), "latency_ms_p95": float(np.percentile(ms, 95))}


def _commands(count: int) -> dict[str, float]:
    """One run of the command latency (see the module)."""
    from ovamos.services.base_driver.config import DriverConfig
    from ovamos.services.base_driver.controller import BaseController
    from ovamos.shared.messages import DriverMode, PlanCommand

    base = MockNode("fake_base.py", "--twist")
    driver = BaseController(DriverConfig(hardware="ros2", ros2={"stamped": False})).start()  # type: ignore[arg-type]
    latencies: list[float] = []

    def wait(predicate: Callable[[], bool], what: str) -> None:
        deadline = time.monotonic() + 10
        while not predicate():
            if time.monotonic() > deadline:
                raise RuntimeError(f"timed out waiting for {what}")
            time.sleep(0.001)
    try:
        wait(lambda: driver.state().mode is DriverMode.READY, "the ros2 base to be ready")
        for k in range(count):
            heard = len(base.lines())
            sent = time.monotonic()
            driver.submit(PlanCommand(action_id=2 * k + 1, stamp=0.0, linear=0.05))
            wait(lambda: any(line.get("v", 0) > 0 for line in base.lines()[heard:]), "cmd_vel")
            latencies.append(next(line["t"] for line in base.lines()[heard:] if line.get("v", 0) > 0) - sent)
            driver.submit(PlanCommand(action_id=2 * k + 2, stamp=0.0, linear=0.0))
            wait(lambda: driver.state().mode is DriverMode.READY and base.lines()[-1].get("v", 1) == 0.0,
                 "the base at rest")
    finally:
        driver.stop()
        base.close()
    ms = np.array(latencies) * 1e3
    return {"command_ms_median": float(np.median(ms)), "command_ms_p95": float(np.percentile(ms, 95))}


def run_benchmark(*, runs: int = 3, seconds: float = 10.0, width: int = 640, height: int = 480, hz: float = 30.0,
                  commands: int = 50, progress: Console | None = None) -> dict[str, Any]:
    """Median over ``runs`` of each figure (see the module); this process pinned to one core."""
    check_loopback_only()
    os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})
    per_run: list[dict[str, float]] = []
    for i in range(runs):
        if progress is not None:
            progress.print(f"run {i + 1}/{runs}: {seconds:.0f} s of {width}x{height} frames at {hz:g} Hz, "
                           f"{commands} commands")
        per_run.append({**_frames(width, height, hz, seconds), **_commands(commands)})
    return {"runs": runs, "seconds": seconds, "width": width, "height": height, "hz": hz, "commands": commands,
            "median": {k: statistics.median(r[k] for r in per_run) for k in per_run[0]}, "per_run": per_run}


def print_table(console: Console, result: dict[str, Any]) -> None:
    m = result["median"]
    table = Table("figure", "median", "runs",
                  title=f"ROS 2: {result['width']}x{result['height']} rgb8 + 16UC1 at {result['hz']:g} Hz into "
                        f"the camera service (one core), and cmd_vel latency; median of {result['runs']} runs")
    rows = (("frames/s on sensors/rgbd", "fps", "{:.1f}"),
            ("header stamp -> camera core, median ms", "latency_ms_median", "{:.1f}"),
            ("header stamp -> camera core, p95 ms", "latency_ms_p95", "{:.1f}"),
            ("submit -> cmd_vel received, median ms", "command_ms_median", "{:.1f}"),
            ("submit -> cmd_vel received, p95 ms", "command_ms_p95", "{:.1f}"))
    for label, key, fmt in rows:
        table.add_row(label, fmt.format(m[key]), ", ".join(fmt.format(r[key]) for r in result["per_run"]))
    console.print(table)
