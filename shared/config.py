"""Configuration models and config files, without Zenoh.

Every config in the project derives from :class:`StrictModel` (unknown keys are
errors: a typo in a TOML file must not pass silently). Cores (mapping, planner,
perception backends, the benchmark) import their configs from here, so that
loading a core never loads Zenoh; only :mod:`ovamos.shared.service` and the adapters do.
"""

from __future__ import annotations

import json
import tomllib
from pathlib import Path
from typing import Any, TypeVar

from pydantic import BaseModel, ConfigDict, ValidationError

__all__ = ["StrictModel", "ServiceConfig", "ServiceConfigError", "read_config", "merged", "parse_overrides",
           "format_override"]


class ServiceConfigError(ValueError):
    """A config file that cannot be read or does not fit the model it is loaded into."""


class StrictModel(BaseModel):
    """Base of every config model: unknown keys are errors (typos must not pass)."""

    model_config = ConfigDict(extra="forbid")


class ServiceConfig(StrictModel):
    """Base of every service's config."""


C = TypeVar("C", bound=BaseModel)


def read_config(model: type[C], path: str | Path | None, overrides: dict[str, Any] | None = None,
                *, what: str = "config") -> C:
    """Read a config file (TOML, or JSON by suffix), apply ``overrides`` and validate it.

    Every problem (unreadable file, bad syntax, a table of the wrong type, a key the
    model does not know, a value out of range) is one :class:`ServiceConfigError`
    naming the file and each offending field.
    """
    data: dict[str, Any] = {}
    if path is not None:
        path = Path(path)
        try:
            text = path.read_text()
            data = tomllib.loads(text) if path.suffix.lower() == ".toml" else json.loads(text)
        except (OSError, ValueError) as exc:
            raise ServiceConfigError(f"cannot read config {path}: {exc}") from None
        if not isinstance(data, dict):
            raise ServiceConfigError(f"config {path} must hold a table/object of settings, "
                                     f"not {type(data).__name__}")
    data = merged(data, overrides or {})
    try:
        return model.model_validate(data)
    except ValidationError as exc:
        problems = "; ".join(f"{'.'.join(map(str, e['loc']))}: {e['msg']}" for e in exc.errors())
        raise ServiceConfigError(f"invalid {what}: {problems}") from None


def merged(base: dict[str, Any], changes: dict[str, Any]) -> dict[str, Any]:
    """``base`` with ``changes`` applied: a table into the table it changes, key by key, so a change
    to one setting of a section keeps the section's others (a profile's config, the demo's or a
    fleet's changes on top); anything else replaces the value."""
    out = dict(base)
    for key, value in changes.items():
        old = out.get(key)
        out[key] = merged(old, value) if isinstance(old, dict) and isinstance(value, dict) else value
    return out


def format_override(key: str, value: Any) -> str:
    """``KEY=JSON``, as :func:`parse_overrides` reads it (``ovamos run --set``)."""
    return f"{key}={json.dumps(value, separators=(',', ':'))}"


def parse_overrides(items: list[str]) -> dict[str, Any]:
    """``["robots=[\"r1\"]", "episode_index=2"]`` as a dict of top-level settings; a value that is
    not JSON is refused (a string is written with its quotes: ``name="x"``)."""
    overrides: dict[str, Any] = {}
    for item in items:
        key, sep, raw = item.partition("=")
        if not sep or not key.strip():
            raise ServiceConfigError(f"--set {item!r}: write KEY=JSON")
        try:
            overrides[key.strip()] = json.loads(raw)
        except ValueError as exc:
            raise ServiceConfigError(f"--set {item!r}: the value is not JSON ({exc})") from None
    return overrides
