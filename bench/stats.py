"""Statistics of a search benchmark's episodes: SR, MSPL, missed targets, paired differences."""

from __future__ import annotations

import statistics
from collections import Counter
from collections.abc import Iterable, Sequence
from typing import Any

import numpy as np

from ovamos.bench.episode import EpisodeResult
from ovamos.bench.policies import policy_rank
from ovamos.shared.messages import Miss


def policy_scores(results: Sequence[EpisodeResult]) -> dict[str, dict[str, float | int]]:
    """Per policy (paper order): SR in %, MSPL, episodes, the % of all targets found (a
    finer signal than SR when few episodes succeed), wrong STOPs, the mean steps an episode and, on a
    wheeled base, the median and 90th percentile search time (simulated seconds); where odometry
    erred, the median and 95th percentile of the episodes' median trajectory error (ATE, metres)
    and the median relative error (RPE over 10 steps, metres and degrees)."""
    scores: dict[str, dict[str, float | int]] = {}
    for policy in sorted({r.policy for r in results}, key=policy_rank):
        mine = [r for r in results if r.policy == policy]
        found = sum(len(set(r.found) & set(r.targets)) for r in mine)
        scores[policy] = {"sr": round(100 * statistics.fmean(r.success for r in mine), 1),
                          "mspl": round(statistics.fmean(r.spl for r in mine), 3),
                          "episodes": len(mine),
                          "targets_found": round(100 * found / sum(len(r.targets) for r in mine), 1),
                          "wrong_stops": sum(not stop.success for r in mine for stop in r.stops),
                          "steps": round(statistics.fmean(r.steps for r in mine), 1)}
        times = [r.search_s for r in mine if r.search_s is not None]
        if len(times) == len(mine):  # a wheeled base's run: search time in simulated seconds
            scores[policy] |= {"median_search_s": round(float(np.median(times)), 1),
                               "p90_search_s": round(float(np.percentile(times, 90)), 1)}
        errors = [r.odometry for r in mine if r.odometry is not None]
        if len(errors) == len(mine):  # odometry erred: how far the belief was from the truth
            ate = [e.ate_median_m for e in errors]
            scores[policy] |= {"ate_median_m": round(float(np.median(ate)), 3),
                               "ate_p95_m": round(float(np.percentile(ate, 95)), 3),
                               "ate_aligned_median_m": round(float(np.median([e.ate_aligned_median_m
                                                                              for e in errors])), 3),
                               "rpe_median_m": round(float(np.median([e.rpe_trans_median_m for e in errors])), 4),
                               "rpe_median_deg": round(float(np.median([e.rpe_rot_median_deg for e in errors])), 3)}
    return scores


def time_by_step(results: Sequence[EpisodeResult]) -> dict[str, dict[str, float]]:
    """Per policy on a wheeled base: where the search time went, the % of all its episodes' simulated
    seconds by kind of step (``EpisodeResult.time_by_step``), largest first; nothing for a policy
    with an episode that did not record it (the kinematic base, older files)."""
    out: dict[str, dict[str, float]] = {}
    for policy in sorted({r.policy for r in results}, key=policy_rank):
        mine = [r.time_by_step for r in results if r.policy == policy]
        if not mine or any(t is None for t in mine):
            continue
        total: Counter[str] = Counter()
        for times in mine:
            total.update(times or {})
        whole = sum(total.values()) or 1.0
        out[policy] = {kind: round(100 * t / whole, 1) for kind, t in total.most_common()}
    return out


def miss_reasons(results: Sequence[EpisodeResult]) -> dict[str, dict[str, int]]:
    """Per policy: how many targets were missed at each stage (:class:`Miss`), and how many were
    searched for. Results read from files written before the funnel was recorded count nothing."""
    out: dict[str, dict[str, int]] = {}
    for r in sorted(results, key=lambda r: policy_rank(r.policy)):
        counts = out.setdefault(r.policy, {"targets": 0, **{m.value: 0 for m in Miss}})
        for funnel in r.funnel:
            counts["targets"] += 1
            if (miss := funnel.miss) is not None:
                counts[miss.value] += 1
    return out


