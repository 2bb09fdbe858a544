"""Continuous motion: the agent's navigation steps become path commands the robot drives without stopping.

Stepwise (the paper's, the default) every step is one primitive and the robot stands still while
the frame taken after it is perceived, fused and decided on. Continuous, a navigation step sends
the navigator's remaining path to the goal instead; the robot follows it closed-loop on odometry
while frames free-run into the map, and the agent is asked again (the step booked with the ground
covered so far) when one of :meth:`Redecision.due`'s events happens or ``decide_every_s`` has
passed, never waiting for the robot to stop. Every other step (the look-around, a turn with nowhere
to go, ovamos-plus's check turns, the STOP beside a found object) stays a primitive, so a found
target still ends with the robot within its STOP distance and a STOP.

A step is then a decision tick: ``decide_every_s`` defaults to about the time a MOVE_FORWARD's
0.25 m takes at a TurtleBot's top speed, so the agent's step-counted rules (re-decide every 4,
stuck after 10, the task's step limit) keep roughly their stepwise meaning in ground covered.
Both the planner's executive (over Zenoh) and the benchmark's simulated-time episodes use this
module, so they drive the same way.
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass

from ovamos.services.planner.agent import AgentConfig, Reason, SearchAgent, Step
from ovamos.services.planner.decide import GoalKind
from ovamos.shared.messages import MAX_PATH_POINTS, MapSnapshot
from ovamos.shared.motion import Action, Pose


def path_for(agent: SearchAgent, step: Step) -> tuple[tuple[float, float], ...] | None:
    """The path to send for ``step`` (the navigator's remaining path, as of the decision just made),
    or None when the step stays a primitive (anything but navigating towards a goal, and navigating
    within ``careful_steps`` of a bump)."""
    if step.reason is not Reason.NAVIGATE:
        return None
    since = agent.bumps.since(agent.task.steps)
    if since is not None and since < agent.config.careful_steps:
        return None
    points = agent.navigator.path
    if len(points) == 0:
        return None
    return tuple((round(float(x), 4), round(float(y), 4)) for x, y in points[:MAX_PATH_POINTS])


def booked_step(step: Step, path: bool, blocked: bool, decided_at: Pose, now: Pose) -> tuple[Step, Pose]:
    """What the agent books for ``step`` and from where: a blocked path as a blocked MOVE_FORWARD
    from where the robot stopped (the bump is ahead of it there, not of where the path began)."""
    if path and blocked:
        return Step(Action.MOVE_FORWARD, Reason.NAVIGATE, step.goal), now
    return step, decided_at


@dataclass
class Redecision:
    """When a path in flight is decided on again: what the map and the robot showed at the decision,
    compared with now."""

    step: Step
    decided_at: float
    confirmed: Counter[str]  # the remaining targets' confirmed objects, by label

    @classmethod
    def start(cls, step: Step, now: float, snapshot: MapSnapshot, remaining: list[str]) -> Redecision:
        return cls(step, now, _confirmed(snapshot, remaining))

    def due(self, now: float, snapshot: MapSnapshot, pose: Pose, remaining: list[str], config: AgentConfig
            ) -> str | None:
        """Why to decide again now (None: keep following): a remaining target confirmed since (it
        may be worth a detour), within STOP distance of the object the path goes to (STOP there,
        not at the path's end), or the decision period has passed (the map has grown: the goal
        may have become unreachable or a better frontier appeared)."""
        if _confirmed(snapshot, remaining) - self.confirmed:  # (positions are refined: counted, not compared)
            return "a target confirmed"
        goal = self.step.goal
        if goal is not None and goal.kind is GoalKind.OBJECT \
                and math.hypot(goal.x - pose.x, goal.y - pose.y) <= config.object_stop_m:
            return "at the object"
        if now - self.decided_at >= config.decide_every_s:
            return "period"
        return None


def _confirmed(snapshot: MapSnapshot, remaining: list[str]) -> Counter[str]:
    return Counter(o.label for o in snapshot.objects if o.confirmed and o.label in remaining)
