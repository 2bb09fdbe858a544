"""Planner core: candidates, belief, best frontier, the task state machine."""

from __future__ import annotations

import numpy as np
import pytest

from ovamos.services.planner.candidates import CandidateConfig, best_frontier, find_candidates
from ovamos.services.planner.task import SearchTask, SearchTaskError
from ovamos.shared.grid import GridGeometry
from ovamos.shared.messages import FoundObject, TaskStatus

GRID = GridGeometry(0.05, 0.0, 0.0, 100, 100)  # 5 x 5 m


def blob(value_map: np.ndarray, x: float, y: float, peak: float, radius_cells: int = 3) -> None:
    r, c = GRID.to_cell(x, y)
    for dr in range(-radius_cells, radius_cells + 1):
        for dc in range(-radius_cells, radius_cells + 1):
            value_map[r + dr, c + dc] = max(value_map[r + dr, c + dc],
                                            peak * (1 - 0.1 * max(abs(dr), abs(dc))))


def test_dbscan_finds_one_candidate_per_blob_at_its_best_cell() -> None:
    vm = np.zeros(GRID.shape, np.float32)
    blob(vm, 1.0, 1.0, 0.8)
    blob(vm, 3.5, 4.0, 0.4)
    vm[GRID.to_cell(4.5, 0.5)] = 0.04  # below the 0.05 threshold
    cands = find_candidates(vm, GRID, CandidateConfig())
    assert len(cands.points) == 2
    assert cands.points[0] == pytest.approx(GRID.to_world(*GRID.to_cell(1.0, 1.0)))
    assert cands.points[1] == pytest.approx(GRID.to_world(*GRID.to_cell(3.5, 4.0)))
    assert cands.belief.sum() == pytest.approx(1.0)
    assert cands.belief == pytest.approx([0.8 / 1.2, 0.4 / 1.2])


def test_cells_further_apart_than_eps_are_separate_candidates() -> None:
    vm = np.zeros(GRID.shape, np.float32)
    vm[20, 20] = 0.5
    vm[21, 21] = 0.6  # diagonal neighbour, 0.07 m: same cluster (eps 0.1)
    vm[21, 25] = 0.7  # 0.2 m further: its own cluster
    cands = find_candidates(vm, GRID, CandidateConfig())
    assert sorted(cands.values.tolist()) == pytest.approx([0.6, 0.7])


def test_min_samples_above_one_cluster_with_sklearns_dbscan_like_the_grid_path() -> None:
    vm = np.zeros(GRID.shape, np.float32)
    blob(vm, 1.0, 1.0, 0.8)
    blob(vm, 3.5, 4.0, 0.4)
    grid_path = find_candidates(vm, GRID, CandidateConfig())
    sklearn_path = find_candidates(vm, GRID, CandidateConfig(dbscan_min_samples=2))
    assert sklearn_path.points == pytest.approx(grid_path.points)
    assert sklearn_path.belief == pytest.approx(grid_path.belief)


def test_no_value_no_candidates() -> None:
    cands = find_candidates(np.zeros(GRID.shape, np.float32), GRID, CandidateConfig())
    assert cands.points.shape == (0, 2) and cands.belief.size == 0


def test_best_frontier_is_the_one_with_most_value_nearby() -> None:
    vm = np.zeros(GRID.shape, np.float32)
    blob(vm, 4.0, 4.0, 0.9, 1)
    frontiers = np.array([[1.0, 1.0], [4.3, 4.3], [4.0, 2.0]])
    assert best_frontier(frontiers, vm, GRID, 0.5) == 1
    assert best_frontier(frontiers, vm, GRID, 0.2) in (0, 1, 2)
    assert best_frontier(np.zeros((0, 2)), vm, GRID, 0.5) is None


def test_task_life_cycle() -> None:
    task = SearchTask("t1", ["cup", "bed"], max_steps=3)
    assert task.state is TaskStatus.QUEUED
    with pytest.raises(SearchTaskError):
        task.record_step(0.25)
    task.start()
    task.record_step(0.25)
    task.mark_found("cup", 1.0, 2.0)
    assert task.remaining == ["bed"] and task.state is TaskStatus.SEARCHING
    task.add_targets(["sofa", "bed"])
    assert task.targets == ["cup", "bed", "sofa"]
    task.remove_targets(["sofa"])
    task.record_step(0.25, ("bed", 0.5, 0.0))  # the STOP that declared it
    assert task.state is TaskStatus.DONE and task.found["cup"].step == 1
    assert task.found["bed"] == FoundObject(label="bed", x=0.5, y=0.0, step=2)  # as reported
    with pytest.raises(SearchTaskError):
        task.cancel()


def test_task_fails_at_the_step_limit_and_can_be_cancelled() -> None:
    task = SearchTask("t2", ["cup"], max_steps=2)
    task.start()
    task.record_step(0.25)
    task.record_step(0.25)
    assert task.state is TaskStatus.FAILED and task.distance == pytest.approx(0.5)
    other = SearchTask("t3", ["cup"])
    other.start()
    other.cancel()
    assert other.state is TaskStatus.CANCELLED
    with pytest.raises(SearchTaskError):
        SearchTask("t4", [])
    with pytest.raises(SearchTaskError, match="not a remaining target"):
        t = SearchTask("t5", ["cup"])
        t.start()
        t.mark_found("bed", 0, 0)
