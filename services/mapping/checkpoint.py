"""Map checkpoints: written atomically, read back with a clear error when damaged.

A checkpoint is a compressed :class:`MapSnapshot` that also carries the
per-layer fusion confidences and searched areas, so a restarted mapping service resumes exactly.
It carries the map's odometry session too: the map of an earlier session is
kept beside the checkpoint under its session id (:func:`session_path`), never
resumed.
"""

from __future__ import annotations

from pathlib import Path

from ovamos.services.mapping.config import MappingConfig
from ovamos.services.mapping.state import MapState
from ovamos.shared.atomic import write_atomic
from ovamos.shared.messages import DecodeError, MapSnapshot


class CheckpointError(ValueError):
    """A checkpoint that cannot be used (damaged, or made for another grid)."""


def save_checkpoint(state: MapState, path: str | Path, stamp: float) -> None:
    """Write atomically (:func:`ovamos.shared.atomic.write_atomic`): a crash never leaves half a file."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_atomic(path, state.snapshot(stamp).to_bytes())


def session_path(path: str | Path, odom_session: str) -> Path:
    """Where the map of an earlier odometry session is kept: ``map.ckpt`` -> ``map.<session>.ckpt``
    (a session id holds only letters, digits, '-' and '_': see ovamos.shared.messages.OdomSession)."""
    path = Path(path)
    return path.with_name(f"{path.stem}.{odom_session or 'no-session'}{path.suffix}")


def load_checkpoint(path: str | Path, config: MappingConfig) -> MapState:
    try:
        snapshot = MapSnapshot.from_bytes(Path(path).read_bytes())
    except (OSError, DecodeError) as exc:
        raise CheckpointError(f"checkpoint {path} is unusable: {exc}") from None
    try:
        return MapState.from_snapshot(snapshot, config)
    except ValueError as exc:
        raise CheckpointError(f"checkpoint {path}: {exc}") from None
