"""The gateway's task life cycle over real HTTP (uvicorn) and real Zenoh, with a mock planner.

Queueing, planner events, cancellation, TaskSpec re-publication, ignored and
malformed events, and persistence across a gateway restart.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from ovamos.services.gateway.client import GatewayClient, GatewayError
from ovamos.shared import keys
from ovamos.shared.messages import FoundObject, TaskStatus
from tests.gateway_mocks import ODOM_SESSION, ROBOT, MockPlanner, RunningGateway, gateway_config
from tests.polling import wait_for

CHAIR = FoundObject(label="chair", x=1.5, y=-0.5, step=3)
FRIDGE = FoundObject(label="fridge", x=4.0, y=2.25, step=7)


def counter(api: GatewayClient, name: str) -> int:
    return api.health()["counters"][name]


def test_one_task_per_robot_the_rest_queue(api: GatewayClient, planner: MockPlanner) -> None:
    first = api.submit(["chair", "fridge"])
    second = api.submit(["cup"], max_steps=50)
    third = api.submit(["sofa"])
    assert (first.status, first.queue_position) == (TaskStatus.SEARCHING, None)
    assert (second.status, second.queue_position) == (TaskStatus.QUEUED, 1)
    assert (third.status, third.queue_position) == (TaskStatus.QUEUED, 2)
    spec = wait_for(lambda: planner.specs(first.id), what="the first TaskSpec")[0]
    assert spec.targets == ("chair", "fridge") and spec.max_steps == 500 and not spec.cancelled
    assert not planner.specs(second.id), "a queued task is not sent to the planner"

    # progress: repeated until the gateway shows it (a put right after declaring can be lost)
    wait_for(lambda: planner.report(first.id, TaskStatus.SEARCHING, ["chair", "fridge"], steps=3,
                                    found=(CHAIR,), x=1.0, y=-0.5) or api.get(first.id).steps == 3,
             what="progress applied")
    task = api.get(first.id)
    assert task.status is TaskStatus.SEARCHING and task.found == [CHAIR]
    assert task.remaining == ["fridge"] and task.distance_m == pytest.approx(0.75)
    assert (task.position.x, task.position.y) == (1.0, -0.5) and task.message == "mock step 3"

    wait_for(lambda: planner.report(first.id, TaskStatus.DONE, ["chair", "fridge"], steps=7,
                                    found=(CHAIR, FRIDGE), x=3.5, y=2.0)
             or api.get(first.id).status is TaskStatus.DONE, what="the task done")
    done = api.get(first.id)
    assert done.found == [CHAIR, FRIDGE] and done.remaining == [] and done.steps == 7
    assert done.finished_at is not None and done.finished_at >= done.started_at >= done.created_at

    # the queue moves on, in submission order
    assert api.get(second.id).status is TaskStatus.SEARCHING
    assert api.get(third.id).queue_position == 1
    spec = wait_for(lambda: planner.specs(second.id), what="the second TaskSpec")[0]
    assert spec.targets == ("cup",) and spec.max_steps == 50


def test_events_not_for_the_active_task_are_counted_and_ignored(api: GatewayClient,
                                                                planner: MockPlanner) -> None:
    active = api.submit(["chair"])
    queued = api.submit(["cup"])
    wait_for(lambda: planner.report(active.id, TaskStatus.FAILED, ["chair"], steps=5)
             or api.get(active.id).status is TaskStatus.FAILED, what="the first task failed")
    after_failure = counter(api, "events_finished_task")  # repeats of the final event count here

    wait_for(lambda: planner.report(active.id, TaskStatus.SEARCHING, ["chair"], steps=99)
             or counter(api, "events_finished_task") > after_failure, what="a late event counted")
    assert api.get(active.id).status is TaskStatus.FAILED and api.get(active.id).steps == 5

    wait_for(lambda: planner.report("ghost", TaskStatus.DONE, ["x"], steps=1)
             or counter(api, "events_unknown_task") >= 1, what="an unknown task's event counted")

    other = api.submit(["sofa"])  # queued behind `queued`, which is now active
    wait_for(lambda: planner.report(other.id, TaskStatus.DONE, ["sofa"], steps=1)
             or counter(api, "events_not_active") >= 1, what="a queued task's event counted")
    assert api.get(other.id).status is TaskStatus.QUEUED and api.get(other.id).steps == 0

    wait_for(lambda: planner.bus.session.put(keys.task_events(ROBOT), b'{"task_id": 5}')
             or counter(api, "events_malformed") >= 1, what="a malformed event counted")
    assert api.get(queued.id).status is TaskStatus.SEARCHING
    assert api.health()["robots"][ROBOT]["active_task"] == queued.id


def test_the_active_task_spec_is_republished_until_it_ends(api: GatewayClient,
                                                          planner: MockPlanner) -> None:
    first = api.submit(["chair"])
    specs = wait_for(lambda: len(s := planner.specs(first.id)) >= 4 and s, what="4 TaskSpecs")
    stamps = [s.stamp for s in specs]
    assert stamps == sorted(stamps) and len(set(stamps)) == len(stamps), "fresh stamps each time"
    assert all(s.targets == ("chair",) and not s.cancelled for s in specs)

    wait_for(lambda: planner.report(first.id, TaskStatus.DONE, ["chair"], steps=2)
             or api.get(first.id).status is TaskStatus.DONE, what="done")
    sent_by_the_end = len(planner.specs(first.id))
    second = api.submit(["cup"])
    wait_for(lambda: len(planner.specs(second.id)) >= 4, what="the next task's TaskSpecs")
    assert len(planner.specs(first.id)) <= sent_by_the_end + 1, "an ended task is not re-sent"


def test_cancel_publishes_a_cancelled_spec_and_starts_the_next(api: GatewayClient,
                                                               planner: MockPlanner) -> None:
    first = api.submit(["chair"])
    second = api.submit(["cup"])
    third = api.submit(["sofa"])
    wait_for(lambda: planner.specs(first.id), what="the first TaskSpec")

    cancelled = api.cancel(first.id)
    assert cancelled.status is TaskStatus.CANCELLED and cancelled.finished_at is not None
    wait_for(lambda: any(s.cancelled for s in planner.specs(first.id)), what="a cancelled TaskSpec")
    assert api.get(second.id).status is TaskStatus.SEARCHING
    wait_for(lambda: planner.specs(second.id), what="the next task's TaskSpec")

    # a queued task is cancelled without the planner ever hearing of it
    assert api.cancel(third.id).status is TaskStatus.CANCELLED
    assert api.get(second.id).status is TaskStatus.SEARCHING
    with pytest.raises(GatewayError, match="already cancelled") as info:
        api.cancel(first.id)
    assert info.value.status == 409
    wait_for(lambda: len(planner.specs(second.id)) >= 3, what="re-sent TaskSpecs of the active task")
    assert not planner.specs(third.id)


def test_tasks_survive_a_gateway_restart(inproc_router: str, tmp_path: Path,
                                         planner: MockPlanner) -> None:
    state = tmp_path / "state"
    first_run = RunningGateway(inproc_router, gateway_config(state))
    try:
        with GatewayClient(first_run.url) as api:
            active = api.submit(["chair", "fridge"])
            queued = api.submit(["cup"])
            wait_for(lambda: planner.report(active.id, TaskStatus.SEARCHING, ["chair", "fridge"],
                                            steps=3, found=(CHAIR,))
                     or api.get(active.id).steps == 3, what="progress before the restart")
    finally:
        first_run.close()
    assert (state / "tasks.sqlite3").exists()

    second_run = RunningGateway(inproc_router, gateway_config(state))  # another port, same file
    try:
        with GatewayClient(second_run.url) as api:
            task = api.get(active.id)
            assert task.status is TaskStatus.SEARCHING and task.found == [CHAIR] and task.steps == 3
            assert task.odom_session == ODOM_SESSION  # the frame its path and found chair are in
            assert api.get(queued.id).status is TaskStatus.QUEUED
            sent_before = len(planner.specs(active.id))
            wait_for(lambda: len(planner.specs(active.id)) >= sent_before + 2,
                     what="the restarted gateway re-sends the active TaskSpec")
            wait_for(lambda: planner.report(active.id, TaskStatus.DONE, ["chair", "fridge"], steps=6,
                                            found=(CHAIR, FRIDGE))
                     or api.get(active.id).status is TaskStatus.DONE, what="done after the restart")
            assert api.get(queued.id).status is TaskStatus.SEARCHING
            assert [t.id for t in api.tasks()] == [queued.id, active.id]
    finally:
        second_run.close()

