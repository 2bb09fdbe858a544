"""Who is alive on the Zenoh network, and what each instance reports (``ovamos status``)."""

from __future__ import annotations

from dataclasses import dataclass

import zenoh

from ovamos.shared import keys
from ovamos.shared.messages import DecodeError, ServiceStats


@dataclass(frozen=True)
class LiveService:
    robot_id: str
    service: str
    instance: str
    stats: ServiceStats | None  # None when it is alive but did not answer in time


def live_services(session: zenoh.Session, robot_id: str = keys.ANY, timeout_s: float = 2.0
                  ) -> list[LiveService]:
    """Instances holding a liveliness token, with their stats where they answer."""
    alive = set()
    for reply in session.liveliness().get(keys.alive(robot_id), timeout=timeout_s):
        if reply.ok is not None:
            alive.add(keys.parse_service_key(str(reply.ok.key_expr)))
    stats: dict[keys.ServiceKey, ServiceStats] = {}
    if alive:
        for reply in session.get(keys.stats(robot_id), timeout=timeout_s):
            if reply.ok is None:
                continue
            try:
                stats[keys.parse_service_key(str(reply.ok.key_expr))] = \
                    ServiceStats.from_bytes(reply.ok.payload.to_bytes())
            except (DecodeError, keys.KeyExprError):
                continue  # a foreign or broken answer: the instance shows without stats
    return [LiveService(*k, stats.get(k)) for k in sorted(alive)]
