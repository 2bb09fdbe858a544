"""Search benchmark (bench/search.py and its jobs, stats, tables and draw modules): determinism
across runs and worker counts, the table and JSON shapes, the files written, and the replay picture.

Episodes are cut to a few steps (the quick-run ``max_steps`` override) so the whole module runs in
well under a minute on two cores; what is checked does not depend on the episodes' length.
"""

from __future__ import annotations

import io
import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from rich.console import Console

from ovamos.bench.draw import draw_chart, legend_lines
from ovamos.bench.episode import EpisodeResult
from ovamos.bench.funnel import StopRecord, TargetFunnel
from ovamos.bench.jobs import EpisodeFailed, Job, iter_results
from ovamos.bench.provenance import code_version
from ovamos.bench.search import (
    CHART_FILE,
    EPISODES_FILE,
    RUN_FILE,
    SUMMARY_FILE,
    TIMINGS_FILE,
    UNRECORDED,
    SearchError,
    SearchRun,
    jsonl_line,
    main,
    parse_episode_id,
    parse_policies,
    read_results,
    replay,
    run_search,
    summary,
    write_outputs,
)
from ovamos.bench.stats import miss_reasons, paired_differences, policy_scores
from ovamos.bench.tables import print_table

SEED, EPISODES, STEPS = 0, 2, 15
POLICIES = ("random", "ovamos")


def quick_run(workers: int) -> SearchRun:
    return run_search(EPISODES, SEED, POLICIES, workers=workers, max_steps=STEPS)


def jsonl(run: SearchRun) -> str:
    return "".join(jsonl_line(r) for r in run.results)


@pytest.fixture(scope="module")
def run() -> SearchRun:
    return quick_run(workers=1)


def fake(policy: str, index: int, success: bool, spl: float, found: tuple[str, ...] = (),
         targets: tuple[str, ...] = ("cup", "bed", "tv"), stops: list[StopRecord] | None = None,
         funnel: list[TargetFunnel] | None = None) -> EpisodeResult:
    """A hand-made result: scores and pictures are checked against known numbers."""
    return EpisodeResult(episode_id=f"0-{index}", policy=policy, scene_seed=1, targets=targets,
                         success=success, spl=spl, found=found, steps=10, path_m=2.0, shortest_m=1.0,
                         state="done" if success else "failed", decisions=3, blocked=0,
                         stops=stops or [], funnel=funnel or [],
                         trajectory=[(1.0, 1.0, 0.0), (1.5, 1.0, 0.0)], seconds=0.5)


def funnel(**stages: int) -> list[TargetFunnel]:
    """cup at the given stages, bed found, tv never in view."""
    return [TargetFunnel(label="cup", **stages), TargetFunnel(label="bed", seen=1, detected=2, confirmed=3,
                                                              stopped=9), TargetFunnel(label="tv")]


# -- arguments -----------------------------------------------------------------------------------
def test_policies_come_back_in_the_papers_order_and_unknown_ones_are_refused() -> None:
    assert parse_policies("ovamos, random,vlfm,ovamos") == ("random", "vlfm", "ovamos")
    with pytest.raises(SearchError, match="ovamso"):
        parse_policies("ovamos,ovamso")
    with pytest.raises(SearchError):
        parse_policies(" , ")


def test_episode_ids_parse_and_bad_ones_are_refused() -> None:
    assert parse_episode_id("0-3") == (0, 3)
    assert parse_episode_id("-2-7") == (-2, 7)
    for bad in ("3", "a-b", "0-", "0--1"):
        with pytest.raises(SearchError):
            parse_episode_id(bad)


# -- runs ----------------------------------------------------------------------------------------
def test_a_run_covers_every_pair_sorted_within_the_step_limit(run: SearchRun) -> None:
    assert [(r.policy, r.episode_id) for r in run.results] == [
        ("ovamos", "0-0"), ("ovamos", "0-1"), ("random", "0-0"), ("random", "0-1")]
    assert all(1 <= r.steps <= STEPS and len(r.trajectory) == r.steps + 1 for r in run.results)


def test_same_seed_gives_byte_identical_jsonl_without_wall_clock(run: SearchRun, tmp_path: Path) -> None:
    again = quick_run(workers=1)
    write_outputs(tmp_path / "a", run, summary(run))
    write_outputs(tmp_path / "b", again, summary(again))
    first = (tmp_path / "a" / EPISODES_FILE).read_bytes()
    assert first == (tmp_path / "b" / EPISODES_FILE).read_bytes()
    assert all("seconds" not in json.loads(line) for line in first.decode().splitlines())


def test_two_worker_processes_give_the_results_of_one(run: SearchRun) -> None:
    assert jsonl(quick_run(workers=2)) == jsonl(run)


