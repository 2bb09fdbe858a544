"""The planner's protocol message by message: lock-step, re-sends, faults, cancel, found objects,
clock skew between hosts, a restart during a command."""

from __future__ import annotations

import numpy as np
import pytest

from ovamos.services.planner.agent import AgentConfig
from ovamos.services.planner.executive import OLD_MAP, Executive, ExecutiveConfig
from ovamos.shared.messages import (
    DecisionTrace,
    DriverMode,
    DriverState,
    MapSnapshot,
    ObjectInstance,
    Odometry,
    PlanCommand,
    TaskEvent,
    TaskSpec,
    TaskStatus,
)
from ovamos.shared.motion import Action

N = 120  # 6 x 6 m at 5 cm


def snapshot(seq: int, objects: tuple[ObjectInstance, ...] = (), after: int | None = None,
             stamp: float | None = None, session: str = "", layers: tuple[str, ...] = ("cup", "bed")
             ) -> MapSnapshot:
    """A map whose newest fused frame is ``seq``, taken after command ``after`` (default: seq), with
    value layers of ``layers`` (perception's reading of the tests' targets)."""
    return MapSnapshot(seq=seq, after_action=seq if after is None else after, odom_session=session,
                       stamp=float(seq) if stamp is None else stamp, resolution=0.05, origin=(0.0, 0.0), layers=layers,
                       objects=objects, obstacle=np.zeros((N, N), bool), explored=np.ones((N, N), bool),
                       counts=np.zeros((len(layers), N, N), np.uint16), values=np.zeros((len(layers), N, N), np.float32),
                       frontiers=np.array([[5.0, 5.0]]))


def driver(completed: int = 0, mode: DriverMode = DriverMode.READY, active: int | None = None,
           outcome: str | None = None, stamp: float = 0.0, session: str = "") -> DriverState:
    return DriverState(stamp=stamp, mode=mode, last_completed=completed, odom_session=session,
                       active_action=active, last_outcome=outcome,
                       faults=("axis 0: heartbeat lost",) if mode is DriverMode.FAULT else ())


def odom(x: float = 1.0, y: float = 1.0, yaw: float = 0.0, stamp: float = 0.0, after: int = 0,
         session: str = "") -> Odometry:
    return Odometry(seq=0, stamp=stamp, x=x, y=y, yaw=yaw, after_action=after, odom_session=session)


def spec(targets: tuple[str, ...] = ("cup",), cancelled: bool = False) -> TaskSpec:
    return TaskSpec(task_id="t1", targets=targets, stamp=0.0, cancelled=cancelled)


def commands(out: list) -> list[PlanCommand]:
    return [m for m in out if isinstance(m, PlanCommand)]


def events(out: list) -> list[TaskEvent]:
    return [m for m in out if isinstance(m, TaskEvent)]


@pytest.fixture
def ex() -> Executive:
    e = Executive(ExecutiveConfig(agent=AgentConfig(initial_turns=2), resend_s=0.3))
    e.on_task(spec())
    return e


def test_nothing_is_sent_before_driver_map_and_odometry(ex: Executive) -> None:
    assert commands(ex.poll(0.0)) == [] and "driver" in ex.waiting
    ex.on_driver(driver())
    assert commands(ex.poll(0.1)) == [] and "map" in ex.waiting
    ex.on_snapshot(snapshot(0))
    assert commands(ex.poll(0.2)) == [] and "odometry" in ex.waiting
    ex.on_odom(odom())
    assert [c.action for c in commands(ex.poll(0.3))] == [Action.TURN_LEFT]


