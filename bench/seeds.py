"""Which benchmark seeds are for development and which for the results we report.

A report seed is drawn once (``secrets.randbelow``), written in the docs before any run on it, and
run once the settings it reports are fixed. Running it again on changed code while choosing
settings is tuning on it: it has become a development seed, and a new report seed is drawn. So
``ovamos bench compare`` refuses to pair runs of different code on a report seed unless told
(``--allow-code-change``: a change that chose nothing on that seed, said so where its numbers go).
"""

from __future__ import annotations

__all__ = ["DEVELOPMENT_SEEDS", "REPORT_SEEDS"]

DEVELOPMENT_SEEDS = frozenset({1})
"""Tune on these (docs/benchmarks/search.md#seeds)."""

REPORT_SEEDS: dict[int, str] = {
    2026: "the search tables (docs/benchmarks/search.md)",
    5503743: "odometry and localization (docs/benchmarks/search.md#odometry-and-localization)",
    6639414: "continuous motion against stepwise (docs/benchmarks/search.md#continuous-motion)",
    8899186: "odometry and localization with turned starts (docs/benchmarks/search.md#odometry-and-localization)",
}
"""Each report seed and what it reports: a new one is added here, and in the docs, before it is run."""