@pytest.mark.parametrize("workers", [1, 2])
def test_a_failing_episode_names_its_work_unit(workers: int) -> None:
    jobs = [Job("no-such-policy", SEED, 0, STEPS), Job("no-such-policy", SEED, 1, STEPS)]
    with pytest.raises(EpisodeFailed, match=r"no-such-policy 0-[01]: ValueError"):
        list(iter_results(jobs, workers=workers))


# -- scores, table, JSON -------------------------------------------------------------------------
def test_scores_are_success_rate_in_percent_and_mean_spl() -> None:
    wrong = StopRecord(step=4, label="tv", x=0.0, y=0.0, success=False, distance_m=3.0)
    results = [fake("ovamos", 0, True, 0.5, ("cup", "bed", "tv")),
               fake("ovamos", 1, False, 0.0, ("cup",), stops=[wrong, wrong]), fake("random", 0, False, 0.0)]
    scores = policy_scores(results)
    assert list(scores) == ["random", "ovamos"]
    assert scores["ovamos"] == {"sr": 50.0, "mspl": 0.25, "episodes": 2, "targets_found": 66.7,
                                "wrong_stops": 2, "steps": 10.0}
    assert scores["random"]["sr"] == 0.0 and scores["random"]["targets_found"] == 0.0


def test_paired_differences_compare_the_same_episodes_with_a_seeded_interval() -> None:
    ovamos = [fake("ovamos", i, True, 0.6) for i in range(6)]
    always = [fake("random", i, False, 0.0) for i in range(6)]
    half = [fake("finder", i, i % 2 == 0, 0.6 if i % 2 == 0 else 0.0) for i in range(8)]  # 2 extra episodes
    paired = paired_differences(ovamos + always + half)
    assert list(paired) == ["random", "finder"]
    assert paired["random"] == {"episodes": 6, "sr_diff": 100.0, "sr_ci": [100.0, 100.0],
                                "mspl_diff": 0.6, "mspl_ci": [0.6, 0.6],
                                "steps_diff": 0.0, "steps_ci": [0.0, 0.0]}
    finder = paired["finder"]
    assert finder["episodes"] == 6 and finder["sr_diff"] == 50.0
    assert 0.0 <= finder["sr_ci"][0] < 50.0 < finder["sr_ci"][1] <= 100.0
    assert paired_differences(ovamos + always + half) == paired  # seeded
    many = [fake(p, i, (i * (3 + k)) % 5 < 2, 0.03 * ((i * (7 + k)) % 11))
            for k, p in enumerate(("ovamos", "vlfm", "finder")) for i in range(30)]
    alone = paired_differences([r for r in many if r.policy != "vlfm"])
    assert alone["finder"]["mspl_ci"][0] < alone["finder"]["mspl_diff"] < alone["finder"]["mspl_ci"][1]
    assert paired_differences(many)["finder"] == alone["finder"]  # whatever other policies ran
    assert paired_differences(always + half) == {}  # no reference policy, nothing to compare


def test_missed_targets_are_counted_by_the_first_stage_they_never_reached() -> None:
    results = [fake("ovamos", 0, False, 0.0, ("bed",), funnel=funnel(seen=2, detected=4)),
               fake("ovamos", 1, False, 0.0, ("bed",), funnel=funnel(seen=2, wrong_stops=1)),
               fake("random", 0, False, 0.0), fake("random", 1, False, 0.0, funnel=funnel())]
    missed = miss_reasons(results)
    assert list(missed) == ["random", "ovamos"]
    assert missed["ovamos"] == {"targets": 6, "wrong stop": 1, "never in view": 2, "never detected": 0,
                                "never confirmed": 1, "not reached": 0}
    assert missed["random"]["targets"] == 3 and missed["random"]["never in view"] == 2
    out = io.StringIO()
    print_table(Console(file=out, width=200), {"policies": policy_scores(results), "missed": missed,
                                               "seconds": 1.0, "episodes_per_min": 1.0, "seed": 0,
                                               "workers": 1, "max_steps": None})
    missed_table = out.getvalue().split("Targets missed")[1]
    row = next(line for line in missed_table.splitlines() if "OVAMOS" in line)
    assert [cell.strip() for cell in row.split("│")[1:-1]] == ["OVAMOS", "6", "1", "2", "0", "1", "0"]


def test_summary_is_the_documented_json_object(run: SearchRun) -> None:
    result = json.loads(json.dumps(summary(run)))
    assert set(result["policies"]) == set(POLICIES)
    for scores in result["policies"].values():
        assert {"sr", "mspl", "episodes"} <= set(scores)
        assert scores["episodes"] == EPISODES and 0 <= scores["sr"] <= 100 and 0 <= scores["mspl"] <= 1
    assert result["seconds"] >= 0 and result["max_steps"] == STEPS
    assert {p: m["targets"] for p, m in result["missed"].items()} == {p: 3 * EPISODES for p in POLICIES}