def test_lock_step_resends_until_acknowledged_and_waits_for_the_next_frame(ex: Executive) -> None:
    ex.on_driver(driver())
    ex.on_snapshot(snapshot(0))
    ex.on_odom(odom())
    first = commands(ex.poll(0.0))
    assert [c.action_id for c in first] == [1]
    assert commands(ex.poll(0.1)) == []                       # not yet due for a re-send
    assert [c.action_id for c in commands(ex.poll(0.4))] == [1]  # lost? sent again, same id
    ex.on_driver(driver(active=1))
    assert commands(ex.poll(0.5)) == []                       # being executed, not due yet
    # while the driver executes it, the copies are its keep-alive (the link is up)
    assert [c.action_id for c in commands(ex.poll(1.0))] == [1]
    ex.on_driver(driver(completed=1))
    ex.on_odom(odom(after=1))
    assert commands(ex.poll(1.1)) == []
    assert ex.map_wanted() == 1 and "after command 1" in ex.waiting  # no frame after it fused yet
    ex.on_snapshot(snapshot(1))
    assert ex.map_wanted() is None
    second = commands(ex.poll(1.2))
    assert [c.action_id for c in second] == [2] and ex.task.steps == 1


def test_no_command_in_fault_or_estop_and_the_event_says_why(ex: Executive) -> None:
    ex.on_snapshot(snapshot(0))
    ex.on_odom(odom())
    ex.on_driver(driver(mode=DriverMode.FAULT))
    out = ex.poll(0.0)
    assert commands(out) == [] and "heartbeat lost" in events(out)[-1].message
    ex.on_driver(driver(mode=DriverMode.ESTOP))
    out = ex.poll(0.1)
    assert commands(out) == [] and "e-stop" in events(out)[-1].message
    ex.on_driver(driver())
    assert len(commands(ex.poll(0.2))) == 1


def test_action_ids_continue_after_the_drivers_last_completed(ex: Executive) -> None:
    ex.on_driver(driver(completed=41))
    ex.on_snapshot(snapshot(7, after=41))
    ex.on_odom(odom(after=41))
    assert [c.action_id for c in commands(ex.poll(0.0))] == [42]


def test_cancel_stops_commands_and_reports_cancelled(ex: Executive) -> None:
    ex.on_driver(driver())
    ex.on_snapshot(snapshot(0))
    ex.on_odom(odom())
    ex.poll(0.0)
    ex.on_task(spec(cancelled=True))
    out = ex.poll(0.1)
    assert commands(out) == [] and events(out)[-1].status is TaskStatus.CANCELLED
    ex.on_task(spec())  # the same task re-published later does not restart it
    assert ex.task.state.value == "cancelled"


def test_no_decision_before_the_map_holds_perception_of_every_remaining_target(ex: Executive) -> None:
    """A new task on a map of before it (no value layer of its targets: perception has not read
    the view for them yet) waits; the map with the layer is decided on. Targets added later wait
    for their layer too."""
    ex.on_driver(driver())
    ex.on_odom(odom())
    ex.on_snapshot(snapshot(0, layers=()))
    assert commands(ex.poll(0.0)) == [] and ex.waiting == "waiting for perception: the map has no values of cup yet"
    ex.on_snapshot(snapshot(0, layers=("cup",)))
    assert len(commands(ex.poll(0.1))) == 1 and ex.waiting == ""
    ex.on_driver(driver(completed=1))
    ex.on_odom(odom(after=1))
    ex.on_task(spec(("cup", "mug")))
    ex.on_snapshot(snapshot(1, layers=("cup",)))
    assert commands(ex.poll(0.2)) == [] and "of mug yet" in ex.waiting
    ex.on_snapshot(snapshot(1, layers=("cup", "mug")))
    assert len(commands(ex.poll(0.3))) == 1


def test_a_confirmed_object_nearby_is_stopped_at_and_reported_found() -> None:
    ex = Executive(ExecutiveConfig(agent=AgentConfig(initial_turns=0)))
    ex.on_task(spec(("cup", "bed")))
    cup = ObjectInstance(label="cup", x=1.5, y=1.0, score=0.8, hits=3, confirmed=True)
    ex.on_driver(driver())
    ex.on_snapshot(snapshot(0, (cup,)))
    ex.on_odom(odom())
    sent = commands(ex.poll(0.0))
    assert [c.action for c in sent] == [Action.STOP]
    ex.on_driver(driver(completed=1))
    ex.on_odom(odom(after=1))
    ex.on_snapshot(snapshot(1, (cup,)))
    out = ex.poll(0.1)
    found = events(out)[-1].found
    assert [(f.label, f.x, f.y) for f in found] == [("cup", 1.5, 1.0)]
    assert ex.task.remaining == ["bed"]
    assert all(c.action is not Action.STOP for c in commands(out))  # the cup is not stopped at twice


