"""Who runs what in the gateway: the task state has one owner thread, and a slow commit there
never holds up HTTP requests that do not need it, nor the event loop and its streams.

The first tests wire a TaskManager to a fake bus (no Zenoh), so the test decides when the
owner thread (here: the test's own thread, pumping the fake network) runs; the last runs the
real gateway with a store whose progress commit takes a second.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest

from ovamos.services.gateway import service as gateway_service
from ovamos.services.gateway.client import GatewayClient
from ovamos.services.gateway.config import GatewayConfig
from ovamos.services.gateway.store import TaskRecord, TaskStore
from ovamos.services.gateway.tasks import GatewayBusy
from ovamos.shared import keys
from ovamos.shared.fake_bus import FakeNetwork
from ovamos.shared.messages import TaskEvent, TaskSpec, TaskStatus
from tests.gateway_mocks import ROBOT, MockPlanner, RunningGateway, gateway_config
from tests.polling import wait_for

OTHER = "r2"


class Wired:
    """A TaskManager on a fake bus, and a fake planner's end of ``task/current`` / ``task/events``."""

    def __init__(self, tmp_path: Path) -> None:
        self.net = FakeNetwork()
        self.bus = self.net.bus(ROBOT, "gateway")
        self.store = TaskStore(tmp_path / "tasks.sqlite3")
        self.notified: list[tuple[int, TaskRecord]] = []  # (thread, record)
        config = GatewayConfig(state_dir=tmp_path, robots=[ROBOT, OTHER], cancel_linger_s=5.0)
        self.manager, _ = gateway_service.wire(self.bus, config, self.store,
                                               lambda record: self.notified.append((threading.get_ident(), record)))
        planner = self.net.bus(ROBOT, "planner")
        self.specs: list[TaskSpec] = []
        planner.subscribe(keys.task_current(ROBOT), TaskSpec, self.specs.append)
        self.events = planner.publisher(keys.task_events(ROBOT), TaskEvent)
        self.net.pump()  # the resume: nothing to start

    def in_thread(self, fn: Any, *args: Any) -> tuple[threading.Thread, dict[str, Any]]:
        """``fn(*args)`` on another thread (an HTTP worker's), its result or error in the dict."""
        out: dict[str, Any] = {}

        def run() -> None:
            try:
                out["result"] = fn(*args)
            except Exception as exc:
                out["error"] = exc

        thread = threading.Thread(target=run, daemon=True)
        thread.start()
        return thread, out

    def report(self, task_id: str, status: TaskStatus, steps: int) -> None:
        self.events.put(TaskEvent(task_id=task_id, status=status, targets=("chair",), steps=steps,
                                  distance_m=0.25 * steps, stamp=time.time(), x=0.5, y=0.5))


@pytest.fixture
def wired(tmp_path: Path) -> Iterator[Wired]:
    w = Wired(tmp_path)
    yield w
    w.manager.close()
    w.store.close()


def test_requests_and_planner_events_run_on_the_owner_thread(wired: Wired) -> None:
    owner = threading.get_ident()  # this thread pumps the fake network: it is the inbox's taker
    worker, out = wired.in_thread(wired.manager.submit, ROBOT, ["chair"], 50)
    wait_for(lambda: wired.bus.inbox.pending() == 1, what="the submit handed to the owner")
    assert wired.store.list() == [] and worker.is_alive(), "the HTTP thread changes nothing itself"
    wired.net.pump()
    worker.join(5)
    task = out["result"]
    assert task.status is TaskStatus.SEARCHING and [s.task_id for s in wired.specs] == [task.id]

    wired.report(task.id, TaskStatus.SEARCHING, steps=3)  # Zenoh's thread would only enqueue this
    assert wired.store.get(task.id).steps == 0
    wired.net.pump()
    assert wired.store.get(task.id).steps == 3
    assert wired.manager.counters()["events_applied"] == 1

    worker, out = wired.in_thread(wired.manager.cancel, task.id)
    wait_for(lambda: wired.bus.inbox.pending() == 1, what="the cancel handed to the owner")
    wired.net.pump()
    worker.join(5)
    assert out["result"].status is TaskStatus.CANCELLED and wired.specs[-1].cancelled
    assert {thread for thread, _ in wired.notified} == {owner}, "every change notified by the owner"


def test_a_request_the_owner_never_took_fails_and_changes_nothing(wired: Wired) -> None:
    worker, out = wired.in_thread(wired.manager.submit, ROBOT, ["chair"], 50)
    wait_for(lambda: wired.bus.inbox.pending() == 1, what="the submit handed to the owner")
    wired.manager.close()  # the gateway stops before its owner got to the request
    worker.join(5)
    assert isinstance(out.get("error"), GatewayBusy)
    wired.net.pump()
    assert wired.store.list() == [], "a request answered 503 is never applied later"
    with pytest.raises(GatewayBusy):
        wired.manager.submit(ROBOT, ["cup"], 50)