def test_tables_list_the_papers_rows_in_order_with_its_numbers() -> None:
    policies = ("random", "vlfm", "finder", "ovamos-greedy", "ovamos-nodecay", "ovamos")
    scores = policy_scores([fake(p, 0, False, 0.0) for p in policies])
    out = io.StringIO()
    print_table(Console(file=out, width=200), {"policies": scores, "seconds": 60.0, "episodes_per_min": 6.0,
                                               "seed": 0, "workers": 2, "max_steps": None})
    text = out.getvalue()
    table_i, table_ii = text.split("Table II")
    rows_i = [table_i.index(name) for name in ("Random", "VLFM", "Finder", "OVAMOS")]
    rows_ii = [table_ii.index(name) for name in ("w/o POMDP", "w/o value decay", "OVAMOS (full)")]
    assert rows_i == sorted(rows_i) and rows_ii == sorted(rows_ii)
    for paper in ("55.0%", "0.497", "28.3%", "0.198", "12.5%", "0.075", "27.5%", "0.154", "45.0%", "0.410"):
        assert paper in text
    assert "6.0 episodes/min" in text


def test_main_prints_one_json_object_and_writes_the_files(tmp_path: Path,
                                                           capsys: pytest.CaptureFixture[str]) -> None:
    log = io.StringIO()  # not a terminal: a progress line per episode instead of a bar
    main(episodes=1, seed=SEED, policies="random", workers=1, as_json=True, out=tmp_path,
         max_steps=STEPS, err=Console(file=log))
    result = json.loads(capsys.readouterr().out)
    assert log.getvalue().startswith("[1/1 ") and "] random 0-0: found" in log.getvalue()
    assert result["policies"]["random"]["episodes"] == 1
    for name in (EPISODES_FILE, TIMINGS_FILE, SUMMARY_FILE):
        assert (tmp_path / name).stat().st_size > 0
    assert json.loads((tmp_path / SUMMARY_FILE).read_text())["policies"] == result["policies"]
    assert [json.loads(line)["seconds"] >= 0 for line in (tmp_path / TIMINGS_FILE).read_text().splitlines()] \
        == [True]
    assert cv2.imread(str(tmp_path / CHART_FILE)) is not None


def test_jsonl_reads_back_to_the_same_results(run: SearchRun, tmp_path: Path) -> None:
    write_outputs(tmp_path, run, summary(run))
    back = read_results(tmp_path / EPISODES_FILE)
    assert [jsonl_line(r) for r in back] == [jsonl_line(r) for r in run.results]
    (tmp_path / "bad.jsonl").write_text(jsonl_line(run.results[0]) + "{not json\n")
    with pytest.raises(SearchError, match="bad.jsonl:2"):
        read_results(tmp_path / "bad.jsonl")



def test_a_run_cut_short_resumes_to_the_files_of_an_uninterrupted_one(run: SearchRun, tmp_path: Path,
                                                                     capsys: pytest.CaptureFixture[str]) -> None:
    main(episodes=1, seed=SEED, policies="random", workers=1, out=tmp_path, max_steps=STEPS,
         as_json=True, err=Console(file=io.StringIO()))
    capsys.readouterr()
    timings = tmp_path / TIMINGS_FILE  # as written before timing lines named the code version
    timings.write_text("".join(json.dumps({k: v for k, v in json.loads(line).items() if k != "code"}) + "\n"
                               for line in timings.read_text().splitlines()))
    with (tmp_path / EPISODES_FILE).open("a") as file:  # a crash in the middle of the next write
        file.write(jsonl_line(run.results[-1])[:40])
    log = io.StringIO()
    main(episodes=EPISODES, seed=SEED, policies=",".join(POLICIES), workers=1, out=tmp_path, max_steps=STEPS,
         as_json=True, resume=True, err=Console(file=log))
    result = json.loads(capsys.readouterr().out)
    code = code_version()
    assert f"1 episodes kept (by code version: {UNRECORDED}: 1), 3 to run on {code}" in log.getvalue()
    assert log.getvalue().count("\n[") == 3
    assert (tmp_path / EPISODES_FILE).read_text() == jsonl(run)
    assert result["resumed"] == 1 and result["policies"] == policy_scores(run.results)
    assert result["code"] == {UNRECORDED: 1, code: 3}
    lines = [json.loads(line) for line in timings.read_text().splitlines()]
    assert sorted((t["episode_id"], t["policy"]) for t in lines) == sorted((r.episode_id, r.policy) for r in run.results)
    assert [t.get("code") for t in lines] == [None, code, code, code]  # the kept line as it was