def test_a_blocked_move_is_reported_to_the_agent_as_a_bump(ex: Executive) -> None:
    ex.agent._scan_left = 0
    ex.on_driver(driver())
    ex.on_snapshot(snapshot(0))
    ex.on_odom(odom(yaw=0.78))  # facing the frontier at (5, 5): the agent drives forward
    sent = commands(ex.poll(0.0))
    assert [c.action for c in sent] == [Action.MOVE_FORWARD]
    ex.on_driver(driver(completed=1, outcome="blocked"))
    ex.on_odom(odom(yaw=0.78, after=1))
    ex.poll(0.1)
    assert len(ex.agent.bumps.points(ex.task.steps)) == 1 and ex.task.distance == 0.0


def test_a_completion_waits_for_the_odometry_taken_after_it(ex: Executive) -> None:
    ex.agent._scan_left = 0
    ex.on_driver(driver())
    ex.on_snapshot(snapshot(0))
    ex.on_odom(odom(yaw=0.78))
    assert [c.action for c in commands(ex.poll(0.0))] == [Action.MOVE_FORWARD]
    ex.on_driver(driver(completed=1))
    ex.on_snapshot(snapshot(1))
    ex.on_odom(odom(yaw=0.78, stamp=99.0))  # a newer stamp, but measured before the completion
    assert commands(ex.poll(0.1)) == [] and "odometry" in ex.waiting and ex.task.steps == 0
    ex.on_odom(odom(x=1.0 + 0.25 * 0.7109, y=1.0 + 0.25 * 0.7031, yaw=0.78, stamp=-99.0, after=1))
    assert len(commands(ex.poll(0.2))) == 1
    assert ex.task.steps == 1 and ex.task.distance == pytest.approx(0.25, abs=1e-3)


def test_no_plan_while_the_drivers_primitives_differ_from_the_planners(ex: Executive) -> None:
    from ovamos.shared.robot import PRIMITIVES, Primitives

    ex.on_snapshot(snapshot(0))
    ex.on_odom(odom())
    longer = Primitives(forward_m=0.30, turn_deg=30.0)
    ex.on_driver(DriverState.from_bytes(driver().model_copy(update={"primitives": longer}).to_bytes()))
    out = ex.poll(0.0)
    assert commands(out) == []
    assert events(out)[-1].message == ("driver's primitives (move 0.30 m, turn 30 deg) differ from "
                                       "the planner's (move 0.25 m, turn 30 deg): fix the configs")
    ex.on_driver(driver().model_copy(update={"primitives": PRIMITIVES}))  # the same sizes: go
    assert len(commands(ex.poll(0.1))) == 1


@pytest.mark.parametrize("skew_s", [5.0, -5.0])
def test_lock_step_is_causal_whatever_the_clocks_of_the_other_hosts(skew_s: float) -> None:
    """The driver's clock runs 5 s ahead of (or behind) the mapping host's: the planner still
    runs a task to its end, and never decides on a map that has not seen the world after its
    last command, however the stamps of the maps and states compare."""
    ex = Executive(ExecutiveConfig(agent=AgentConfig(initial_turns=0)))
    ex.on_task(TaskSpec(task_id="t1", targets=("cup",), max_steps=12, stamp=0.0))
    now = 100.0
    ex.on_driver(driver(stamp=now + skew_s))
    ex.on_snapshot(snapshot(0, stamp=now))
    ex.on_odom(odom(stamp=now + skew_s))
    sent = commands(ex.poll(0.0))
    decisions = 0
    while sent:
        (command,) = sent
        decisions += 1
        k = command.action_id
        now += 1.0
        # the completion and the pose after it arrive, then a map that has not fused a frame after
        # the command yet, stamped later than the completion on any clock
        ex.on_driver(driver(completed=k, stamp=now + skew_s))
        ex.on_odom(odom(stamp=now + skew_s, after=k))
        ex.on_snapshot(snapshot(k - 1, after=k - 1, stamp=now + 10.0))
        stale = commands(ex.poll(float(k)))
        assert stale == [], f"decided after command {k} on a map that had not seen its result"
        assert ex.map_wanted() == k
        ex.on_snapshot(snapshot(k, after=k, stamp=now - 10.0))  # fresh, stamped earlier: still fresh
        sent = commands(ex.poll(k + 0.5))
    assert ex.task.state in (TaskStatus.DONE, TaskStatus.FAILED) and ex.task.steps == 12
    assert decisions == 12


