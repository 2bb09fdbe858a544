"""The search benchmark's tables as a terminal shows them: the paper's Tables I and II, ours beside
the paper's, the paired differences and the missed targets."""

from __future__ import annotations

from typing import Any

from rich.console import Console
from rich.table import Table

from ovamos.bench.policies import ABLATIONS, LABELS, PAPER
from ovamos.services.planner.policies import FINDER, GREEDY, NO_DECAY, OVAMOS, OVAMOS_PLUS, RANDOM, VLFM
from ovamos.shared.messages import Miss

TABLE_I = (RANDOM.name, VLFM.name, FINDER.name, OVAMOS.name)
TABLE_II = (GREEDY.name, NO_DECAY.name, OVAMOS.name)
#: Ours: the planner of services/planner/plus.py, its ablations, and the paper's best three to beat.
TABLE_PLUS = (FINDER.name, GREEDY.name, OVAMOS.name, *ABLATIONS, OVAMOS_PLUS.name)


def print_table(console: Console, result: dict[str, Any]) -> None:
    """Table I (baselines vs. the method) and Table II (ablations), ours beside the paper's."""
    scores = result["policies"]
    limit = "" if result.get("max_steps") is None else f", max {result['max_steps']} steps (quick run)"
    limit += f", {result.get('perception', 'ideal')} perception, {result.get('homes', 'default')} homes"
    limit += f", {result.get('base', 'kinematic')} base, {result.get('motion', 'stepwise')}"
    if result.get("base", "kinematic") != "kinematic" and "step_latency_s" in result:
        limit += f", {result['step_latency_s']:g} s a step besides motion"
    if result.get("odometry", "ideal") != "ideal" or result.get("localization"):
        limit += f", {result.get('odometry', 'ideal')} odometry, localization {'on' if result.get('localization') else 'off'}"
    for title, rows in (("Table I: comparison with baselines", TABLE_I),
                        ("Table II: ablations", TABLE_II), ("Ours: OVAMOS-plus and its ablations", TABLE_PLUS)):
        present = [p for p in rows if p in scores]
        if not present or (rows is TABLE_PLUS and OVAMOS_PLUS.name not in scores):
            continue
        timed = all("median_search_s" in scores[p] for p in present)  # a wheeled base: simulated time
        drifted = all("ate_median_m" in scores[p] for p in present)  # odometry erred: how far off
        table = Table("method", "episodes", "SR", "MSPL", "targets found", "wrong STOPs", "steps",
                      *(("search s (median / p90)",) if timed else ()),
                      *(("ATE m (median / p95)", "ATE aligned m", "RPE (10 steps)") if drifted else ()),
                      "paper SR", "paper MSPL",
                      title=f"{title} (seed {result['seed']}{limit})")
        for policy in present:
            s = scores[policy]
            paper_sr, paper_mspl = (f"{PAPER[policy][0]:.1f}%", f"{PAPER[policy][1]:.3f}") if policy in PAPER \
                else ("", "")
            label = "OVAMOS (full)" if rows is TABLE_II and policy == OVAMOS.name else LABELS[policy]
            table.add_row(label, str(s["episodes"]), f"{s['sr']:.1f}%", f"{s['mspl']:.3f}",
                          f"{s['targets_found']:.1f}%", str(s.get("wrong_stops", "")), f"{s.get('steps', 0):.0f}",
                          *((f"{s['median_search_s']:.0f} / {s['p90_search_s']:.0f}",) if timed else ()),
                          *((f"{s['ate_median_m']:.3f} / {s['ate_p95_m']:.3f}",
                             f"{s.get('ate_aligned_median_m', 0.0):.3f}",
                             f"{s['rpe_median_m']:.3f} m, {s['rpe_median_deg']:.2f} deg") if drifted else ()),
                          paper_sr, paper_mspl)
        console.print(table)
    for key, name in (("vs_ovamos", "OVAMOS"), ("vs_plus", "OVAMOS-plus")):
        if result.get(key):
            console.print(_paired_table(result[key], name))
    missed = {p: m for p, m in result.get("missed", {}).items() if m["targets"]}
    if missed:
        table = Table("method", "targets", *(m.value for m in Miss),
                      title="Targets missed, by the first stage they never reached")
        for policy, m in missed.items():
            table.add_row(LABELS.get(policy, policy), str(m["targets"]), *(str(m[k.value]) for k in Miss))
        console.print(table)
    spent = result.get("time_by_step") or {}
    if spent:
        kinds = sorted({k for shares in spent.values() for k in shares},
                       key=lambda k: -max(shares.get(k, 0.0) for shares in spent.values()))
        table = Table("method", *kinds, title="Where the search time goes: % of the simulated seconds, by kind of step")
        for policy, shares in spent.items():
            table.add_row(LABELS.get(policy, policy), *(f"{shares.get(k, 0.0):.1f}" for k in kinds))
        console.print(table)
    if result.get("code"):
        console.print("episodes by the code version that ran them: "
                      + ", ".join(f"{v} {n}" for v, n in result["code"].items()), highlight=False)
    total = sum(s["episodes"] for s in scores.values())
    console.print(f"{total} episodes in {result['seconds']:.0f} s on {result['workers']} worker(s): "
                  f"{result['episodes_per_min']:.1f} episodes/min")


def _paired_table(paired: dict[str, Any], name: str) -> Table:
    """``name`` minus each policy on the episodes both ran, with the bootstrap intervals."""
    table = Table("method", "episodes", f"{name} SR minus it", "95% CI", f"{name} MSPL minus it", "95% CI",
                  title=f"{name} against each policy on the same episodes (bootstrap)")
    for policy, d in paired.items():
        table.add_row(LABELS.get(policy, policy), str(d["episodes"]), f"{d['sr_diff']:+.1f}",
                      f"[{d['sr_ci'][0]:+.1f}, {d['sr_ci'][1]:+.1f}]", f"{d['mspl_diff']:+.3f}",
                      f"[{d['mspl_ci'][0]:+.3f}, {d['mspl_ci'][1]:+.3f}]")
    return table
