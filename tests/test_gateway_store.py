"""The task store's file handling: one gateway per file, clear errors for unusable paths, files
written by an older gateway."""

from __future__ import annotations

import os
import sqlite3
from pathlib import Path

import pytest

from ovamos.services.gateway.store import StoreError, TaskStore
from ovamos.shared.messages import TaskStatus


def test_a_second_store_on_the_same_file_is_refused_until_the_first_closes(tmp_path: Path) -> None:
    path = tmp_path / "tasks.sqlite3"
    first = TaskStore(path)
    task = first.add("sim", ["chair"], 500)
    with pytest.raises(StoreError, match=rf"in use by another gateway \(pid {os.getpid()}\)"):
        TaskStore(path)
    first.close()
    second = TaskStore(path)  # the lock went with the first store
    try:
        assert second.get(task.id) is not None
    finally:
        second.close()


def test_an_unusable_path_is_a_store_error(tmp_path: Path) -> None:
    (tmp_path / "file").write_text("not a folder")
    with pytest.raises(StoreError, match="cannot open the task store"):
        TaskStore(tmp_path / "file" / "tasks.sqlite3")
    (tmp_path / "garbage.sqlite3").write_bytes(b"this is not a database" * 100)
    for _ in range(2):  # the second time too: a failed open leaves no lock behind
        with pytest.raises(StoreError, match="cannot open the task store"):
            TaskStore(tmp_path / "garbage.sqlite3")


def test_a_task_keeps_the_odometry_session_of_its_latest_report(tmp_path: Path) -> None:
    """Its path and found objects are in that session's frame: a restarted gateway must still say
    which, and a report without one (an older planner) does not erase it."""
    path = tmp_path / "tasks.sqlite3"
    store = TaskStore(path)
    task = store.add("sim", ["chair"], 500)
    assert store.get(task.id).odom_session is None
    store.progress(task.id, found=(), steps=1, distance_m=0.0, message="", position=(1.0, 2.0), odom_session="S1")
    store.progress(task.id, found=(), steps=2, distance_m=0.2, message="", position=(1.2, 2.0))
    store.close()
    store = TaskStore(path)
    try:
        record = store.get(task.id)
        assert record.odom_session == "S1" and record.steps == 2 and record.path == [(1.0, 2.0), (1.2, 2.0)]
    finally:
        store.close()


def test_a_file_from_before_odometry_sessions_gains_the_column_and_keeps_its_tasks(tmp_path: Path) -> None:
    path = tmp_path / "tasks.sqlite3"
    with sqlite3.connect(path) as db:  # the schema as the first gateways wrote it
        db.executescript("""
            CREATE TABLE tasks (seq INTEGER PRIMARY KEY AUTOINCREMENT, id TEXT NOT NULL UNIQUE,
                robot_id TEXT NOT NULL, status TEXT NOT NULL, targets TEXT NOT NULL, max_steps INTEGER NOT NULL,
                found TEXT NOT NULL DEFAULT '[]', steps INTEGER NOT NULL DEFAULT 0,
                distance_m REAL NOT NULL DEFAULT 0, message TEXT NOT NULL DEFAULT '',
                path TEXT NOT NULL DEFAULT '[]', created REAL NOT NULL, started REAL,
                updated REAL NOT NULL, finished REAL);
            INSERT INTO tasks (id, robot_id, status, targets, max_steps, steps, created, updated)
                VALUES ('old', 'sim', 'done', '["cup"]', 500, 42, 1.0, 2.0);""")
    db.close()
    store = TaskStore(path)
    try:
        old = store.get("old")
        assert old.steps == 42 and old.status is TaskStatus.DONE and old.odom_session is None
        new = store.add("sim", ["chair"], 500)
        store.progress(new.id, found=(), steps=1, distance_m=0.0, message="", position=None, odom_session="S2")
        assert store.get(new.id).odom_session == "S2"
    finally:
        store.close()