def test_a_resume_with_other_settings_or_no_settings_file_is_refused(tmp_path: Path) -> None:
    main(episodes=1, seed=SEED, policies="random", workers=1, out=tmp_path, max_steps=STEPS, as_json=True,
         err=Console(file=io.StringIO()))
    with pytest.raises(SearchError, match="perception 'ideal' there, 'realistic' here"):
        run_search(1, SEED, ("random",), workers=1, max_steps=STEPS, perception="realistic", out=tmp_path,
                   resume=True)
    (tmp_path / RUN_FILE).unlink()
    with pytest.raises(SearchError, match="run.json does not say"):
        run_search(1, SEED, ("random",), workers=1, max_steps=STEPS, out=tmp_path, resume=True)
    with pytest.raises(SearchError, match="--resume needs --out"):
        run_search(1, SEED, ("random",), workers=1, max_steps=STEPS, resume=True)

# -- pictures ------------------------------------------------------------------------------------
def test_chart_bars_grow_with_the_scores() -> None:
    low = draw_chart(policy_scores([fake("ovamos", 0, False, 0.0)]))
    high = draw_chart(policy_scores([fake("ovamos", 0, True, 0.9)]))
    assert low.shape == high.shape and low.ndim == 3 and low.shape[0] >= 300
    assert (high != 255).sum() > (low != 255).sum()  # taller bars cover more of the white


def test_legend_says_which_stop_was_wrong_and_which_target_was_missed() -> None:
    wrong = StopRecord(step=7, label="cup", x=1.0, y=1.0, success=False, distance_m=2.5)
    text = [line for line, _ in legend_lines(fake("ovamos", 3, False, 0.0, ("bed",), stops=[wrong],
                                                  funnel=funnel(seen=1, wrong_stops=1)))]
    assert any("FAILURE: found 1/3" in line for line in text)
    assert any("cup: missed (wrong stop)" in line for line in text)
    assert any("tv: missed (never in view)" in line for line in text) and any("bed: found" in line for line in text)
    assert any("S1 step 7 cup: WRONG, 2.50 m" in line for line in text)


def test_replay_reruns_the_episode_and_draws_it(run: SearchRun, tmp_path: Path) -> None:
    write_outputs(tmp_path, run, summary(run))
    rerun_png, rerun = replay("0-1", tmp_path / "rerun", "ovamos", max_steps=STEPS)
    stored = next(r for r in run.results if r.episode_id == "0-1" and r.policy == "ovamos")
    assert jsonl_line(rerun) == jsonl_line(stored)
    read_png, read = replay("0-1", tmp_path / "read", "ovamos", source=tmp_path / EPISODES_FILE)
    assert jsonl_line(read) == jsonl_line(stored)
    image = cv2.imread(str(read_png))
    assert image is not None and image.shape[0] >= 300 and image.shape[1] >= 800
    assert np.array_equal(image, cv2.imread(str(rerun_png)))
    with pytest.raises(SearchError, match="no episode 0-1 with policy vlfm"):
        replay("0-1", tmp_path, "vlfm", source=tmp_path / EPISODES_FILE)


def test_a_run_with_a_perception_preset_and_a_home_tier_says_so_and_bad_names_are_refused() -> None:
    hard = run_search(1, SEED, ("ovamos",), workers=1, max_steps=STEPS, perception="hard", homes="large")
    result = summary(hard)
    assert (result["perception"], result["homes"]) == ("hard", "large")
    out = io.StringIO()
    print_table(Console(file=out, width=200), result)
    assert "hard perception, large homes" in out.getvalue()
    with pytest.raises(SearchError, match="unknown perception preset 'perfect'"):
        run_search(1, SEED, ("ovamos",), workers=1, perception="perfect")
    with pytest.raises(SearchError, match="unknown home tier 'huge'"):
        run_search(1, SEED, ("ovamos",), workers=1, homes="huge")


def test_ovamos_plus_and_an_ablation_run_under_their_names_and_get_their_own_tables() -> None:
    ours = run_search(1, SEED, ("ovamos-plus-noverify", "ovamos-plus", "ovamos"), workers=1, max_steps=STEPS)
    assert [r.policy for r in ours.results] == ["ovamos", "ovamos-plus", "ovamos-plus-noverify"]
    result = json.loads(json.dumps(summary(ours)))
    assert set(result["vs_plus"]) == {"ovamos", "ovamos-plus-noverify"}
    out = io.StringIO()
    print_table(Console(file=out, width=200), result)
    text = out.getvalue()
    assert "Ours: OVAMOS-plus and its ablations" in text and "plus w/o verifying" in text
    assert "OVAMOS-plus against each policy" in text
    with pytest.raises(SearchError, match="ovamos-plus-nothing"):
        parse_policies("ovamos-plus-nothing")
