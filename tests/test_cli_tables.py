"""The command line's tables for people stay readable on an 80-column terminal."""

from __future__ import annotations

from rich.console import Console

from ovamos.cli import live_table
from ovamos.shared.bus.status import LiveService
from ovamos.shared.messages import CounterSet, ServiceStats


def test_status_keeps_its_headers_and_numbers_whole_at_80_columns() -> None:
    stats = ServiceStats(robot_id="robot1", service="base_driver", instance="0", pid=1234567, started=0.0,
                         counters={"a": CounterSet(received=1234567, published=7654321, dropped=3),
                                   "b": CounterSet(received=1, malformed=2, errors=4, denied=5)})
    services = [LiveService("robot1", "base_driver", "0", stats), LiveService("sim", "perception", "2", None)]
    console = Console(width=80, record=True)
    console.print(live_table(services))
    text = console.export_text()
    assert max(len(line) for line in text.splitlines()) <= 80 and "…" not in text
    header = next(line for line in text.splitlines() if "dropped" in line).split()
    assert header == ["robot", "service", "pid", "in", "out", "dropped", "bad", "errors", "denied"]
    row = next(line for line in text.splitlines() if line.startswith("robot1") or " robot1 " in line).split()
    assert row == ["robot1", "base_driver", "1234567", "1234568", "7654321", "3", "2", "4", "5"]
    assert "perception#2" in text  # an instance other than 0 is named


def test_up_help_names_every_shipped_profile() -> None:
    from typer.testing import CliRunner

    from ovamos.cli import app
    from ovamos.profiles import PROFILE_DIR
    shipped = sorted(p.stem for p in PROFILE_DIR.glob("*.toml"))
    assert len(shipped) >= 7
    text = " ".join(CliRunner().invoke(app, ["up", "--help"], env={"COLUMNS": "200"}).output.split())
    assert all(f" {name} " in f" {text.replace('|', ' ').replace(',', ' ')} " for name in shipped), (shipped, text)
