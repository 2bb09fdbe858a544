"""Recorder benchmark: sustained 640x480 RGB-D at 30 Hz plus map snapshots at 2 Hz, over Zenoh into MCAP.

A publisher puts frames at 30 Hz and map snapshots at 2 Hz on a robot's keys through a router;
``ovamos record``'s code (:func:`ovamos.record.live.record`: the tap, the byte-bounded queue,
the writer thread, zstd chunks, the Foxglove views) writes them to a file, all in this
process, on this machine's cores. Reported: raw megabytes per second written, frames lost
(published but not written, whether the recorder's queue dropped them or Zenoh did), frames
written per second.

The frames are the simulator's renders of a real home, fused into a map for realistic
snapshots. A render has a few flat colours and compresses ~170x, which would flatter the
recorder, so by default each frame gets a camera's noise (sigma 2 grey levels on colour,
depth as uint16 millimetres, as a RealSense sends it, with 0.5 % noise); ``noise=False``
records the renders as they are.
"""

from __future__ import annotations

import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
from rich.console import Console
from rich.table import Table

from ovamos.bench.sim import SCENE_SEED, camera_poses
from ovamos.record.channels import select
from ovamos.record.live import record
from ovamos.record.recorder import RecorderConfig
from ovamos.services.mapping.config import MappingConfig
from ovamos.services.mapping.state import MapState
from ovamos.shared import keys
from ovamos.shared.bus import Bus
from ovamos.shared.bus.zconfig import build_config, open_session
from ovamos.shared.messages import MapSnapshot, RgbdFrame
from ovamos.shared.procs import free_port, loopback
from ovamos.world.evaluator import GroundTruth
from ovamos.world.generate import generate_scene
from ovamos.world.render import SceneRenderer

FRAME_HZ, MAP_HZ = 30.0, 2.0
DISTINCT_FRAMES = 20
ROBOT = "bench"
RGB_NOISE, DEPTH_NOISE = 2.0, 0.005


def _camera_like(frame: RgbdFrame, rng: np.random.Generator) -> RgbdFrame:
    rgb = np.clip(frame.rgb + rng.normal(0.0, RGB_NOISE, frame.rgb.shape), 0, 255).astype(np.uint8)
    depth_m = frame.depth * (1.0 + rng.normal(0.0, DEPTH_NOISE, frame.depth.shape))
    depth = np.clip(np.round(depth_m * 1000.0), 0, 65535).astype("<u2")
    return frame.model_copy(update={"rgb": rgb, "depth": depth, "depth_scale": 0.001, "instance_ids": None})


def frames_and_map(noise: bool, width: int = 640, height: int = 480) -> tuple[list[bytes], bytes]:
    """Encoded frames of a simulated home and one snapshot of a map that fused them."""
    scene = generate_scene(SCENE_SEED)
    truth = GroundTruth(scene)
    state = MapState(MappingConfig())
    rng = np.random.default_rng(0)
    frames = []
    with SceneRenderer(scene, width, height) as renderer:
        for seq, (x, y, yaw) in enumerate(camera_poses(truth, DISTINCT_FRAMES)):
            frame = renderer.render(x, y, yaw, seq=seq, stamp=time.time())
            state.integrate(frame)
            frames.append(bytes((_camera_like(frame, rng) if noise else frame).to_bytes()))
    return frames, bytes(state.snapshot(time.time(), with_confidence=False).to_bytes())


def run_benchmark(seconds: float = 20.0, noise: bool = True) -> dict[str, Any]:
    frames, snapshot = frames_and_map(noise)
    endpoint = loopback(free_port())
    router = open_session(build_config("router", listen=[endpoint]))
    zcfg = build_config(connect=[endpoint])
    stop, stats = threading.Event(), {}
    try:
        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / "bench.mcap"
            recorder = threading.Thread(target=lambda: stats.update(
                record(zcfg, ROBOT, select(["rgbd", "map_snapshot"]), path, RecorderConfig(), stop)))
            recorder.start()
            with Bus.open(zcfg, ROBOT, "benchpub") as bus:
                while not any(r.ok for r in bus.session.liveliness().get(keys.ready(ROBOT, "recorder"), timeout=1)):
                    pass
                rgbd = bus.publisher(keys.rgbd(ROBOT), RgbdFrame)
                maps = bus.publisher(keys.map_snapshot(ROBOT), MapSnapshot)
                published, start = 0, time.monotonic()
                next_map = start
                while (now := time.monotonic()) - start < seconds:
                    rgbd.put_bytes(frames[published % len(frames)])
                    published += 1
                    if now >= next_map:
                        maps.put_bytes(snapshot)
                        next_map += 1.0 / MAP_HZ
                    time.sleep(max(0.0, start + published / FRAME_HZ - time.monotonic()))
                elapsed = time.monotonic() - start
            time.sleep(0.5)  # the last frames' way through the router
            stop.set()
            recorder.join()
            file_mb = sum(Path(p).stat().st_size for p in stats["files"]) / 1e6
    finally:
        router.close()
    written = stats["written"].get("rgbd", 0)
    return {"frames_per_s": round(written / elapsed, 1), "dropped": published - written,
            "mb_per_s": round(stats["bytes"] / 1e6 / elapsed, 1), "file_mb_per_s": round(file_mb / elapsed, 1),
            "frame_mb": round(len(frames[0]) / 1e6, 2), "published": published, "seconds": round(elapsed, 1),
            "noise": noise, "views": stats.get("views", {})}


def print_table(console: Console, r: dict[str, Any]) -> None:
    table = Table("frames", "frames/s written", "dropped", "raw MB/s", "file MB/s", "frame MB", "seconds",
                  title=f"recording 640x480 RGB-D at {FRAME_HZ:.0f} Hz + maps at {MAP_HZ:.0f} Hz over Zenoh")
    table.add_row("camera-like (noise)" if r["noise"] else "sim renders", str(r["frames_per_s"]), str(r["dropped"]),
                  str(r["mb_per_s"]), str(r["file_mb_per_s"]), str(r["frame_mb"]), str(r["seconds"]))
    console.print(table)
