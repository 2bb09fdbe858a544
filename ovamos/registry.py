"""Which services ``ovamos run`` can start, imported lazily.

Lazy imports keep a robot that only runs the base driver free of the heavy
dependencies (torch, MuJoCo) of the services it does not run.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

from ovamos.shared.topology import TOPOLOGY

if TYPE_CHECKING:  # importing ovamos.shared.service loads Zenoh; profiles only need the names
    from ovamos.shared.service import Service

#: every service ``ovamos run`` can start: its adapter, as the topology declares it
SERVICES: dict[str, str] = {name: node.adapter for name, node in TOPOLOGY.items()}


class UnknownServiceError(LookupError):
    """A service name ``ovamos run`` cannot start."""


def service_class(name: str) -> type[Service]:
    if name not in SERVICES:
        raise UnknownServiceError(f"unknown service {name!r}; available: {', '.join(SERVICES)}")
    module, _, attr = SERVICES[name].partition(":")
    return getattr(importlib.import_module(module), attr)
