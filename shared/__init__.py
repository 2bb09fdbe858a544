"""Shared runtime of the OVAMOS services: keys, messages, codec, Zenoh bus, config."""
