"""The task store's file handling: one gateway per file, and clear errors for unusable paths."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from services.gateway.store import StoreError, TaskStore


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
