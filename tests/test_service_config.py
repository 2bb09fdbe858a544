"""Service config files: TOML or JSON, validated against the service's model.

A typo in a config key must stop the service at start-up with a message that
names the key, not be silently ignored while a default is used instead.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from pydantic import ValidationError

from ovamos.services.diag import service as diag
from ovamos.shared.service import ServiceConfig, ServiceConfigError, load_config

SERVICE = diag.TestPatternService


def test_no_file_gives_the_defaults() -> None:
    config = load_config(SERVICE, None)
    assert isinstance(config, SERVICE.Config)
    assert config == SERVICE.Config()


def test_toml_file(tmp_path: Path) -> None:
    path = tmp_path / "tp.toml"
    path.write_text("rate_hz = 2.5\nwidth = 64\nheight = 48\nseed = 7\n")
    config = load_config(SERVICE, path)
    assert (config.rate_hz, config.width, config.height, config.seed) == (2.5, 64, 48, 7)


def test_json_file(tmp_path: Path) -> None:
    path = tmp_path / "tp.json"
    path.write_text(json.dumps({"rate_hz": 3, "width": 32, "seed": 1}))
    config = load_config(SERVICE, str(path))
    assert (config.rate_hz, config.width, config.height, config.seed) == (3.0, 32, 480, 1)


def test_overrides_win_over_the_file(tmp_path: Path) -> None:
    path = tmp_path / "tp.toml"
    path.write_text("width = 64\nseed = 7\n")
    config = load_config(SERVICE, path, {"seed": 9})
    assert (config.width, config.seed) == (64, 9)


@pytest.mark.parametrize("suffix,text", [(".toml", "widht = 64\n"), (".json", '{"widht": 64}')])
def test_unknown_key_is_named(tmp_path: Path, suffix: str, text: str) -> None:
    path = tmp_path / f"tp{suffix}"
    path.write_text(text)
    with pytest.raises(ServiceConfigError, match="widht") as info:
        load_config(SERVICE, path)
    assert "testpattern" in str(info.value)


def test_unknown_override_is_named() -> None:
    with pytest.raises(ServiceConfigError, match="colour"):
        load_config(SERVICE, None, {"colour": "red"})


@pytest.mark.parametrize("text", ['width = "wide"\n', "rate_hz = 0\n", "width = 4\n", "seed = 1.5\n",
                                  "rate_hz = [1]\n"])
def test_bad_value_is_a_config_error(tmp_path: Path, text: str) -> None:
    path = tmp_path / "tp.toml"
    path.write_text(text)
    key = text.split(" ")[0]
    with pytest.raises(ServiceConfigError, match=key):
        load_config(SERVICE, path)


def test_missing_file_is_a_config_error(tmp_path: Path) -> None:
    with pytest.raises(ServiceConfigError, match="absent.toml"):
        load_config(SERVICE, tmp_path / "absent.toml")


def test_directory_is_a_config_error(tmp_path: Path) -> None:
    with pytest.raises(ServiceConfigError):
        load_config(SERVICE, tmp_path)


@pytest.mark.parametrize("name,text", [("tp.toml", "width = = 3"), ("tp.json", "{width: 3}"),
                                       ("tp.toml", b"\xff\xfe width = 3"), ("tp.json", b"\x80")])
def test_malformed_file_is_a_config_error(tmp_path: Path, name: str, text: str | bytes) -> None:
    path = tmp_path / name
    if isinstance(text, bytes):
        path.write_bytes(text)
    else:
        path.write_text(text)
    with pytest.raises(ServiceConfigError, match=name):
        load_config(SERVICE, path)


@pytest.mark.parametrize("text", ["[1, 2]", "null", '"text"', "3"])
def test_json_file_that_is_not_an_object_is_a_config_error(tmp_path: Path, text: str) -> None:
    """Once escaped as AttributeError ('list' object has no attribute 'update')."""
    path = tmp_path / "tp.json"
    path.write_text(text)
    with pytest.raises(ServiceConfigError, match="tp.json"):
        load_config(SERVICE, path)


def test_base_config_rejects_unknown_keys() -> None:
    """Every service config inherits 'extra=forbid' from ServiceConfig."""
    class Empty(ServiceConfig):
        pass

    with pytest.raises(ValidationError, match="x"):
        Empty.model_validate({"x": 1})
