"""The latest map of a robot as a PNG, asked from its mapping service on demand.

The gateway keeps no map of its own: it queries ``map/snapshot`` when a
picture is requested, so it never holds megabytes per robot nor shows a map
staler than the mapping service's. The robot's path (the positions its
latest task reported) is drawn over the map.
"""

from __future__ import annotations

from collections.abc import Sequence

import cv2

from services.mapping.render import render_map
from shared.bus import Bus
from shared.messages import MapSnapshot
from shared.topology import TOPOLOGY

MAP_SNAPSHOT = TOPOLOGY["gateway"].port("queries", "map_snapshot")


class NoMap(LookupError):
    """No mapping service answered for the robot."""


def fetch_snapshot(bus: Bus, robot_id: str, timeout_s: float) -> MapSnapshot:
    """The first valid snapshot a mapping service answers; NoMap when none does (a malformed
    answer is counted by the bus and treated as none). Blocks: for HTTP worker threads."""
    snapshot = bus.get(MAP_SNAPSHOT.key(robot_id), MapSnapshot, timeout_s)
    if snapshot is None:
        raise NoMap(f"no map for robot {robot_id!r}: no mapping service answered with a valid map "
                    f"within {timeout_s} s")
    return snapshot


def map_png(snapshot: MapSnapshot, path: Sequence[tuple[float, float]] = (),
            layer: str | None = None) -> bytes:
    """PNG bytes of :func:`render_map`; ValueError for an unknown ``layer``."""
    ok, data = cv2.imencode(".png", render_map(snapshot, layer=layer, path=path))
    if not ok:
        raise ValueError("the map could not be encoded as PNG")
    return data.tobytes()
