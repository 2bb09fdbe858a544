"""The search benchmark's pictures: the SR/MSPL chart, and one episode drawn from above (trajectory,
STOPs, the targets' instances and a legend) so that a person can see why it failed."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any

import cv2
import numpy as np

from ovamos.bench.episode import EpisodeResult
from ovamos.bench.policies import LABELS, PAPER, POLICY_ORDER
from ovamos.world.draw import MARGIN_M, draw_scene
from ovamos.world.scene import Scene

FONT = cv2.FONT_HERSHEY_SIMPLEX
INK = (30, 30, 30)
SR_COLOUR, MSPL_COLOUR = (180, 110, 30), (40, 140, 240)   # BGR: blue, orange
SUCCESS_COLOUR, FAILURE_COLOUR = (40, 160, 40), (40, 40, 220)
MISSED_COLOUR = (200, 40, 200)


def _put(image: np.ndarray, text: str, at: tuple[int, int], scale: float = 0.45,
         colour: tuple[int, int, int] = INK, centred: bool = False) -> None:
    if centred:
        width = cv2.getTextSize(text, FONT, scale, 1)[0][0]
        at = (at[0] - width // 2, at[1])
    cv2.putText(image, text, at, FONT, scale, colour, 1, cv2.LINE_AA)


def draw_chart(scores: dict[str, dict[str, Any]], height: int = 440) -> np.ndarray:
    """Grouped bars per policy: SR (as a fraction) and MSPL on one 0..1 axis, the paper's values
    as black ticks across the bars. A BGR image."""
    policies = [p for p in POLICY_ORDER if p in scores]
    left, top, bottom, group = 70, 75, 60, 150
    image = np.full((height, max(left + group * len(policies) + 20, 460), 3), 255, np.uint8)
    plot_h = height - top - bottom

    def y(value: float) -> int:
        return int(round(top + plot_h * (1 - min(max(value, 0.0), 1.0))))

    for tick in np.linspace(0, 1, 5):
        cv2.line(image, (left, y(tick)), (image.shape[1] - 10, y(tick)), (220, 220, 220), 1)
        _put(image, f"{tick:.2f}", (left - 45, y(tick) + 5), 0.4)
    _put(image, "Search benchmark: SR (as a fraction) and MSPL per policy", (left, 24), 0.5)
    _chart_key(image, left, 40)
    for i, policy in enumerate(policies):
        x0 = left + i * group + 25
        paper = (PAPER[policy][0] / 100, PAPER[policy][1]) if policy in PAPER else (None, None)
        ours = (scores[policy]["sr"] / 100, scores[policy]["mspl"])
        for j, (value, ref, colour) in enumerate(zip(ours, paper, (SR_COLOUR, MSPL_COLOUR))):
            xa = x0 + j * 50
            cv2.rectangle(image, (xa, y(value)), (xa + 45, y(0)), colour, -1)
            _put(image, f"{value:.2f}", (xa + 22, y(value) - 6), 0.4, centred=True)
            if ref is not None:
                cv2.line(image, (xa - 3, y(ref)), (xa + 48, y(ref)), (0, 0, 0), 2)
        _put(image, LABELS.get(policy, policy), (x0 + 47, y(0) + 22), 0.45, centred=True)
        _put(image, f"n={scores[policy]['episodes']}", (x0 + 47, y(0) + 42), 0.4, centred=True)
    return image


def _chart_key(image: np.ndarray, x: int, y: int) -> None:
    """SR and MSPL swatches and the paper's tick, in one row from (x, y) (the row's top)."""
    for name, colour in (("SR", SR_COLOUR), ("MSPL", MSPL_COLOUR)):
        cv2.rectangle(image, (x, y), (x + 14, y + 14), colour, -1)
        _put(image, name, (x + 20, y + 13), 0.45)
        x += 90
    cv2.line(image, (x, y + 7), (x + 24, y + 7), (0, 0, 0), 2)
    _put(image, "the paper", (x + 30, y + 13), 0.45)


def _world_to_px(image: np.ndarray, px_per_m: float) -> Callable[[float, float], tuple[int, int]]:
    """World metres -> pixels of a :func:`draw_scene` picture (same margin, y up)."""
    height = image.shape[0]
    return lambda x, y: (int(round((x + MARGIN_M) * px_per_m)),
                         int(round(height - (y + MARGIN_M) * px_per_m)))


def _draw_trajectory(image: np.ndarray, px: Callable[[float, float], tuple[int, int]],
                     trajectory: Sequence[Sequence[float]]) -> None:
    """The path coloured by time (cold = early, hot = late), so its direction and revisits show."""
    points = [px(x, y) for x, y, _ in trajectory]
    if len(points) < 2:
        return
    ramp = cv2.applyColorMap(np.linspace(0, 255, len(points) - 1).astype(np.uint8).reshape(-1, 1),
                             cv2.COLORMAP_JET).reshape(-1, 3)
    for (a, b), colour in zip(zip(points, points[1:]), ramp):
        cv2.line(image, a, b, tuple(int(c) for c in colour), 2, cv2.LINE_AA)


def _draw_pose(image: np.ndarray, px: Callable[[float, float], tuple[int, int]],
               pose: Sequence[float], fill: tuple[int, int, int], text: str, px_per_m: float) -> None:
    x, y, yaw = pose
    centre = px(x, y)
    cv2.circle(image, centre, int(0.2 * px_per_m), fill, -1, cv2.LINE_AA)
    cv2.circle(image, centre, int(0.2 * px_per_m), (0, 0, 0), 2, cv2.LINE_AA)
    cv2.line(image, centre, px(x + 0.4 * math.cos(yaw), y + 0.4 * math.sin(yaw)), (0, 0, 0), 2,
             cv2.LINE_AA)
    _put(image, text, (centre[0] - 5, centre[1] + 5), 0.45, (0, 0, 0))


def _draw_targets(image: np.ndarray, px: Callable[[float, float], tuple[int, int]], scene: Scene,
                  result: EpisodeResult, px_per_m: float) -> None:
    """A ring round every instance of every target: green when that target was found, magenta
    when it was missed; labelled T1.. in target order."""
    found = set(result.found)
    for n, target in enumerate(result.targets, 1):
        colour = SUCCESS_COLOUR if target in found else MISSED_COLOUR
        for obj in scene.instances(target):
            radius = int((0.5 * math.hypot(obj.sx, obj.sy) + 0.15) * px_per_m)
            centre = px(obj.x, obj.y)
            cv2.circle(image, centre, radius, colour, 3, cv2.LINE_AA)
            at = (min(centre[0] + radius, image.shape[1] - 30), max(centre[1] - radius, 18))
            _put(image, f"T{n}", at, 0.55, colour)  # kept inside the picture


def _draw_stops(image: np.ndarray, px: Callable[[float, float], tuple[int, int]],
                result: EpisodeResult, px_per_m: float) -> None:
    for n, stop in enumerate(result.stops, 1):
        colour = SUCCESS_COLOUR if stop.success else FAILURE_COLOUR
        centre = px(stop.x, stop.y)
        cv2.circle(image, centre, int(0.22 * px_per_m), colour, -1, cv2.LINE_AA)
        cv2.circle(image, centre, int(1.0 * px_per_m), colour, 1, cv2.LINE_AA)  # the 1 m (straight)
        _put(image, f"S{n}", (centre[0] - 9, centre[1] + 5), 0.45, (255, 255, 255))


def legend_lines(result: EpisodeResult) -> list[tuple[str, tuple[int, int, int]]]:
    """The replay's text: outcome, targets, path, why the agent stopped, every STOP."""
    found = set(result.found)
    verdict = "SUCCESS" if result.success else f"FAILURE: found {len(found & set(result.targets))}" \
                                               f"/{len(result.targets)}"
    lines = [(f"episode {result.episode_id}  policy {result.policy}", INK),
             (f"{verdict}   SPL {result.spl:.3f}", SUCCESS_COLOUR if result.success else FAILURE_COLOUR),
             (f"scene seed {result.scene_seed}", INK), ("targets:", INK)]
    why = {f.label: f.miss for f in result.funnel}
    lines += [(f"  T{n} {t}: " + ("found" if t in found else "missed" + (f" ({why[t].value})" if why.get(t) else "")),
               SUCCESS_COLOUR if t in found else MISSED_COLOUR) for n, t in enumerate(result.targets, 1)]
    lines += [(f"steps {result.steps}, decisions {result.decisions}, blocked {result.blocked}", INK),
              (f"path {result.path_m:.1f} m, shortest tour {result.shortest_m:.1f} m", INK),
              (f"agent: {result.state} {result.reason}".strip(), INK),
              (f"STOPs ({len(result.stops)}):", INK)]
    lines += [(f"  S{n} step {s.step} {s.label}: {'ok' if s.success else 'WRONG'}, "
               f"{s.distance_m:.2f} m to nearest", SUCCESS_COLOUR if s.success else FAILURE_COLOUR)
              for n, s in enumerate(result.stops, 1)]
    lines += [("", INK), ("key:", INK), ("  S = start, E = end (arrow: heading)", INK),
              ("  path: blue (early) -> red (late)", INK),
              ("  S1..: STOP, green ok / red wrong; thin ring 1 m", INK),
              ("  T1..: target instances, green found / magenta missed", INK)]
    return lines


