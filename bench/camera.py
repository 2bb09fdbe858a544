"""Camera benchmark: the RealSense backend at 640x480, frames published over Zenoh and acked.

What a robot's camera does per frame, in one process (so ``taskset -c 0`` puts all
of it on one core, the SDK's and Zenoh's threads included):

- ``feed``: the frame enters pyrealsense2's own software device (the simulator's
  render of a generated home as rgb8 + z16); on a robot the camera's USB
  transfer takes this place, so it is reported but is not the camera's work;
- ``sync``: the SDK's syncer pairs depth with colour and hands the frameset over;
- ``align``: depth filters (off, the default), ``rs.align`` to colour and the
  numpy copies, i.e. the rest of :meth:`RealSenseBackend.read`;
- ``encode``: the :class:`~ovamos.shared.messages.RgbdFrame` (uint16 depth + depth scale,
  identity pose) built and serialised;
- ``publish``: the payload put on a Zenoh session, through a router in this
  process, to a second session's bus that decodes it and acks; the time until
  the ack is back.

Frames go one at a time (the next is fed when the previous is acked), so
``fps_640x480`` is what the whole chain sustains when nothing overlaps: a lower
bound for a camera whose frames arrive while the previous one is in flight.
"""

from __future__ import annotations

import statistics
import threading
import time
from typing import Any

import numpy as np
from rich.console import Console
from rich.table import Table

from ovamos.services.camera.capture import CapturedFrame
from ovamos.services.camera.realsense import RealSenseBackend, RealSenseConfig
from ovamos.services.camera.software_device import SoftwareCamera
from ovamos.shared import keys
from ovamos.shared.bus import Bus
from ovamos.shared.bus.zconfig import build_config, open_session
from ovamos.shared.messages import JsonMessage, RgbdFrame
from ovamos.shared.procs import free_port, loopback

ROBOT = "bench"
FRAME_KEY, ACK_KEY = keys.rgbd(ROBOT), keys.bench(ROBOT, "camera-ack")
STAGES = ("feed", "sync", "align", "encode", "publish")
DISTINCT_FRAMES = 8  # rendered once, fed round-robin
WARMUP = 5
SCENE_SEED = 4
ACK_TIMEOUT_S = 5.0


class Ack(JsonMessage):
    seq: int


def rendered_frames(width: int, height: int, count: int = DISTINCT_FRAMES,
                    depth_scale: float = 0.001) -> tuple[list[tuple[np.ndarray, np.ndarray]], Any]:
    """``count`` simulator frames of a generated home as (rgb uint8, depth z16), and the
    renderer's intrinsics."""
    from ovamos.bench.sim import camera_poses
    from ovamos.world.evaluator import GroundTruth
    from ovamos.world.generate import generate_scene
    from ovamos.world.render import SceneRenderer

    scene = generate_scene(SCENE_SEED)
    out = []
    with SceneRenderer(scene, width, height) as renderer:
        for x, y, yaw in camera_poses(GroundTruth(scene), count):
            frame = renderer.render(x, y, yaw)
            depth = np.round(frame.depth / depth_scale).astype(np.uint16)
            out.append((frame.rgb.copy(), depth))
        return out, renderer.intrinsics


class _Link:
    """A camera-side bus and an acking subscriber bus, both clients of an in-process router."""

    def __init__(self) -> None:
        endpoint = loopback(free_port())
        self._router = open_session(build_config("router", listen=[endpoint]))
        cfg = build_config(connect=[endpoint])
        self.camera = Bus.open(cfg, ROBOT, "camera")
        self.sink = Bus.open(cfg, ROBOT, "camera-sink")
        ack_pub = self.sink.publisher(ACK_KEY, Ack)
        self.sink.subscribe(FRAME_KEY, RgbdFrame, lambda f: ack_pub.put(Ack(seq=f.seq)), keep=1)
        self.acked = threading.Event()
        self._want = -1
        self.camera.subscribe(ACK_KEY, Ack, self._on_ack)
        # The raw Zenoh publisher: encoding is timed apart, so the payload is put as is.
        self._pub = self.camera.session.declare_publisher(FRAME_KEY)

    def _on_ack(self, ack: Ack) -> None:
        if ack.seq == self._want:
            self.acked.set()

    def send(self, seq: int, payload: bytes | bytearray) -> bool:
        self._want = seq
        self.acked.clear()
        self._pub.put(bytes(payload))
        return self.acked.wait(ACK_TIMEOUT_S)

    def wait_ready(self, payload_for: Any, timeout_s: float = 20.0) -> None:
        """Declarations propagate asynchronously: send until one frame is acked."""
        deadline = time.monotonic() + timeout_s
        seq = 10**9
        while True:
            self._want = seq
            self.acked.clear()
            self._pub.put(bytes(payload_for(seq)))
            if self.acked.wait(0.2):
                return
            if time.monotonic() > deadline:
                raise TimeoutError("the subscriber never acknowledged a frame")
            seq += 1

    def close(self) -> None:
        self._pub.undeclare()
        self.camera.close()
        self.sink.close()
        self._router.close()