def test_a_restarted_planner_waits_for_the_drivers_command_and_continues_after_its_id() -> None:
    """The driver still runs command 7 from the planner before the restart: the new planner sends
    nothing until it ends (a new command 7 would be dropped as a duplicate and the old completion
    booked to the new step), then sends 8."""
    ex = Executive(ExecutiveConfig(agent=AgentConfig(initial_turns=1)))
    ex.on_task(spec())
    ex.on_driver(driver(completed=6, active=7))
    ex.on_snapshot(snapshot(3, after=6))
    ex.on_odom(odom(after=6))
    out = ex.poll(0.0)
    assert commands(out) == [] and "command 7" in ex.waiting and ex.task.steps == 0
    ex.on_driver(driver(completed=7))
    ex.on_odom(odom(after=7))
    assert commands(ex.poll(0.1)) == [] and ex.task.steps == 0  # the map has not seen after 7
    ex.on_snapshot(snapshot(4, after=7))
    assert [c.action_id for c in commands(ex.poll(0.2))] == [8]


def test_no_decision_while_the_camera_reports_a_fault_and_the_event_says_why(ex: Executive) -> None:
    from ovamos.shared.messages import CameraState

    ex.on_driver(driver())
    ex.on_snapshot(snapshot(0))
    ex.on_odom(odom())
    ex.on_camera(CameraState(stamp=0.0, backend="realsense", fault="no frames for 1.2 s"))
    out = ex.poll(0.0)
    assert commands(out) == [] and events(out)[-1].message == "camera: no frames for 1.2 s"
    ex.on_camera(CameraState(stamp=1.0, backend="realsense"))  # frames again
    assert len(commands(ex.poll(0.1))) == 1


def test_events_carry_the_goal_while_the_task_searches() -> None:
    ex = Executive(ExecutiveConfig(agent=AgentConfig(initial_turns=0)))
    ex.on_task(spec())
    assert ex.event().goal is None  # nothing decided yet
    cup = ObjectInstance(label="cup", x=3.0, y=1.0, score=0.8, hits=3, confirmed=True)
    ex.on_driver(driver())
    ex.on_snapshot(snapshot(0, (cup,)))
    ex.on_odom(odom())
    assert commands(ex.poll(0.0))
    goal = ex.event().goal
    assert goal is not None and (goal.kind, goal.x, goal.y, goal.label) == ("object", 3.0, 1.0, "cup")
    ex.on_task(spec(cancelled=True))
    assert ex.event().goal is None  # over: no goal shown


def test_each_decision_goes_out_as_a_trace_and_a_kept_goal_sends_none() -> None:
    ex = Executive(ExecutiveConfig(agent=AgentConfig(initial_turns=0)))
    ex.on_task(spec())
    cup = ObjectInstance(label="cup", x=3.0, y=1.0, score=0.8, hits=3, confirmed=True)
    ex.on_driver(driver())
    ex.on_snapshot(snapshot(0, (cup,)))
    ex.on_odom(odom())
    out = ex.poll(0.0)
    traces = [m for m in out if isinstance(m, DecisionTrace)]
    assert len(traces) == 1 and commands(out)
    trace = traces[0]
    assert (trace.task_id, trace.map_seq, trace.remaining, trace.robot_x) == ("t1", 0, ("cup",), 1.0)
    assert trace.goal == ex.event().goal and "confirmed cup" in trace.reason
    ex.on_driver(driver(completed=1))
    ex.on_odom(odom(x=1.25, after=1))
    ex.on_snapshot(snapshot(1, (cup,)))
    out = ex.poll(0.1)
    assert commands(out) and not [m for m in out if isinstance(m, DecisionTrace)]  # same goal: no decision


