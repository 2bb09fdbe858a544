"""Tasks in a SQLite file, so that an accepted task survives a gateway restart.

One row per task. The queue of a robot is its ``queued`` rows in submission
order (``seq``); at most one task per robot is ``searching`` at a time, which
a partial unique index enforces, so a logic error cannot start two searches
on one robot. Every write is committed before the call returns: once
``POST /v1/tasks`` has answered 202 the task is on disk.

Threads: every write goes through one connection, used by the one thread that
owns the task state (the TaskManager's, see :mod:`ovamos.services.gateway.tasks`); a
lock guards it only against :meth:`TaskStore.close`. Reads, from any thread,
take a query-only connection from a small pool, and the file is in WAL mode,
so a read sees the last committed state and never waits for a write or a slow
commit: an HTTP handler reading a task is never held up by the planner's
progress being committed. No lock of the store is ever held across a commit
by a reader, and none is taken on the asyncio event loop.

One gateway per file: the store holds an exclusive lock on ``<file>.lock``
while open. Two gateways on one file would each start the queued task and
publish two TaskSpecs for one robot; the second is refused at start instead.
"""

from __future__ import annotations

import fcntl
import json
import os
import sqlite3
import threading
import time
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ovamos.shared.messages import FoundObject, TargetMiss, TaskStatus

MAX_PATH_POINTS = 20_000  # a 500-step search reports ~500; this only bounds a runaway planner

_SCHEMA = """
CREATE TABLE IF NOT EXISTS tasks (
    seq INTEGER PRIMARY KEY AUTOINCREMENT,
    id TEXT NOT NULL UNIQUE,
    robot_id TEXT NOT NULL,
    status TEXT NOT NULL,
    targets TEXT NOT NULL,
    max_steps INTEGER NOT NULL,
    found TEXT NOT NULL DEFAULT '[]',
    steps INTEGER NOT NULL DEFAULT 0,
    distance_m REAL NOT NULL DEFAULT 0,
    message TEXT NOT NULL DEFAULT '',
    path TEXT NOT NULL DEFAULT '[]',
    odom_session TEXT,
    misses TEXT NOT NULL DEFAULT '[]',
    last_action INTEGER NOT NULL DEFAULT 0,
    created REAL NOT NULL,
    started REAL,
    updated REAL NOT NULL,
    finished REAL
);
CREATE UNIQUE INDEX IF NOT EXISTS one_search_per_robot ON tasks(robot_id) WHERE status = 'searching';
CREATE INDEX IF NOT EXISTS by_robot_status ON tasks(robot_id, status, seq);
"""
#: columns added since the first schema, with their type: added to a file made before them
_ADDED_COLUMNS = {"odom_session": "TEXT", "misses": "TEXT NOT NULL DEFAULT '[]'",
                  "last_action": "INTEGER NOT NULL DEFAULT 0"}


class StoreError(RuntimeError):
    """The task file cannot be opened or is not a task store."""


@dataclass
class TaskRecord:
    """One stored task (times are epoch seconds)."""

    id: str
    robot_id: str
    status: TaskStatus
    targets: list[str]
    max_steps: int
    seq: int = 0
    found: list[FoundObject] = field(default_factory=list)
    steps: int = 0
    distance_m: float = 0.0
    message: str = ""
    path: list[tuple[float, float]] = field(default_factory=list)
    odom_session: str | None = None  # of the planner's latest report: the frame of path and found
    misses: list[TargetMiss] = field(default_factory=list)  # once failed: the targets not found, why
    last_action: int = 0  # the newest command the planner booked as a step: a restarted one goes on after it
    created: float = 0.0
    started: float | None = None
    updated: float = 0.0
    finished: float | None = None

    @property
    def position(self) -> tuple[float, float] | None:
        return self.path[-1] if self.path else None


