"""The perception benchmark runs and reports what its table prints (sim part; hf is minutes)."""

from __future__ import annotations

import io

from rich.console import Console

from ovamos.bench.perception import main, print_table, run_benchmark


def test_the_sim_part_reports_frames_per_second_and_prints() -> None:
    result = run_benchmark(frames=1, runs=2, sim_frames=2, hf=False)
    assert result["sim"]["fps"] > 0 and len(result["sim"]["run_fps"]) == 2
    assert len(result["targets"]) == 3 and "hf" not in result
    out = io.StringIO()
    print_table(Console(file=out, width=200), result)
    assert f"{result['sim']['fps']:.1f}" in out.getvalue()


def test_json_output_is_one_object(capsys) -> None:
    import json
    main(["--no-hf", "--runs", "1", "--sim-frames", "1", "--json"])
    assert json.loads(capsys.readouterr().out)["sim"]["frames_per_run"] == 1