def paired_differences(results: Sequence[EpisodeResult], reference: str = "ovamos",
                       resamples: int = 2000, seed: int = 0) -> dict[str, dict[str, Any]]:
    """Each policy against ``reference`` on the episodes both ran: the mean difference
    (reference minus policy) in SR (%), MSPL and steps with a 95 % bootstrap interval over episodes.

    Why: with 120 episodes one episode is 0.8 points of SR, and policies share episodes, so an
    ordering is only worth reporting when the paired interval excludes zero. The resampling is
    seeded afresh for each pair: the same two policies' results give the same interval whatever
    other policies the run had (a table merged from runs with other policies agrees with one run)."""
    by_policy = results_by_policy(results)
    ref = by_policy.get(reference, {})
    out: dict[str, dict[str, Any]] = {}
    for policy in sorted(by_policy, key=policy_rank):
        if policy != reference and (pair := paired(ref, by_policy[policy], resamples, seed)) is not None:
            out[policy] = pair
    return out


def results_by_policy(results: Iterable[EpisodeResult]) -> dict[str, dict[str, EpisodeResult]]:
    """Results by policy, then episode id (what :func:`paired` takes)."""
    by_policy: dict[str, dict[str, EpisodeResult]] = {}
    for r in results:
        by_policy.setdefault(r.policy, {})[r.episode_id] = r
    return by_policy


def paired(a: dict[str, EpisodeResult], b: dict[str, EpisodeResult], resamples: int = 2000,
           seed: int = 0) -> dict[str, Any] | None:
    """``a`` minus ``b`` on the episodes (by id) both hold: SR (%), MSPL and steps, each with a
    95 % bootstrap interval; None if none is shared."""
    shared = sorted(set(a) & set(b))
    if not shared:
        return None
    diff = np.array([[a[e].success - b[e].success, a[e].spl - b[e].spl, a[e].steps - b[e].steps]
                     for e in shared], dtype=float)
    resampled = np.random.default_rng(seed).integers(0, len(shared), (resamples, len(shared)))
    means = diff[resampled].mean(axis=1)
    lo, hi = np.percentile(means, [2.5, 97.5], axis=0)
    mean = diff.mean(axis=0)
    return {"episodes": len(shared),
            "sr_diff": round(100 * mean[0], 1), "sr_ci": [round(100 * lo[0], 1), round(100 * hi[0], 1)],
            "mspl_diff": round(mean[1], 3), "mspl_ci": [round(lo[1], 3), round(hi[1], 3)],
            "steps_diff": round(mean[2], 1), "steps_ci": [round(lo[2], 1), round(hi[2], 1)]}


def search_time_ratio(a: dict[str, EpisodeResult], b: dict[str, EpisodeResult], resamples: int = 2000,
                      seed: int = 0) -> dict[str, Any] | None:
    """The median search time (simulated seconds) of ``a`` and of ``b`` on the episodes both timed,
    and ``b``'s median over ``a``'s with a 95 % bootstrap interval (the same episodes resampled for
    both: paired); None unless both timed a shared episode (a kinematic base has no time)."""
    shared = sorted(e for e in set(a) & set(b) if a[e].search_s is not None and b[e].search_s is not None)
    if not shared:
        return None
    times = np.array([[a[e].search_s, b[e].search_s] for e in shared], dtype=float)
    resampled = np.random.default_rng(seed).integers(0, len(shared), (resamples, len(shared)))
    medians = np.median(times[resampled], axis=1)
    lo, hi = np.percentile(medians[:, 1] / medians[:, 0], [2.5, 97.5])
    median_a, median_b = np.median(times, axis=0)
    return {"episodes": len(shared), "a": round(float(median_a), 1), "b": round(float(median_b), 1),
            "b_over_a": round(float(median_b / median_a), 3), "b_over_a_ci": [round(float(lo), 3), round(float(hi), 3)]}