def _encode(captured: CapturedFrame, seq: int, buffer: bytearray) -> bytearray:
    frame = RgbdFrame(seq=seq, stamp=captured.host_time_s, intrinsics=captured.intrinsics,
                      depth_scale=captured.depth_scale, rgb=captured.rgb, depth=captured.depth)
    return frame.to_bytes(buffer)


def _run(camera: SoftwareCamera, backend: RealSenseBackend, link: _Link,
         frames: list[tuple[np.ndarray, np.ndarray]], count: int, first_seq: int
         ) -> tuple[float, dict[str, float]]:
    """One run: frames per second over ``count`` frames, and the median ms of each stage."""
    samples: dict[str, list[float]] = {s: [] for s in STAGES}
    buffer = bytearray()
    start = time.perf_counter()
    for i in range(count):
        seq = first_seq + i
        rgb, depth = frames[seq % len(frames)]
        t0 = time.perf_counter()
        camera.push(rgb, depth)
        t1 = time.perf_counter()
        captured = backend.read(2.0)
        t2 = time.perf_counter()
        if captured is None:
            raise RuntimeError(f"frame {seq} fed to the software device never came out")
        payload = _encode(captured, seq, buffer)
        t3 = time.perf_counter()
        if not link.send(seq, payload):
            raise RuntimeError(f"frame {seq} was not acknowledged within {ACK_TIMEOUT_S} s")
        t4 = time.perf_counter()
        samples["feed"].append(t1 - t0)
        samples["sync"].append(backend.timing_ms["wait"] / 1e3)
        samples["align"].append(backend.timing_ms["align"] / 1e3)
        samples["encode"].append(t3 - t2)
        samples["publish"].append(t4 - t3)
    fps = count / (time.perf_counter() - start)
    return fps, {s: statistics.median(v) * 1e3 for s, v in samples.items()}


def run_benchmark(frames: int = 150, runs: int = 5, width: int = 640, height: int = 480,
                  filters: bool = False, progress: Console | None = None) -> dict[str, Any]:
    """Median over ``runs`` runs of ``frames`` frames each (see the module docstring);
    ``filters`` turns on the backend's spatial, temporal and hole-filling depth filters."""
    if frames < 1 or runs < 1:
        raise ValueError("frames and runs must be at least 1")
    rendered, intrinsics = rendered_frames(width, height)
    camera = SoftwareCamera(width, height, intrinsics, depth_scale=0.001, fps=30)
    config = RealSenseConfig(width=width, height=height, fps=30, warmup_frames=0,
                             spatial=filters, temporal=filters, hole_filling=filters)
    backend = RealSenseBackend(config, source=camera)
    link = _Link()
    fps_runs: list[float] = []
    stage_runs: dict[str, list[float]] = {s: [] for s in STAGES}
    first: CapturedFrame | None = None
    try:
        backend.start()
        # The syncer's start-up pair comes out split and is skipped: feed until frames flow.
        captured: CapturedFrame | None = None
        for _ in range(WARMUP):
            camera.push(*rendered[0])
            captured = backend.read(1.0) or captured
        if captured is None:
            raise RuntimeError("the software device delivers no frames")
        first = captured
        link.wait_ready(lambda seq: _encode(captured, seq, bytearray()))
        seq = 0
        for run in range(runs):
            fps, stages = _run(camera, backend, link, rendered, frames, seq)
            seq += frames
            fps_runs.append(fps)
            for s in STAGES:
                stage_runs[s].append(stages[s])
            if progress:
                progress.print(f"run {run + 1}/{runs}: {fps:.1f} frames/s, " + ", ".join(
                    f"{s} {stages[s]:.2f} ms" for s in STAGES))
    finally:
        backend.stop()
        link.close()
    assert first is not None  # the warm-up raised otherwise
    ms = {s: round(statistics.median(v), 3) for s, v in stage_runs.items()}
    return {
        f"fps_{width}x{height}": round(statistics.median(fps_runs), 1),
        "ms_per_frame": ms,
        "frames_per_run": frames, "runs": runs, "width": width, "height": height,
        "depth_filters": filters,
        "run_fps": [round(f, 1) for f in fps_runs],
        "frame_bytes": len(_encode(first, 0, bytearray())),
    }


def print_table(console: Console, result: dict[str, Any]) -> None:
    w, h = result["width"], result["height"]
    fps = result[f"fps_{w}x{h}"]
    table = Table("stage", "ms/frame (median)",
                  title=f"RealSense backend on the SDK's software device, {w}x{h}, depth filters "
                        f"{'on' if result['depth_filters'] else 'off'}, published over "
                        f"Zenoh and acked; median of {result['runs']} runs x "
                        f"{result['frames_per_run']} frames")
    for stage in STAGES:
        table.add_row(stage, f"{result['ms_per_frame'][stage]:.2f}")
    console.print(table)
    console.print(f"{fps:.1f} frames/s end to end ({1e3 / fps:.1f} ms/frame; runs: "
                  f"{', '.join(f'{r:.1f}' for r in result['run_fps'])}); "
                  f"frame {result['frame_bytes'] / 1e6:.2f} MB")
