"""The search agent's goal keeping on hand-made maps."""

from __future__ import annotations

from services.planner.agent import AgentConfig, SearchAgent
from services.planner.task import Task
from shared.motion import Pose
from tests.planner_maps import snapshot


def agent(**config: object) -> SearchAgent:
    return SearchAgent(Task("t", ["cup"]), AgentConfig(initial_turns=0, **config))  # type: ignore[arg-type]


def test_a_frontier_goal_is_decided_again_every_few_commands() -> None:
    a, pose = agent(redecide_every=2), Pose(x=2.0, y=5.0, yaw=0.0)
    for _ in range(5):
        a.executed(a.next_step(snapshot({}, [(8.0, 5.0)]), pose), 0.25, pose=pose)
    assert a.decisions == 3
