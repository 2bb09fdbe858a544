"""A stack left up for task after task (processes, real Zenoh, HTTP): every task that can succeed
succeeds about as fast as from a fresh start, a failed one says why per target, memory stays flat."""

from __future__ import annotations

import pytest

from ovamos.bench.soak import ABSENT_STEPS, fresh_steps, run_soak, soak_tasks

pytestmark = pytest.mark.system  # processes, routers, browsers or real-time devices: make test-all

TASKS = 5
"""The episode's targets, a pair, a class the house lacks, the pair again, a cancelled single: every
kind of task :func:`soak_tasks` makes (``ovamos bench soak`` runs as many more as asked)."""
MARGIN_STEPS = 120
"""Over a fresh start's steps: the robot starts where the last task left it, anywhere in the demo's
13 x 10 m house; crossing it costs ~50 forward steps plus their turns, after the 12-turn
look-around (the 20-task soak's most was +107)."""
RSS_GROWTH = 1.25
"""Each service's RSS after the last task over after the first: per-task state is released."""


@pytest.mark.timeout(900)
def test_five_tasks_in_one_session_each_solvable_as_if_fresh(tmp_path) -> None:
    tasks = soak_tasks(TASKS)
    assert any(t.max_steps == ABSENT_STEPS for t in tasks) and any(t.cancel_after for t in tasks)
    assert len({t.targets for t in tasks if t.can_succeed}) < sum(t.can_succeed for t in tasks)  # repeats
    reference = fresh_steps(tasks)
    result = run_soak(tasks, out_dir=tmp_path, on_task=print)  # shown when it fails
    rows = result["tasks"]
    assert len(rows) == TASKS and all(n == 0 for n in result["restarts"].values()), result["restarts"]
    for task, row in zip(tasks, rows):
        if task.cancel_after is not None:
            assert row["status"] == "cancelled", row
        elif task.max_steps == ABSENT_STEPS:  # the house has none: fails, and says so per target
            assert row["status"] == "failed" and row["message"].startswith(f"step limit {ABSENT_STEPS} reached"), row
            assert [m["label"] for m in row["misses"]] == list(task.targets), row
            assert row["misses"][0]["stage"] in ("never detected", "never confirmed"), row
            assert task.targets[0] in row["message"], row
        else:
            ok, fresh = reference[task.targets]
            assert ok, f"{task.targets} is not found from a fresh start either: the soak must ask for others"
            assert row["status"] == "done", row
            assert row["steps"] <= fresh + MARGIN_STEPS, (row, fresh)
    first, last = rows[0]["rss_mb"], rows[-1]["rss_mb"]
    assert set(first) == set(last) == {"mapping", "perception", "planner", "sim", "gateway"}
    for name in first:
        assert last[name] <= RSS_GROWTH * first[name], (name, first[name], last[name])