def test_the_robot_unreachable_pauses_the_task_with_the_reason_and_it_resumes_by_itself(ex: Executive) -> None:
    ex.on_driver(driver())
    ex.on_snapshot(snapshot(0))
    ex.on_odom(odom())
    assert [c.action_id for c in commands(ex.poll(0.0))] == [1]
    ex.on_driver(driver(active=1))
    ex.on_robot_link(False)                                   # the driver's liveliness is gone
    out = ex.poll(0.5)
    assert commands(out) == [] and events(out)[-1].message == "robot unreachable"
    assert commands(ex.poll(5.0)) == [] and ex.waiting == "robot unreachable"
    ex.on_robot_link(True)                                    # back: its state before the loss is stale
    assert commands(ex.poll(5.1)) == [] and "driver" in ex.waiting
    ex.on_driver(driver(completed=1, outcome="aborted"))      # it stopped the command meanwhile
    ex.on_odom(odom(x=1.1, after=1))
    ex.on_snapshot(snapshot(1))
    out = ex.poll(5.2)
    assert [c.action_id for c in commands(out)] == [2] and ex.task.steps == 1 and ex.waiting == ""


def test_a_driver_that_says_it_shuts_down_is_not_reported_unreachable(ex: Executive) -> None:
    """A normal shutdown of the stack stops the driver before the planner: it says so first
    (``DriverMode.OFF``), so the token's loss that follows is not a lost link."""
    ex.on_driver(driver())
    ex.on_snapshot(snapshot(0))
    ex.on_odom(odom())
    assert commands(ex.poll(0.0))
    ex.on_driver(driver(mode=DriverMode.OFF, active=1))
    assert commands(ex.poll(0.5)) == [] and ex.waiting == "the robot's driver shut down"
    ex.on_robot_link(False)
    out = ex.poll(1.0)
    assert commands(out) == [] and ex.unreachable_why == ex.waiting == "the robot's driver shut down"
    ex.on_robot_link(True)
    ex.on_driver(driver(active=1))
    ex.on_robot_link(False)                                   # no word this time: the link
    assert commands(ex.poll(2.0)) == [] and ex.waiting == "robot unreachable"
    # its word arriving after the token's loss (they travel apart) still names the cause
    ex.on_driver(driver(mode=DriverMode.OFF, active=1))
    assert commands(ex.poll(2.5)) == [] and ex.waiting == "the robot's driver shut down"
    assert ex.driver is None  # a late word changes the reason, not the state kept


def test_a_driver_restart_is_a_new_odometry_session_and_no_plan_is_made_on_the_old_map(
        ex: Executive) -> None:
    ex.on_driver(driver(session="A"))
    ex.on_snapshot(snapshot(0, session="A"))
    ex.on_odom(odom(session="A"))
    assert [c.action_id for c in commands(ex.poll(0.0))] == [1]
    ex.on_driver(driver(active=1, session="A"))
    ex.on_robot_link(False)                                   # the driver process died ...
    ex.on_robot_link(True)
    ex.on_driver(driver(session="B"))                         # ... and started again: odometry at zero
    ex.on_odom(odom(x=0.0, y=0.0, session="B"))
    assert ex.in_flight is None                               # command 1 was decided in the old frame
    assert ex.map_wanted() == 0                               # the map is asked for at once
    out = ex.poll(0.1)
    assert commands(out) == [] and events(out)[-1].message == f"{OLD_MAP} (the map is of session 'A', the driver's is 'B')"
    assert events(out)[-1].odom_session == "B"
    ex.on_snapshot(snapshot(1, after=1, session="A"))         # a late map of session A changes nothing
    assert commands(ex.poll(0.2)) == [] and ex.waiting.startswith(OLD_MAP)
    ex.on_snapshot(snapshot(0, after=0, session="B"))         # the fresh map (its seq starts again)
    assert ex.map_wanted() is None
    out = ex.poll(0.3)
    assert [c.action for c in commands(out)] == [Action.TURN_LEFT]  # a new look-around, then on
    assert [c.action_id for c in commands(out)] == [2] and ex.task.steps == 0 and ex.waiting == ""