def _legend(lines: Sequence[tuple[str, tuple[int, int, int]]], height: int, width: int = 480
            ) -> np.ndarray:
    panel = np.full((max(height, 22 * len(lines) + 30), width, 3), 250, np.uint8)
    for k, (text, colour) in enumerate(lines):
        _put(panel, text[:60], (12, 28 + 22 * k), 0.48, colour)
    return panel


def draw_replay(result: EpisodeResult, scene: Scene, px_per_m: float = 60.0) -> np.ndarray:
    """The scene from above with the episode drawn on it, and a legend to its right (BGR)."""
    image = draw_scene(scene, px_per_m=px_per_m)
    px = _world_to_px(image, px_per_m)
    _draw_targets(image, px, scene, result, px_per_m)
    _draw_trajectory(image, px, result.trajectory)
    _draw_stops(image, px, result, px_per_m)
    _draw_pose(image, px, result.trajectory[0], (255, 255, 255), "S", px_per_m)
    _draw_pose(image, px, result.trajectory[-1], (200, 200, 200), "E", px_per_m)
    panel = _legend(legend_lines(result), image.shape[0])
    if panel.shape[0] > image.shape[0]:
        image = cv2.copyMakeBorder(image, 0, panel.shape[0] - image.shape[0], 0, 0,
                                   cv2.BORDER_CONSTANT, value=(255, 255, 255))
    return np.hstack([image, panel])