def _record(row: sqlite3.Row) -> TaskRecord:
    return TaskRecord(
        id=row["id"], robot_id=row["robot_id"], status=TaskStatus(row["status"]),
        targets=json.loads(row["targets"]), max_steps=row["max_steps"], seq=row["seq"],
        found=[FoundObject.model_validate(f) for f in json.loads(row["found"])],
        steps=row["steps"], distance_m=row["distance_m"], message=row["message"],
        path=[tuple(p) for p in json.loads(row["path"])], odom_session=row["odom_session"],
        misses=[TargetMiss.model_validate(m) for m in json.loads(row["misses"])],
        last_action=row["last_action"], created=row["created"],
        started=row["started"], updated=row["updated"], finished=row["finished"])


def _take_lock(lock_path: Path) -> int:
    """An open descriptor holding an exclusive lock on ``lock_path`` (released when closed, also
    by the OS when the process dies: a killed gateway never leaves a stale lock)."""
    fd = os.open(lock_path, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        holder = os.pread(fd, 32, 0).decode(errors="replace").strip() or "unknown"
        os.close(fd)
        raise StoreError(f"the task store {lock_path.with_suffix('')} is in use by another gateway "
                         f"(pid {holder}); give each gateway its own state_dir") from None
    except OSError:
        os.close(fd)
        raise
    os.ftruncate(fd, 0)
    os.pwrite(fd, str(os.getpid()).encode(), 0)
    return fd


class TaskStore:
    """Create, read and update tasks in ``path`` (created with its folder when missing)."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._write_lock = threading.Lock()  # the writer connection against close(); no reader takes it
        self._pool_lock = threading.Lock()  # the idle readers (held for no query)
        self._idle: list[sqlite3.Connection] = []
        self._closed = False
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            self._owner = _take_lock(path.with_name(path.name + ".lock"))
        except OSError as exc:
            raise StoreError(f"cannot open the task store {path}: {exc}") from None
        try:
            self._db = self._connect()
            self._db.execute("PRAGMA journal_mode=WAL")
            self._db.executescript(_SCHEMA)
            have = {row["name"] for row in self._db.execute("PRAGMA table_info(tasks)")}
            for name, kind in _ADDED_COLUMNS.items():
                if name not in have:  # a file written by an older gateway: its tasks keep NULL
                    self._db.execute(f"ALTER TABLE tasks ADD COLUMN {name} {kind}")
        except (OSError, sqlite3.Error) as exc:
            os.close(self._owner)
            raise StoreError(f"cannot open the task store {path}: {exc}") from None

    def _connect(self) -> sqlite3.Connection:
        db = sqlite3.connect(self.path, check_same_thread=False)  # pooled: used by many threads in turn
        db.row_factory = sqlite3.Row
        return db

    def close(self) -> None:
        with self._write_lock, self._pool_lock:
            if self._closed:
                return
            self._closed = True
            for reader in self._idle:
                reader.close()
            self._idle.clear()
            self._db.close()
            os.close(self._owner)  # releases the lock

    @contextmanager
    def _reader(self) -> Iterator[sqlite3.Connection]:
        """A read connection of the pool (query-only), for one read. In WAL mode a reader sees
        the last commit and never waits for the writer; the pool grows to the number of
        threads reading at once."""
        with self._pool_lock:
            if self._closed:
                raise StoreError(f"the task store {self.path} is closed")
            db = self._idle.pop() if self._idle else None
        if db is None:
            db = self._connect()
            db.execute("PRAGMA query_only = ON")
        try:
            yield db
        finally:
            with self._pool_lock:
                if self._closed:
                    db.close()
                else:
                    self._idle.append(db)

    def _write(self, sql: str, args: tuple[Any, ...]) -> None:
        with self._write_lock, self._db:
            self._db.execute(sql, args)

    def _read(self, sql: str, args: tuple[Any, ...] = ()) -> list[TaskRecord]:
        with self._reader() as db:
            return [_record(r) for r in db.execute(sql, args).fetchall()]

    def _scalar(self, sql: str, args: tuple[Any, ...]) -> Any:
        with self._reader() as db:
            return db.execute(sql, args).fetchone()[0]

    # -- creating and reading ------------------------------------------------------------------
    def add(self, robot_id: str, targets: list[str], max_steps: int) -> TaskRecord:
        now = time.time()
        task_id = uuid.uuid4().hex
        self._write("INSERT INTO tasks (id, robot_id, status, targets, max_steps, created, updated) "
                    "VALUES (?, ?, ?, ?, ?, ?, ?)",
                    (task_id, robot_id, TaskStatus.QUEUED.value, json.dumps(targets), max_steps,
                     now, now))
        record = self.get(task_id)
        assert record is not None
        return record

    def get(self, task_id: str) -> TaskRecord | None:
        rows = self._read("SELECT * FROM tasks WHERE id = ?", (task_id,))
        return rows[0] if rows else None

    def list(self, robot_id: str | None = None, status: TaskStatus | None = None,
             limit: int = 100) -> list[TaskRecord]:
        """Newest first."""
        where, args = [], []
        if robot_id is not None:
            where.append("robot_id = ?")
            args.append(robot_id)
        if status is not None:
            where.append("status = ?")
            args.append(status.value)
        clause = f"WHERE {' AND '.join(where)}" if where else ""
        return self._read(f"SELECT * FROM tasks {clause} ORDER BY seq DESC LIMIT ?", (*args, limit))

    def active(self, robot_id: str) -> TaskRecord | None:
        rows = self._read("SELECT * FROM tasks WHERE robot_id = ? AND status = ?",
                          (robot_id, TaskStatus.SEARCHING.value))
        return rows[0] if rows else None

    def next_queued(self, robot_id: str) -> TaskRecord | None:
        rows = self._read("SELECT * FROM tasks WHERE robot_id = ? AND status = ? ORDER BY seq LIMIT 1",
                          (robot_id, TaskStatus.QUEUED.value))
        return rows[0] if rows else None

    def queue_position(self, record: TaskRecord) -> int | None:
        """1 for the next task to start, None when ``record`` is not queued."""
        if record.status is not TaskStatus.QUEUED:
            return None
        ahead = self._scalar("SELECT COUNT(*) FROM tasks WHERE robot_id = ? AND status = ? AND seq < ?",
                             (record.robot_id, TaskStatus.QUEUED.value, record.seq))
        return ahead + 1

    def count(self, robot_id: str, status: TaskStatus) -> int:
        return self._scalar("SELECT COUNT(*) FROM tasks WHERE robot_id = ? AND status = ?",
                            (robot_id, status.value))

    # -- state changes -------------------------------------------------------------------------
    def start(self, task_id: str) -> None:
        now = time.time()
        self._write("UPDATE tasks SET status = ?, started = ?, updated = ? WHERE id = ?",
                    (TaskStatus.SEARCHING.value, now, now, task_id))

    def finish(self, task_id: str, status: TaskStatus, message: str | None = None) -> None:
        now = time.time()
        self._write("UPDATE tasks SET status = ?, message = COALESCE(?, message), finished = ?, "
                    "updated = ? WHERE id = ?", (status.value, message, now, now, task_id))

    def progress(self, task_id: str, *, found: tuple[FoundObject, ...], steps: int, distance_m: float,
                 message: str, position: tuple[float, float] | None, odom_session: str | None = None,
                 misses: tuple[TargetMiss, ...] = (), last_action: int = 0) -> None:
        """Record the planner's latest report; ``position`` extends the task's path, whose points
        (and the found objects') are in the frame of ``odom_session``."""
        with self._write_lock, self._db:
            row = self._db.execute("SELECT path FROM tasks WHERE id = ?", (task_id,)).fetchone()
            if row is None:
                return
            path = json.loads(row["path"])
            if position is not None and (not path or path[-1] != list(position)):
                path = (path + [list(position)])[-MAX_PATH_POINTS:]
            self._db.execute(
                "UPDATE tasks SET found = ?, steps = ?, distance_m = ?, message = ?, path = ?, "
                "odom_session = COALESCE(?, odom_session), misses = ?, last_action = ?, updated = ? "
                "WHERE id = ?",
                (json.dumps([f.model_dump() for f in found]), steps, distance_m, message,
                 json.dumps(path), odom_session, json.dumps([m.model_dump(mode="json") for m in misses]),
                 last_action, time.time(), task_id))
