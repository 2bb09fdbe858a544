"""``ovamos bench compare A B``: two runs on their shared episodes, B minus A."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from ovamos.bench.compare import compare_runs
from ovamos.bench.episode import EpisodeResult
from ovamos.bench.search import EPISODES_FILE, RUN_FILE, TIMINGS_FILE, SearchError, jsonl_line
from ovamos.bench.seeds import DEVELOPMENT_SEEDS, REPORT_SEEDS
from tests.polling import ovamos_unwrapped
from tests.test_bench_search import fake


def _run(folder: Path, results: list[EpisodeResult], **settings: object) -> Path:
    folder.mkdir()
    (folder / RUN_FILE).write_text(json.dumps({"seed": 0, "perception": "ideal", "homes": "default",
                                               "max_steps": None, **settings}))
    (folder / EPISODES_FILE).write_text("".join(jsonl_line(r) for r in results))
    return folder


def test_b_minus_a_on_the_shared_episodes_with_steps(tmp_path: Path) -> None:
    a = _run(tmp_path / "a", [fake("ovamos", i, i < 2, 0.5 if i < 2 else 0.0) for i in range(4)])  # no base: kinematic
    b_results = [fake("ovamos", i, True, 0.5) for i in range(3)] + [fake("finder", 0, True, 0.5)]
    for r in b_results:
        r.steps = 15
    b = _run(tmp_path / "b", b_results, base="kobuki")
    result = compare_runs(a, b)
    assert result["a"]["base"] == "kinematic" and result["b"]["base"] == "kobuki"
    assert list(result["policies"]) == ["ovamos"]  # finder ran in B only
    p = result["policies"]["ovamos"]
    assert p["a"] == {"sr": pytest.approx(66.7), "mspl": pytest.approx(0.333), "steps": 10.0}  # episodes 0-2
    assert p["b"] == {"sr": 100.0, "mspl": 0.5, "steps": 15.0} and p["steps_ratio"] == 1.5
    d = p["b_minus_a"]
    assert d["episodes"] == 3 and d["sr_diff"] == pytest.approx(33.3) and d["steps_diff"] == 5.0
    assert d["sr_ci"][0] <= d["sr_diff"] <= d["sr_ci"][1]


def test_runs_with_nothing_in_common_or_no_results_are_refused(tmp_path: Path) -> None:
    a = _run(tmp_path / "a", [fake("ovamos", 0, True, 0.5)])
    b = _run(tmp_path / "b", [fake("finder", 0, True, 0.5)])
    with pytest.raises(SearchError, match="share no"):
        compare_runs(a, b)
    with pytest.raises(SearchError, match="no episodes.jsonl"):
        compare_runs(a, tmp_path)
    done = ovamos_unwrapped("bench", "compare", str(a), str(tmp_path / "missing"))
    assert done.returncode == 2 and "no episodes.jsonl" in done.stderr + done.stdout


def test_two_timed_runs_compare_their_median_search_times(tmp_path: Path) -> None:
    """Continuous against stepwise on wheels: B's median search time over A's, paired over the
    episodes both timed; a kinematic run has no time to compare."""
    def timed(i: int, seconds: float | None) -> EpisodeResult:
        result = fake("ovamos", i, True, 0.5)
        result.search_s = seconds
        return result
    a = _run(tmp_path / "a", [timed(i, 100.0 * (i + 1)) for i in range(5)], base="kobuki")
    b = _run(tmp_path / "b", [timed(i, 40.0 * (i + 1)) for i in range(4)] + [timed(4, None)], base="kobuki",
             motion="continuous")
    result = compare_runs(a, b)
    assert result["b"]["motion"] == "continuous" and result["a"]["motion"] == "stepwise"
    t = result["policies"]["ovamos"]["search_s"]
    assert t["episodes"] == 4 and (t["a"], t["b"]) == (250.0, 100.0) and t["b_over_a"] == 0.4
    assert t["b_over_a_ci"] == [0.4, 0.4]  # every episode 0.4x: no spread to resample
    kinematic = _run(tmp_path / "k", [fake("ovamos", i, True, 0.5) for i in range(5)])
    assert "search_s" not in compare_runs(kinematic, b)["policies"]["ovamos"]
    done = ovamos_unwrapped("bench", "compare", str(a), str(b))
    assert done.returncode == 0 and "search time, simulated seconds" in done.stdout and "0.40 [0.40," in done.stdout


def _timed_by(folder: Path, code: str) -> Path:
    """``folder``'s episodes, each timing line naming ``code`` as the version that ran it."""
    lines = [json.loads(line) for line in (folder / EPISODES_FILE).read_text().splitlines()]
    (folder / TIMINGS_FILE).write_text("".join(json.dumps({"episode_id": r["episode_id"], "policy": r["policy"],
                                                           "seconds": 1.0, "steps": 10, "code": code}) + "\n"
                                               for r in lines))
    return folder


def test_runs_of_different_code_on_a_report_seed_are_refused_unless_allowed(tmp_path: Path) -> None:
    (report,) = [s for s in REPORT_SEEDS if s == 5503743]
    results = [fake("ovamos", i, i % 2 == 0, 0.5) for i in range(4)]
    a = _timed_by(_run(tmp_path / "a", results, seed=report), "abc123")
    b = _timed_by(_run(tmp_path / "b", results, seed=report), "def456")
    with pytest.raises(SearchError, match=rf"A ran code abc123 and B def456 on report seed {report}.*development seed"):
        compare_runs(a, b)
    allowed = compare_runs(a, b, allow_code_change=True)
    assert allowed["a"]["code"] == ["abc123"] and allowed["b"]["code"] == ["def456"]
    same = _timed_by(_run(tmp_path / "same", results, seed=report), "abc123")
    assert compare_runs(a, same)["policies"]["ovamos"]["b_minus_a"]["sr_diff"] == 0.0  # one code: fine
    dev = min(DEVELOPMENT_SEEDS)
    assert compare_runs(_timed_by(_run(tmp_path / "d1", results, seed=dev), "abc123"),
                        _timed_by(_run(tmp_path / "d2", results, seed=dev), "def456"))["policies"]
    done = ovamos_unwrapped("bench", "compare", str(a), str(b))
    assert done.returncode == 2 and "--allow-code-change" in done.stderr + done.stdout
    assert ovamos_unwrapped("bench", "compare", str(a), str(b), "--allow-code-change").returncode == 0