def test_a_forged_driver_state_is_ignored_and_a_restart_is_followed_on_evidence() -> None:
    """Issue 33, finding 1: one driver state of a made-up session dropped the command in flight
    and held the task waiting for a map of that session."""
    clock = [0.0]
    ex = Executive(ExecutiveConfig(agent=AgentConfig(initial_turns=2)), receipt_clock=lambda: clock[0])
    ex.on_task(spec())
    ex.on_driver(driver(session="A", stamp=1.0))
    ex.on_snapshot(snapshot(0, session="A"))
    ex.on_odom(odom(session="A"))
    assert [c.action_id for c in commands(ex.poll(0.0))] == [1]
    for forged in ("20991231T235959Z-ffffff", ""):
        clock[0] += 0.1
        ex.on_driver(driver(session=forged, stamp=10**9))
    assert ex.in_flight is not None and ex.driver is not None and ex.driver.odom_session == "A"
    assert not ex.waiting
    # the driver restarts without its link being lost: A goes quiet, B's states stream at 5 Hz
    clock[0] += 1.0
    for k in range(5):
        clock[0] += 0.2
        ex.on_driver(driver(session="B", stamp=2.0 + k * 0.2))
    assert ex.in_flight is None and ex.driver is not None and ex.driver.odom_session == "B"
    out = ex.poll(0.5)
    assert events(out)[-1].message == f"{OLD_MAP} (the map is of session 'A', the driver's is 'B')"
    ex.on_driver(driver(session="A", stamp=3.0))  # a late state of the session left: ignored
    assert ex.driver.odom_session == "B"


def test_a_forged_odometry_stream_mid_task_reaches_no_pose_and_a_restart_seen_in_odometry_is_followed() -> None:
    """Issue 49: 30 odometry messages of another session at 10 Hz mid-task, between the real ones,
    put forged poses at the map origin into the task's events (its recorded path). Odometry now
    follows the driver's session as its states do: the forged ones are counted, and no event carries
    them. A driver that really restarts (its session quiet, a new one streaming odometry) is followed
    from its odometry as from its states."""
    clock = [0.0]
    ex = Executive(ExecutiveConfig(agent=AgentConfig(initial_turns=2)), receipt_clock=lambda: clock[0])
    ex.on_task(spec())
    ex.on_driver(driver(session="A", stamp=1.0))
    ex.on_snapshot(snapshot(0, session="A"))
    ex.on_odom(odom(x=2.0, y=3.0, session="A"))
    assert [c.action_id for c in commands(ex.poll(0.0))] == [1]
    seen = []
    for k in range(30):
        clock[0] += 0.05
        ex.on_odom(Odometry(seq=k + 1, stamp=clock[0], x=2.0 + 0.001 * k, y=3.0, yaw=0.0, odom_session="A"))
        clock[0] += 0.05
        ex.on_odom(Odometry(seq=k + 1, stamp=clock[0], x=0.0, y=0.0, yaw=0.0, odom_session="forged"))
        seen.append(ex.event())
    assert all(e.x is not None and e.x >= 2.0 and e.y == 3.0 and e.odom_session == "A" for e in seen)
    assert ex.sessions.stray["odom"] == 30 and ex.sessions.current == "A" and ex.in_flight is not None
    clock[0] += 1.0  # A goes quiet; B's odometry streams at 10 Hz
    for k in range(5):
        clock[0] += 0.1
        ex.on_odom(Odometry(seq=k + 1, stamp=clock[0], x=0.1 * k, y=0.0, yaw=0.0, odom_session="B"))
    assert ex.sessions.current == "B" and ex.in_flight is None and ex.odom is not None and ex.odom.x == pytest.approx(0.4)
    ex.on_driver(driver(session="B", stamp=5.0))
    assert ex.driver is not None and ex.driver.odom_session == "B" and ex.event().odom_session == "B"
