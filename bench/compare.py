"""Two benchmark runs side by side on the episodes both hold: ``ovamos bench compare A B``.

For a question one run cannot answer: does the method lose on wheeled bases (``--base kinematic``
against ``--base kobuki``, same seed), did a change help (the run before against the run after).
Per policy: each run's SR, MSPL and mean steps on the shared episodes, and B minus A with 95 %
bootstrap intervals (:func:`ovamos.bench.stats.paired`, steps too), and B's mean steps over A's;
when both ran on wheels (``--motion continuous`` against stepwise), their median search times in
simulated seconds and B's over A's (:func:`ovamos.bench.stats.search_time_ratio`). Two runs of
different code on a report seed are refused (:mod:`ovamos.bench.seeds`).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from rich.console import Console
from rich.table import Table

from ovamos.bench.episode import EpisodeResult
from ovamos.bench.policies import LABELS, policy_rank
from ovamos.bench.search import (
    EPISODES_FILE,
    RUN_FILE,
    SETTING_DEFAULTS,
    UNRECORDED,
    SearchError,
    code_versions,
    read_results,
)
from ovamos.bench.seeds import DEVELOPMENT_SEEDS, REPORT_SEEDS
from ovamos.bench.stats import paired, results_by_policy, search_time_ratio

__all__ = ["compare_runs", "print_comparison"]


def _run(folder: Path) -> tuple[dict[str, Any], dict[str, dict[str, EpisodeResult]]]:
    """A run's settings (with the code versions its episodes ran) and its results by policy, then
    episode id."""
    episodes = folder / EPISODES_FILE
    if not episodes.exists():
        raise SearchError(f"{folder}: no {EPISODES_FILE} (the --out folder of an ovamos bench search run?)")
    settings = json.loads((folder / RUN_FILE).read_text()) if (folder / RUN_FILE).exists() else {}
    results = read_results(episodes, torn_tail=True)
    return {**SETTING_DEFAULTS, **settings, "code": sorted(code_versions(folder, results))}, results_by_policy(results)


def _same_code_on_a_report_seed(a: dict[str, Any], b: dict[str, Any]) -> None:
    """The report-seed protocol (:mod:`ovamos.bench.seeds`): two runs of different code on a report
    seed are refused. Runs whose episodes name no code version (from before they were recorded)
    cannot be told apart and pass."""
    seed = a.get("seed")
    if seed != b.get("seed") or seed not in REPORT_SEEDS or UNRECORDED in a["code"] + b["code"]:
        return
    if a["code"] != b["code"]:
        raise SearchError(
            f"A ran code {', '.join(a['code'])} and B {', '.join(b['code'])} on report seed {seed} "
            f"({REPORT_SEEDS[seed]}): comparing code on a report seed is choosing settings on it, which makes "
            f"it a development seed. Compare on a development seed ({', '.join(map(str, sorted(DEVELOPMENT_SEEDS)))}), "
            "or pass --allow-code-change for a change that chose nothing on this seed (and say so where the "
            "numbers go)")


def _means(results: dict[str, EpisodeResult], shared: list[str]) -> dict[str, float]:
    n = len(shared)
    return {"sr": round(100 * sum(results[e].success for e in shared) / n, 1),
            "mspl": round(sum(results[e].spl for e in shared) / n, 3),
            "steps": round(sum(results[e].steps for e in shared) / n, 1)}


def compare_runs(a: Path, b: Path, allow_code_change: bool = False) -> dict[str, Any]:
    """The ``--json`` object: each run's folder and settings (``code``: the versions its episodes
    ran), and per shared policy the scores of both on their shared episodes and ``b_minus_a``.
    Runs of different code on a report seed are refused unless ``allow_code_change``."""
    (settings_a, runs_a), (settings_b, runs_b) = _run(a), _run(b)
    if not allow_code_change:
        _same_code_on_a_report_seed(settings_a, settings_b)
    policies: dict[str, Any] = {}
    for policy in sorted(set(runs_a) & set(runs_b), key=policy_rank):
        # paired() gives first minus second: B minus A
        diff = paired(runs_b[policy], runs_a[policy])
        if diff is None:
            continue
        shared = sorted(set(runs_a[policy]) & set(runs_b[policy]))
        means_a, means_b = _means(runs_a[policy], shared), _means(runs_b[policy], shared)
        policies[policy] = {"a": means_a, "b": means_b, "b_minus_a": diff,
                            "steps_ratio": round(means_b["steps"] / max(means_a["steps"], 1e-9), 3)}
        timed = search_time_ratio(runs_a[policy], runs_b[policy])
        if timed is not None:
            policies[policy]["search_s"] = timed
    if not policies:
        raise SearchError(f"{a} and {b} share no (policy, episode): same seed and policies?")
    return {"a": {"folder": str(a), **settings_a}, "b": {"folder": str(b), **settings_b}, "policies": policies}


def _label(run: dict[str, Any]) -> str:
    return (f"{run.get('base')} base, {run.get('motion')}, {run.get('perception')} perception, "
            f"seed {run.get('seed')}")


def print_comparison(console: Console, result: dict[str, Any]) -> None:
    a, b = result["a"], result["b"]
    table = Table("method", "episodes", "SR A", "SR B", "B - A (95% CI)", "MSPL A", "MSPL B", "B - A (95% CI)",
                  "steps A", "steps B", "B / A",
                  title=f"A: {_label(a)} ({a['folder']})\nB: {_label(b)} ({b['folder']})")
    for policy, p in result["policies"].items():
        d = p["b_minus_a"]
        table.add_row(LABELS.get(policy, policy), str(d["episodes"]), f"{p['a']['sr']:.1f}%", f"{p['b']['sr']:.1f}%",
                      f"{d['sr_diff']:+.1f} [{d['sr_ci'][0]:+.1f}, {d['sr_ci'][1]:+.1f}]",
                      f"{p['a']['mspl']:.3f}", f"{p['b']['mspl']:.3f}",
                      f"{d['mspl_diff']:+.3f} [{d['mspl_ci'][0]:+.3f}, {d['mspl_ci'][1]:+.3f}]",
                      f"{p['a']['steps']:.0f}", f"{p['b']['steps']:.0f}", f"{p['steps_ratio']:.2f}x")
    console.print(table)
    timed = {policy: p["search_s"] for policy, p in result["policies"].items() if "search_s" in p}
    if timed:
        times = Table("method", "episodes", "median search A (s)", "median search B (s)", "B / A (95% CI)",
                      title="search time, simulated seconds (first command to the last STOP)")
        for policy, t in timed.items():
            times.add_row(LABELS.get(policy, policy), str(t["episodes"]), f"{t['a']:.0f}", f"{t['b']:.0f}",
                          f"{t['b_over_a']:.2f} [{t['b_over_a_ci'][0]:.2f}, {t['b_over_a_ci'][1]:.2f}]")
        console.print(times)