def test_republish_rounds_collapse_and_the_cancel_linger_ignores_the_wall_clock(
        wired: Wired, monkeypatch: pytest.MonkeyPatch) -> None:
    worker, out = wired.in_thread(wired.manager.submit, ROBOT, ["chair"], 50)
    wait_for(lambda: wired.bus.inbox.pending() == 1, what="the submit handed to the owner")
    wired.net.pump()
    worker.join(5)
    task = out["result"]
    worker, _ = wired.in_thread(wired.manager.cancel, task.id)
    wait_for(lambda: wired.bus.inbox.pending() == 1, what="the cancel handed to the owner")
    wired.net.pump()
    worker.join(5)
    sent = len(wired.specs)

    for _ in range(5):  # the timer fired five times while the owner was busy
        wired.manager.request_republish()
    assert wired.bus.inbox.pending() == 1
    real_time = time.time
    monkeypatch.setattr(time, "time", lambda: real_time() + 3600.0)  # the wall clock jumps an hour
    wired.net.pump()
    assert len(wired.specs) == sent + 1 and wired.specs[-1].cancelled, \
        "the cancelled spec is still re-sent: its linger runs on the monotonic clock"


class SlowCommits(TaskStore):
    """A task store whose first commit of planner progress, once ``armed``, takes a second."""

    SLOW_S = 1.0

    def __init__(self, path: Path) -> None:
        super().__init__(path)
        self.armed = threading.Event()
        self.in_slow_commit = threading.Event()
        self.slow_commit_over = threading.Event()
        self._progress_pending = False
        self._db.set_trace_callback(self._trace)  # the connection that writes

    def _trace(self, sql: str) -> None:
        if sql.startswith("UPDATE tasks SET found"):  # TaskStore.progress
            self._progress_pending = True
        elif sql.strip() == "COMMIT" and self._progress_pending:
            self._progress_pending = False
            if self.armed.is_set() and not self.in_slow_commit.is_set():
                self.in_slow_commit.set()
                time.sleep(self.SLOW_S)
                self.slow_commit_over.set()


def test_a_slow_commit_holds_up_no_request_that_does_not_need_it(
        inproc_router: str, tmp_path: Path, planner: MockPlanner,
        monkeypatch: pytest.MonkeyPatch) -> None:
    stores: list[SlowCommits] = []

    def make_store(path: Path) -> SlowCommits:
        stores.append(SlowCommits(path))
        return stores[-1]

    monkeypatch.setattr(gateway_service, "TaskStore", make_store)
    running = RunningGateway(inproc_router, gateway_config(tmp_path, robots=[ROBOT, OTHER],
                                                           sse_heartbeat_s=0.1))
    try:
        (store,) = stores
        with GatewayClient(running.url) as api:
            busy = api.submit(["chair"])  # its progress will take a second to commit
            other = api.submit(["cup"], robot_id=OTHER)
            # a stream of the other robot's task: what each line saw of the slow commit
            lines: list[tuple[str, bool, bool]] = []
            done = threading.Event()

            def follow() -> None:
                with httpx.stream("GET", f"{running.url}/v1/tasks/{other.id}/events", timeout=10) as r:
                    for line in r.iter_lines():
                        lines.append((line, store.in_slow_commit.is_set(), store.slow_commit_over.is_set()))
                        if done.is_set():
                            return

            streamer = threading.Thread(target=follow, daemon=True)
            streamer.start()
            wait_for(lambda: any(line == ": keep-alive" for line, _, _ in lines), what="the stream")

            store.armed.set()
            wait_for(lambda: planner.report(busy.id, TaskStatus.SEARCHING, ["chair"], steps=3)
                     or store.in_slow_commit.wait(0.1), what="the slow commit to begin")

            # a read of another task: answered from the last commit, without waiting for this one
            view = api.get(other.id)
            assert not store.slow_commit_over.is_set(), "the read waited for the slow commit"
            assert view.status is TaskStatus.SEARCHING and view.robot_id == OTHER
            # a refused request: answered (and counted) on the event loop
            refused = httpx.post(f"{running.url}/v1/tasks", json={"targets": []}, timeout=10)
            assert not store.slow_commit_over.is_set(), "the event loop waited for the slow commit"
            assert refused.status_code == 422
            # the event loop keeps the stream alive meanwhile
            wait_for(lambda: store.slow_commit_over.is_set()
                     or any(line == ": keep-alive" and during and not over for line, during, over in lines),
                     what="a keep-alive or the end of the slow commit")
            assert any(line == ": keep-alive" and during and not over for line, during, over in lines), \
                "no keep-alive reached the stream during the slow commit"

            # the slow commit went through, and the owner carries on
            wait_for(lambda: api.get(busy.id).steps == 3, what="the slowly committed progress")
            assert api.get(busy.id).status is TaskStatus.SEARCHING
            done.set()
    finally:
        running.close()
