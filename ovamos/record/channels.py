"""Which keys a recording holds, and how each is stored as a raw MCAP channel.

The list is derived from :data:`ovamos.shared.topology.TOPOLOGY` (every key a service publishes,
with its message type), never kept a second time here: a new key in the topology is
recorded, replayed and viewed without a change in this package.

A raw channel stores each payload exactly as it was published (a replay puts the same
bytes back on the wire). Its topic is the Zenoh key; its metadata names the key, the robot,
the message type and its version, so a reader knows what it holds without our code. JSON
messages carry their JSON schema (Foxglove shows their fields), binary ones the codec's
description (see :mod:`ovamos.shared.codec`).
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import foxglove

from ovamos.shared import keys
from ovamos.shared.messages import BinaryMessage, JsonMessage
from ovamos.shared.topology import TOPOLOGY

__all__ = ["UnknownKeyError", "RawChannel", "recorded_ports", "select", "from_metadata"]

JSON_ENCODING = "json"
BINARY_ENCODING = "ovamos-binary"
BINARY_SCHEMA_ENCODING = "ovamos-codec"
META_KEY, META_ROBOT, META_MESSAGE, META_VERSION = ("ovamos.key", "ovamos.robot_id", "ovamos.message",
                                                    "ovamos.version")


class UnknownKeyError(ValueError):
    """A key name that is not one the services publish, or a channel this version cannot read."""


def recorded_ports() -> dict[str, type[JsonMessage] | type[BinaryMessage]]:
    """Every key some service publishes, by its builder's name in :mod:`ovamos.shared.keys`, with its type."""
    out: dict[str, type] = {}
    for node in TOPOLOGY.values():
        for port in node.outputs:
            if port.message is not None:
                out.setdefault(port.name, port.message)
    return out


def select(names: Sequence[str] | None) -> dict[str, type]:
    """The recorded ports named in ``names`` (all when None or empty); unknown names raise."""
    ports = recorded_ports()
    if not names:
        return ports
    unknown = sorted(set(names) - set(ports))
    if unknown:
        raise UnknownKeyError(f"unknown key(s) {', '.join(unknown)}; known: {', '.join(sorted(ports))}")
    return {n: ports[n] for n in names}


@dataclass(frozen=True)
class RawChannel:
    """The raw channel of one key of one robot."""

    name: str
    message: type
    robot_id: str

    @property
    def key(self) -> str:
        return getattr(keys, self.name)(self.robot_id)

    @property
    def encoding(self) -> str:
        return JSON_ENCODING if issubclass(self.message, JsonMessage) else BINARY_ENCODING

    def metadata(self) -> dict[str, str]:
        return {META_KEY: self.name, META_ROBOT: self.robot_id, META_MESSAGE: self.message.__name__,
                META_VERSION: str(self.message.VERSION)}

    def schema(self) -> foxglove.Schema:
        name = f"ovamos.{self.message.__name__}"
        if issubclass(self.message, JsonMessage):
            return foxglove.Schema(name=name, encoding="jsonschema",
                                   data=json.dumps(self.message.model_json_schema()).encode())
        arrays = {n: {"dtypes": list(s.dtypes), "ndim": s.ndim} for n, s in self.message.ARRAYS.items()}
        description = {"codec": "shared/codec.py", "kind": self.message.KIND, "version": self.message.VERSION,
                       "arrays": arrays}
        return foxglove.Schema(name=name, encoding=BINARY_SCHEMA_ENCODING, data=json.dumps(description).encode())

    def open(self, context: foxglove.Context) -> foxglove.Channel:
        return foxglove.Channel(self.key, schema=self.schema(), message_encoding=self.encoding,
                                context=context, metadata=self.metadata())


def from_metadata(metadata: Mapping[str, str], ports: Mapping[str, type] | None = None) -> RawChannel | None:
    """The raw channel a recorded channel's metadata describes; None for a view channel.

    Raises :class:`UnknownKeyError` for a key this version does not publish, or a message
    type or version other than this version's (its payloads would not decode).
    """
    name = metadata.get(META_KEY)
    if name is None:
        return None
    ports = recorded_ports() if ports is None else ports
    message = ports.get(name)
    if message is None:
        raise UnknownKeyError(f"recorded key {name!r} is not one this version publishes")
    recorded = (metadata.get(META_MESSAGE), metadata.get(META_VERSION))
    if recorded != (message.__name__, str(message.VERSION)):
        raise UnknownKeyError(f"recorded key {name!r} holds {recorded[0]} v{recorded[1]}, this version "
                              f"reads {message.__name__} v{message.VERSION}")
    return RawChannel(name, message, metadata.get(META_ROBOT, ""))
