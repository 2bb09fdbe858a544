"""ovamos bench homes: the statistics of generated homes, checked on a hand-made house, and the
command's JSON beside ProcTHOR-10K's figures."""

from __future__ import annotations

import json

import pytest
from typer.testing import CliRunner

from ovamos.bench.homes import PROCTHOR_10K, home_statistics
from ovamos.cli import app
from ovamos.world.prior import ObjectPrior
from tests.sim_scenes import two_rooms


def test_statistics_of_a_hand_made_house() -> None:
    """two_rooms: 24 m2, a 12 m2 kitchen and a 12 m2 office, three pieces of furniture (two
    fridges, a table: a desk for the prior) and a cup on the table."""
    scene = two_rooms()
    scene = scene.model_copy(update={"objects": tuple(
        o.model_copy(update={"cls": "desk"}) if o.cls == "table" else o for o in scene.objects)})
    stats = home_statistics([scene], ObjectPrior.load())
    assert stats["rooms per home (mean)"] == 2
    assert stats["home area m2 (median)"] == pytest.approx(24.0)
    assert stats["kitchen m2 (median)"] == pytest.approx(12.0)
    assert "bedroom m2 (median)" not in stats
    assert stats["m2 per piece of furniture"] == pytest.approx(24.0 / 3)
    assert stats["small objects per room (mean)"] == pytest.approx(0.5)
    assert stats["small objects per receptacle used (mean)"] == 1
    with pytest.raises(ValueError, match="no homes"):
        home_statistics([], ObjectPrior.load())


def test_the_command_compares_a_tier_with_procthor() -> None:
    out = CliRunner().invoke(app, ["bench", "homes", "--count", "6", "--homes", "large", "--json"])
    assert out.exit_code == 0, out.output
    result = json.loads(out.output)
    assert (result["homes"], result["count"]) == ("large", 6)
    assert 8 <= result["ours"]["rooms per home (mean)"] <= 12
    assert result["procthor_10k"] == PROCTHOR_10K
    bad = CliRunner().invoke(app, ["bench", "homes", "--homes", "huge"])
    assert bad.exit_code != 0 and "unknown home tier 'huge'" in bad.output
