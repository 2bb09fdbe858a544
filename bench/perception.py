"""Perception benchmark: frames per second of each backend on 640x480 frames with 3 targets.

* ``sim``: the simulator's perception (what tests and the demo run).
* ``hf``: the real pipeline (BLIP ITM scores for all targets, GroundingDINO
  boxes, SAM masks for the boxes) with FULL-SIZE architectures built from the
  default configs (BLIP-base ITM at 384 px, GroundingDINO Swin-T, SAM ViT-B)
  and seeded random weights: no download, and random weights cost the same
  time as trained ones. CPU always (fp32); CUDA too (fp16) when torch sees a GPU.

Frames are rendered once (not timed) in the generated home of the other
benchmarks, from seeded free poses. A frame's time is what the service spends
on it: ``score`` then ``detect``. One warm-up frame per device is not timed.
Random weights make GroundingDINO keep up to ``max_detections`` (20) boxes,
more than trained weights usually do, so SAM's per-box decoder is timed at its
worst; its image encoder, once per frame, dominates anyway.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from typing import Any

from rich.console import Console
from rich.table import Table

from ovamos.bench.sim import SCENE_SEED, camera_poses
from ovamos.services.perception.backend import PerceptionBackend
from ovamos.services.perception.sim_backend import SimBackend
from ovamos.shared.messages import RgbdFrame
from ovamos.world.evaluator import GroundTruth
from ovamos.world.generate import generate_scene

WIDTH, HEIGHT = 640, 480
TARGETS_COUNT = 3


def _render(count: int) -> tuple[Any, list[RgbdFrame]]:
    from ovamos.world.render import SceneRenderer
    scene = generate_scene(SCENE_SEED)
    with SceneRenderer(scene, WIDTH, HEIGHT) as renderer:
        return scene, [renderer.render(x, y, yaw, seq=i)
                       for i, (x, y, yaw) in enumerate(camera_poses(GroundTruth(scene), count))]


def _timed_run(backend: PerceptionBackend, frames: list[RgbdFrame], targets: list[str]) -> float:
    """Frames per second for one pass over ``frames``."""
    start = time.perf_counter()
    for frame in frames:
        backend.score(frame, targets)
        backend.detect(frame, targets)
    return len(frames) / (time.perf_counter() - start)


def _summary(fps: list[float]) -> dict[str, Any]:
    return {"fps": round(statistics.median(fps), 3), "run_fps": [round(f, 3) for f in fps]}


def _stage_ms(backend: Any, frames: list[RgbdFrame], targets: list[str]) -> dict[str, Any]:
    """Median milliseconds of each hf stage, and of the boxes found, over ``frames``."""
    times: dict[str, list[float]] = {"score": [], "detect": [], "segment": []}
    boxes = []
    for frame in frames:
        t0 = time.perf_counter()
        backend.scorer(frame.rgb, targets)
        t1 = time.perf_counter()
        found = backend.detector(frame.rgb, targets)
        t2 = time.perf_counter()
        backend.segmenter(frame.rgb, [b.box for b in found])
        t3 = time.perf_counter()
        for stage, took in zip(times, (t1 - t0, t2 - t1, t3 - t2)):
            times[stage].append(took * 1e3)
        boxes.append(len(found))
    return {"stage_ms": {k: round(statistics.median(v), 1) for k, v in times.items()},
            "boxes": statistics.median(boxes)}


def _hf_devices() -> list[tuple[str, bool]]:
    import torch
    return [("cpu", False)] + ([("cuda", True)] if torch.cuda.is_available() else [])


def _bench_hf(frames: list[RgbdFrame], targets: list[str], runs: int,
              progress: Console | None) -> dict[str, Any]:
    import torch

    from ovamos.bench.random_models import loaded
    from ovamos.services.perception.config import HfBackendConfig
    from ovamos.services.perception.hf.backend import HfBackend
    from ovamos.services.perception.hf.loading import Placement

    out: dict[str, Any] = {}
    for device, fp16 in _hf_devices():
        placement = Placement.resolve(device, fp16)
        backend = HfBackend(*loaded("full", placement), placement, HfBackendConfig())
        _timed_run(backend, frames[:1], targets)  # warm-up: allocations, kernels, caches
        result = _summary([_timed_run(backend, frames, targets) for _ in range(runs)])
        result.update(_stage_ms(backend, frames, targets))
        result["dtype"] = str(placement.dtype).removeprefix("torch.")
        result["device_name"] = torch.cuda.get_device_name() if device == "cuda" else \
            f"CPU, {torch.get_num_threads()} threads"
        out[device] = result
        if progress:
            progress.print(f"hf {device}: {result['fps']:.3f} frames/s")
        del backend
    return out


def run_benchmark(frames: int = 1, runs: int = 3, sim_frames: int = 40, hf: bool = True,
                  progress: Console | None = None) -> dict[str, Any]:
    if frames < 1 or runs < 1 or sim_frames < 1:
        raise ValueError("frames, runs and sim_frames must be at least 1")
    scene, rendered = _render(max(frames, sim_frames))
    targets = sorted(scene.classes())[:TARGETS_COUNT]
    sim = SimBackend(scene)
    result: dict[str, Any] = {"width": WIDTH, "height": HEIGHT, "targets": targets, "runs": runs,
                              "sim": {"frames_per_run": sim_frames,
                                      **_summary([_timed_run(sim, rendered[:sim_frames], targets)
                                                  for _ in range(runs)])}}
    if progress:
        progress.print(f"sim: {result['sim']['fps']:.1f} frames/s")
    if hf:
        result["hf_frames_per_run"] = frames
        result["hf"] = _bench_hf(rendered[:frames], targets, runs, progress)
    return result


def print_table(console: Console, result: dict[str, Any]) -> None:
    table = Table("backend", "device", "frames/s (median)", "runs (frames/s)", "ms: score / detect / segment",
                  "boxes", title=f"Perception per {result['width']}x{result['height']} frame, "
                                 f"{len(result['targets'])} targets; median of {result['runs']} runs")
    sim = result["sim"]
    table.add_row("sim", "CPU", f"{sim['fps']:.1f}", ", ".join(f"{f:.1f}" for f in sim["run_fps"]), "-", "-")
    for device, r in result.get("hf", {}).items():
        stages = " / ".join(f"{r['stage_ms'][s]:.0f}" for s in ("score", "detect", "segment"))
        table.add_row(f"hf ({r['dtype']})", r["device_name"], f"{r['fps']:.3f}",
                      ", ".join(f"{f:.3f}" for f in r["run_fps"]), stages, f"{r['boxes']:g}")
    console.print(table)


def main(argv: list[str] | None = None) -> None:
    """``python -m ovamos.bench.perception`` (what ``ovamos bench perception`` runs)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=1, help="hf frames per run (~90 s each on 2 CPU cores)")
    parser.add_argument("--runs", type=int, default=3, help="runs (the median is reported)")
    parser.add_argument("--sim-frames", type=int, default=40, help="sim frames per run")
    parser.add_argument("--no-hf", dest="hf", action="store_false", help="skip the real models")
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    args = parser.parse_args(argv)
    err = Console(stderr=True)
    result = run_benchmark(frames=args.frames, runs=args.runs, sim_frames=args.sim_frames, hf=args.hf,
                           progress=None if args.json else err)
    if args.json:
        print(json.dumps(result))
    else:
        print_table(Console(), result)


if __name__ == "__main__":
    main()
