"""Shared runtime of the OVAMOS services: keys, messages, codec, Zenoh bus, config."""

__version__ = "0.1.0"
