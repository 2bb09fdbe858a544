"""The mapping service: frames + perception results in, map snapshots out.

Frames and perception results arrive on separate keys and are matched by
frame seq. A frame whose result has not come within ``match_timeout_s`` is
fused without values (obstacles, explored area, frontiers still grow), so a
slow or absent perception service never stalls the map. The value layers
follow the target list of the newest perception result.

Everything runs on the service's one thread (fusing, snapshots for the
periodic put and for queries, checkpoints), so the map needs no lock and a
snapshot is always of one consistent state (:meth:`MapState.snapshot` copies).
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

from pydantic import Field

from services.mapping.checkpoint import CheckpointError, load_checkpoint, save_checkpoint
from services.mapping.config import MappingConfig
from services.mapping.state import MapState
from shared.bus import BusCore
from shared.messages import MapSnapshot, PerceptionResult, RgbdFrame
from shared.service import Service


class MappingServiceConfig(MappingConfig):
    publish_hz: float = Field(default=2.0, gt=0, description="snapshot publication rate")
    match_timeout_s: float = Field(default=1.0, gt=0, description="wait this long for a frame's result")
    max_pending: int = Field(default=16, ge=1, description="frames or results waiting for their pair")
    checkpoint_path: Path | None = Field(
        default=None, description="'{robot_id}' in it is replaced: one map per robot, never another's")
    checkpoint_every_s: float = Field(default=5.0, gt=0)


class MappingService(Service):
    name = "mapping"
    Config = MappingServiceConfig
    config: MappingServiceConfig

    def __init__(self, bus: BusCore, config: MappingServiceConfig) -> None:
        if config.checkpoint_path is not None:
            config = config.model_copy(update={"checkpoint_path": Path(
                str(config.checkpoint_path).replace("{robot_id}", bus.robot_id))})
        super().__init__(bus, config)
        self.tick_hz = config.publish_hz
        self._frames: dict[int, tuple[RgbdFrame, float]] = {}
        self._results: dict[int, PerceptionResult] = {}
        self._published_seq = -2
        self._last_checkpoint = time.monotonic()
        self.state = self._initial_state()

    def _initial_state(self) -> MapState:
        path = self.config.checkpoint_path
        if path is not None and path.exists():
            try:
                state = load_checkpoint(path, self.config)
                self.log.info("resumed the map from %s (last frame seq %d)", path, state.seq)
                return state
            except CheckpointError as exc:
                self.log.error("%s; starting a fresh map", exc)
        return MapState(self.config)

    def start(self) -> None:
        self.wire({"rgbd": self._on_frame, "perception_result": self._on_result},
                  answers={"map_snapshot": self.snapshot})

    # -- inputs --------------------------------------------------------------------------------
    def _on_frame(self, frame: RgbdFrame) -> None:
        result = self._results.pop(frame.seq, None)
        if result is None:
            self._frames.setdefault(frame.seq, (frame, time.monotonic()))  # a repeat keeps its wait
            _trim(self._frames, self.config.max_pending)
            return
        self.state.apply(frame, result)

    def _on_result(self, result: PerceptionResult) -> None:
        pending = self._frames.pop(result.seq, None)
        if pending is None:
            self._results[result.seq] = result
            _trim(self._results, self.config.max_pending)
            return
        self.state.apply(pending[0], result)

    # -- periodic work -------------------------------------------------------------------------
    def tick(self) -> None:
        now = time.monotonic()
        expired = sorted(s for s, (_, t) in self._frames.items() if now - t > self.config.match_timeout_s)
        for seq in expired:
            self.state.apply(self._frames.pop(seq)[0], None)
        if self.state.seq != self._published_seq:
            snapshot = self.snapshot()
            self.out["map_snapshot"].put(snapshot)
            self._published_seq = snapshot.seq
        if self.config.checkpoint_path and now - self._last_checkpoint >= self.config.checkpoint_every_s:
            self._checkpoint()

    def snapshot(self) -> MapSnapshot:
        return self.state.snapshot(time.time(), with_confidence=False)

    def _checkpoint(self) -> None:
        assert self.config.checkpoint_path is not None
        save_checkpoint(self.state, self.config.checkpoint_path, time.time())
        self._last_checkpoint = time.monotonic()

    def info(self) -> dict[str, Any]:
        return {"seq": self.state.seq, "after_action": self.state.after_action,
                "layers": list(self.state.layers),
                "explored_m2": round(float(self.state.explored.sum()) * self.config.resolution ** 2, 2),
                "objects": len(self.state.objects.instances()),
                "pending_frames": len(self._frames), "pending_results": len(self._results)}

    def stop(self) -> None:
        if self.config.checkpoint_path:
            self._checkpoint()


def _trim(pending: dict[int, Any], limit: int) -> None:
    """Drop the oldest (lowest seq) entries beyond ``limit``."""
    for seq in sorted(pending)[:max(0, len(pending) - limit)]:
        del pending[seq]
