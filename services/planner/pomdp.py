"""The paper's POMDP for choosing where to go next (Sec. III-C), as a generative model for POUCT.

State: (robot point, target point) as indices into the decision step's action
points (0 is the robot's current position, then the candidates, then the best
frontier if any). Actions: MoveTo(point). Observation: 1 when the target is
seen, with P(o=1) = 1 if d <= delta else exp(-beta (d - delta)), d the path
distance between the robot and the target. Reward: -lambda_move * distance
travelled + lambda_frontier for going to the frontier + lambda_target when the
robot ends within delta of the target. Reaching the target or the frontier
ends the simulated episode: beyond the frontier the model knows nothing, and
without the end the planner could collect the frontier bonus forever.
All distances come from one matrix computed per decision step (path lengths on
the map), never from a path search inside a simulated step.
"""

from __future__ import annotations

import math
import random
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

State = tuple[int, int]  # (robot point, target point)


class POMDPConfig(BaseModel):
    """Paper values as defaults."""

    model_config = ConfigDict(extra="forbid")
    lambda_move: float = Field(default=20.0, ge=0, description="reward per metre travelled (negated)")
    lambda_frontier: float = Field(default=500.0, description="reward for exploring the frontier")
    lambda_target: float = Field(default=500.0, description="reward for reaching the target")
    delta: float = Field(default=1.0, gt=0, description="metres within which the target is found")
    beta: float = Field(default=1.0, gt=0, description="detection fall-off per metre beyond delta")
    gamma: float = Field(default=0.95, gt=0, le=1)
    num_sims: int = Field(default=500, ge=1)
    max_depth: int = Field(default=5, ge=1)
    exploration: float = Field(default=500.0, gt=0, description="UCB1 constant, on the reward scale")
    particles: int = Field(default=200, ge=1, description="root belief particles")


@dataclass
class SearchPOMDP:
    """Generative model over one decision step's action points."""

    distances: np.ndarray           # P x P path lengths between points (0 = robot)
    candidates: Sequence[int]       # point indices that are candidates (where the target may be)
    frontier: int | None            # point index of the best frontier, if any
    config: POMDPConfig

    def __post_init__(self) -> None:
        c = self.config
        # plain lists: the simulation loop indexes them millions of times
        self._d = self.distances.tolist()
        self._actions = [*self.candidates, *([self.frontier] if self.frontier is not None else [])]
        self._p_seen = [[1.0 if d <= c.delta else math.exp(-c.beta * (d - c.delta)) for d in row]
                        for row in self._d]

    def actions(self, state: State) -> Sequence[int]:
        return self._actions

    def step(self, state: State, action: int, rng: random.Random) -> tuple[State, int, float, bool]:
        robot, target = state
        c = self.config
        reward = -c.lambda_move * self._d[robot][action]
        if action == self.frontier:
            return (action, target), 0, reward + c.lambda_frontier, True
        if self._d[action][target] <= c.delta:
            return (action, target), 1, reward + c.lambda_target, True
        seen = 1 if rng.random() < self._p_seen[action][target] else 0
        return (action, target), seen, reward, False

    def rollout(self, state: State, rng: random.Random) -> int:
        return rng.choice(self._actions)


def root_particles(candidates: Sequence[int], belief: np.ndarray, count: int, seed: int) -> list[State]:
    """Robot at point 0, target drawn from the belief over candidates."""
    rng = np.random.default_rng(seed)
    picks = rng.choice(len(candidates), size=count, p=belief)
    return [(0, int(candidates[i])) for i in picks]
