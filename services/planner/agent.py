"""The search loop of one robot: decisions, navigation and found-object STOPs, one command at a time.

The planner service (over Zenoh) and the in-process episode runner both drive
this class, so the distributed system and the benchmark run the same method:

    step = agent.next_step(snapshot, pose)   # what to execute now
    ... execute step.action, get a new frame fused into the map ...
    agent.executed(step, moved_m, blocked)   # book-keeping: steps, found targets

A decision (the POUCT step of :mod:`ovamos.services.planner.decide`) picks a goal; the
navigator turns it into primitives. A candidate goal (the POMDP's macro
action) is kept until it is reached; frontier and object goals are decided
again every ``redecide_every`` commands (1 m of travel by default). Any goal
is dropped when it proves unreachable, and a candidate or frontier when a
confirmed object of a remaining target appears. A reached candidate is not
chosen again (its place has been looked at from within delta). A STOP is only
ever sent beside a confirmed object, and declares that target found (checked
again on arrival): reaching a candidate or a frontier is not a STOP (the
paper's STOP ends the search for a target, so a wrong one costs the target).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from enum import Enum

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from ovamos.services.planner.decide import Decision, DecisionConfig, GoalKind, away, decide
from ovamos.services.planner.navigator import NavigationConfig, Navigator, NavMap, Unreachable
from ovamos.services.planner.outcome import explain, target_misses
from ovamos.services.planner.plus import goal_budget, strict_objects
from ovamos.services.planner.task import SearchTask
from ovamos.shared.grid import inflate
from ovamos.shared.messages import MapSnapshot, ObjectInstance, TargetMiss, TaskStatus
from ovamos.shared.motion import Action, DriveMode, Pose
from ovamos.shared.robot import PRIMITIVES, ROBOT, Primitives

log = logging.getLogger("ovamos.planner")


class AgentConfig(BaseModel):
    """Everything one search needs besides the map: the method's and the controller's parameters."""

    model_config = ConfigDict(extra="forbid")
    decision: DecisionConfig = Field(default_factory=DecisionConfig)
    navigation: NavigationConfig = Field(default_factory=NavigationConfig)
    initial_turns: int = Field(default=round(360 / PRIMITIVES.turn_deg), ge=0,
                               description="look around first (12 x 30 deg = 360)")
    redecide_every: int = Field(
        default=4, ge=1,
        description="commands towards a frontier or object goal before deciding again (4 = 1 m)")
    object_stop_m: float = Field(default=0.9, gt=0, le=1.0,
                                 description="STOP this close to a confirmed object (success: 1 m)")
    max_blocked: int = Field(default=3, ge=1,
                             description="blocked moves in a row before the goal is given up")
    max_idle_turns: int = Field(default=12, ge=1,
                                description="turns with nowhere to go before the task fails")
    stuck_steps: int = Field(
        default=10, ge=2,
        description="navigation commands that leave the robot within 0.1 m before the goal is "
                    "given up (a controller oscillating between two headings)")
    bump_depth_m: float = Field(
        default=PRIMITIVES.forward_m, gt=0,
        description="a blocked MOVE_FORWARD marks an obstacle this far ahead (the step it could not "
                    "make): what the depth camera cannot see (closer than its range, below its "
                    "view) the bumper can")
    memory_steps: int = Field(
        default=100, ge=1,
        description="bumps and goals found unreachable are forgotten after this many commands")
    boxed_in_share: float = Field(
        default=0.5, gt=0, le=1,
        description="with no goal it can reach, the robot is boxed in when it can reach less than "
                    "this share of the explored area it could stand on; it then recovers: forgets "
                    "bumps and unreachable goals, takes the cells it drove over as free, looks around")

    motion: DriveMode = Field(
        default="stepwise",
        description="stepwise: every step one primitive, the robot standing still for the frame after "
                    "it (the paper's; deterministic); continuous: a navigation step is a path the robot "
                    "follows while frames free-run, decided again on events and every decide_every_s "
                    "(services/planner/continuous.py)")
    careful_steps: int = Field(
        default=5, ge=0,
        description="continuous: after a bump, this many steps drive primitives (the navigator's 0.25 m "
                    "moves, each checked on the map with the bump), or careful paths where careful_path_m "
                    "is set: a path re-planned past a bump the camera cannot see, at full speed, grazes it "
                    "again")
    careful_path_m: float = Field(
        default=0.0, ge=0,
        description="continuous: > 0: the careful steps are careful paths, the navigator's path cut to this "
                    "length, at careful_m_s, the bumps named, and the navigator's map grows each bump by "
                    "careful_clearance_m; 0 (the default): primitives. Off because on the development seed "
                    "(40 episodes, OpenCR) careful paths of 0.5 m at 0.15 m/s lost SR and MSPL against "
                    "primitives (docs/benchmarks/search.md#careful-paths-after-a-bump-development-seed)")
    careful_m_s: float = Field(default=0.15, gt=0, description="continuous: a careful path's top speed")
    careful_clearance_m: float = Field(
        default=0.05, ge=0,
        description="continuous, with careful paths: the navigator's map grows each bump remembered (one "
                    "point of an obstacle the map may not have) so that its paths keep the robot's footprint "
                    "this far from it; a careful path that would still come closer is a primitive")
    decide_every_s: float = Field(
        default=1.0, gt=0,
        description="continuous: re-decide this often while a path is followed (a step: about one "
                    "MOVE_FORWARD of ground at a TurtleBot's 0.26 m/s, so the step-counted rules keep "
                    "their meaning)")
    better_frontier: float = Field(
        default=0.25, gt=0,
        description="continuous, going to a frontier: a frontier scoring this much above the best one at the "
                    "decision (the value map's units: each target's layer is normalised to 0..1) is decided on at "
                    "once, not at the next decide_every_s")
    tell_obstacles_m: float = Field(
        default=0.5, ge=0,
        description="continuous: a path command names the mapped obstacles this close to the path, which the "
                    "robot's follower slows near (it has no map); 0: none")
    turn_ahead_deg: float = Field(
        default=0.0, ge=0, le=PRIMITIVES.turn_deg,
        description="continuous: a turn's next step is decided once the turn is this near its heading (for the "
                    "pose it will end at), so a further turn the same way carries on without stopping (a "
                    "look-around, idle turns) and anything else is sent the moment it ends; 0 (the default): "
                    "once the robot stands still. Off because on the development seed (40 episodes) 30 lost SR "
                    "and took longer (docs/benchmarks/search.md#turns-without-standing-still-development-seed)")

    @property
    def primitives(self) -> Primitives:
        """The primitive sizes this planner plans with (its navigator's)."""
        return Primitives(forward_m=self.navigation.forward_m, turn_deg=self.navigation.turn_deg)


class Reason(str, Enum):
    SCAN = "scan"              # the initial look-around
    NAVIGATE = "navigate"      # a primitive towards the goal
    LOOK = "look"              # goal reached, nothing new chosen: turn to see more
    IDLE = "idle"              # nowhere to go (yet): turn in place
    WANDER = "wander"          # the random baseline's walk
    CHECK = "check"            # beside a confirmed object: face it and look again (ovamos-plus)
    FOUND = "found"            # STOP beside a confirmed object
    OVER = "over"              # the task is no longer searching


@dataclass(frozen=True)
class BoxedIn:
    """Where and since when the robot has been cut off from the space it explored."""

    step: int
    x: float
    y: float

    def __str__(self) -> str:
        return f"boxed in near ({self.x:.1f}, {self.y:.1f})"


@dataclass(frozen=True)
class Step:
    """One command and why it was chosen (``action`` None when the task is over)."""

    action: Action | None
    reason: Reason
    goal: Decision | None = None


class ExpiringPlaces:
    """Places remembered for ``memory`` steps (commands), then forgotten: a time-to-live memory.
    A bump or a goal that could not be reached is evidence about the map as it was: a narrow
    doorway the robot bumped into on both sides, and every goal behind it, stay closed for ever
    otherwise, and a robot whose map lost part of what it had seen (a restart from an older
    checkpoint) bumps a lot."""

    def __init__(self, memory: int) -> None:
        self.memory = memory
        self._items: list[tuple[float, float, int]] = []

    def add(self, x: float, y: float, step: int) -> None:
        self._items.append((x, y, step))

    def points(self, step: int) -> list[tuple[float, float]]:
        """The places remembered at ``step``; older ones are dropped."""
        self._items = [item for item in self._items if step - item[2] < self.memory]
        return [(x, y) for x, y, _ in self._items]

    def clear(self) -> None:
        self._items.clear()

    def since(self, step: int) -> int | None:
        """Steps from the newest place remembered to ``step`` (None: none is)."""
        return step - self._items[-1][2] if self._items else None


class SearchAgent:
    """Drives one task; holds the goal, the navigator and the goals found unreachable."""

    def __init__(self, task: SearchTask, config: AgentConfig | None = None) -> None:
        self.task = task
        self.config = config or AgentConfig()
        self.policy = self.config.decision.chosen
        self.navigator = Navigator(self.config.navigation)
        self.goal: Decision | None = None
        self.decisions = 0
        self.unreachable = ExpiringPlaces(self.config.memory_steps)
        self.visited: list[tuple[float, float]] = []   # candidates reached
        self.rejected: list[tuple[float, float]] = []  # confirmed objects a close look did not bear out
        self._look: tuple[Decision, int, int, int] | None = None  # looked at: hits, views then; turns
        self._scan_left = self.config.initial_turns
        self._toward_goal = 0
        self._goal_commands = 0                 # commands towards the same goal, across re-decisions
        self._goal_budget: int | None = None    # ovamos-plus: commands before the goal is given up
        self._blocked = 0
        self._idle = 0
        self._recent: list[tuple[float, float]] = []
        self.bumps = ExpiringPlaces(self.config.memory_steps)
        self.trail: list[tuple[float, float]] = []  # where the robot stood, step by step
        self.boxed: BoxedIn | None = None           # cut off, and not moved towards a goal since
        self._trail_free = False                    # after a recovery: the cells driven over are free
        self._goalless_since: int | None = None     # the step since which no goal could be driven to
        self._objects: tuple[ObjectInstance, ...] = ()  # the newest map's, for the failure's reason
        if task.state is TaskStatus.QUEUED:
            task.start()

    # -- the loop ------------------------------------------------------------------------------
    def next_step(self, snapshot: MapSnapshot, pose: Pose) -> Step:
        if self.task.state is not TaskStatus.SEARCHING:
            return Step(None, Reason.OVER)
        self._objects = snapshot.objects
        if self._scan_left > 0:
            return Step(Action.TURN_LEFT, Reason.SCAN)
        remaining = self.policy.targets(self.task.remaining)
        plus = self.config.decision.plus
        if self.policy.plus_switches and plus.strict_stop:  # a stricter idea of found
            snapshot = snapshot.model_copy(update={"objects": strict_objects(snapshot.objects, plus)})
        if self.goal is None or self._goal_expired() or (
                self.goal.kind is not GoalKind.OBJECT and self._object_seen(snapshot, remaining)):
            self._decide(snapshot, pose, remaining)
        for _ in range(2):  # the goal, then (if it was reached or unreachable) one fresh decision
            if self.goal is None:
                return self._wander() if self.policy.wanders else self._idle_turn(snapshot, pose)
            goal = self.goal
            if goal.kind is GoalKind.OBJECT and math.hypot(goal.x - pose.x, goal.y - pose.y) \
                    <= self.config.object_stop_m:
                obj = self._confirmed_at(snapshot, goal)
                if obj is not None:
                    turn = self._look_turn(obj, pose, goal)
                    if turn is None:
                        return Step(Action.STOP, Reason.FOUND, goal)
                    if turn is not Action.STOP:
                        return Step(turn, Reason.CHECK, goal)
                    log.info("step %d: %s at (%.2f, %.2f) not detected again from close by: left alone",
                             self.task.steps, goal.label, goal.x, goal.y)
                    self.rejected.append((goal.x, goal.y))
                self._decide(snapshot, pose, remaining)  # the close views unconfirmed it
                continue
            if self._goal_budget is not None and self._goal_commands >= self._goal_budget:
                log.info("step %d: goal (%.2f, %.2f) not reached in its %d commands: given up",
                         self.task.steps, goal.x, goal.y, self._goal_budget)
                self.unreachable.add(goal.x, goal.y, self.task.steps)
                self._decide(snapshot, pose, remaining)
                continue
            try:
                action = self.navigator.next_command(self._nav_map(snapshot), pose, (goal.x, goal.y),
                                                     self._snap_radius(goal))
            except Unreachable as exc:
                log.info("step %d: %s", self.task.steps, exc)
                self.unreachable.add(goal.x, goal.y, self.task.steps)
                self._decide(snapshot, pose, remaining)
                continue
            if action is not Action.STOP:
                self._idle, self._goalless_since, self.boxed = 0, None, None
                return Step(action, Reason.NAVIGATE, goal)
            if goal.kind is GoalKind.OBJECT:  # as close as the map allows, still too far
                log.info("step %d: %s at (%.2f, %.2f): the closest reachable place is %.2f m away",
                         self.task.steps, goal.label, goal.x, goal.y,
                         math.hypot(goal.x - pose.x, goal.y - pose.y))
                self.unreachable.add(goal.x, goal.y, self.task.steps)
            elif goal.kind is GoalKind.CANDIDATE:
                self.visited.append((goal.x, goal.y))
            self._decide(snapshot, pose, remaining, reached=goal)
        if self._boxed_in(snapshot, pose):
            return self._recover(pose)
        return Step(Action.TURN_LEFT, Reason.LOOK, self.goal)

    def executed(self, step: Step, moved_m: float, blocked: bool = False, pose: Pose | None = None
                 ) -> None:
        """Book-keeping after ``step`` was executed (``pose``: where it was executed from): one
        step spent, a STOP declares its target, a bump marks an obstacle."""
        if step.action is None or self.task.state is not TaskStatus.SEARCHING:
            return
        if pose is not None:
            self.trail.append((pose.x, pose.y))
        found = None
        if step.reason is Reason.FOUND and step.goal is not None and step.goal.label is not None:
            found = (step.goal.label, step.goal.x, step.goal.y)
            self.goal = None
        if step.reason is Reason.SCAN:
            self._scan_left -= 1
        elif step.reason is Reason.NAVIGATE:
            self._toward_goal += 1
            self._goal_commands += 1
        self._blocked = self._blocked + 1 if blocked else 0
        if blocked and step.action is Action.MOVE_FORWARD and pose is not None:
            d = self.config.bump_depth_m
            ahead = (pose.x + d * math.cos(pose.yaw), pose.y + d * math.sin(pose.yaw))
            self.bumps.add(*ahead, self.task.steps)
        if self._blocked >= self.config.max_blocked or self._stuck(step, pose):
            self._give_up_goal()
        self.task.record_step(moved_m, found)
        if self.task.state is TaskStatus.FAILED:
            self.task.explain(self.why_not_found())

    # -- what the operator is told -------------------------------------------------------------
    @property
    def condition(self) -> str:
        """The search's state when it is not plain searching (an operator wants to know)."""
        if self.boxed is not None:
            return (f"{self.boxed} since step {self.boxed.step}: recovering (bumps and unreachable goals "
                    f"forgotten, the cells it drove over taken as free, looking around)")
        if self._goalless_since is not None:
            return f"no reachable frontier or candidate since step {self._goalless_since}: looking around"
        return ""

    def misses(self) -> tuple[TargetMiss, ...]:
        """The targets not found yet and how far the newest map shows their search got."""
        return target_misses(self.task.remaining, self._objects)

    def why_not_found(self) -> str:
        """``no reachable frontier or candidate since step 212 (boxed in near (11.5, 6.2)); bed
        never seen``: what kept the robot from its goals, then each target's stage."""
        parts = [explain(self.misses())]
        if self._goalless_since is not None:
            boxed = f" ({self.boxed})" if self.boxed is not None else ""
            parts.insert(0, f"no reachable frontier or candidate since step {self._goalless_since}{boxed}")
        return "; ".join(p for p in parts if p)

    # -- helpers -------------------------------------------------------------------------------
    def _decide(self, snapshot: MapSnapshot, pose: Pose, remaining: list[str],
                reached: Decision | None = None) -> None:
        visited = self.visited + ([(reached.x, reached.y)] if reached else [])
        previous = self.goal
        self.goal = decide(snapshot, (pose.x, pose.y), remaining, self.config.decision,
                           np.array(self._avoided(), float).reshape(-1, 2), np.array(visited, float))
        g, same_place = self.goal, self.config.decision.avoid_radius_m
        if g is not None and (previous is None or (g.kind, g.label) != (previous.kind, previous.label)
                              or math.hypot(g.x - previous.x, g.y - previous.y) > same_place):
            log.info("step %d: goal %s%s at (%.2f, %.2f) of %d candidates", self.task.steps, g.kind.value,
                     f" {g.label}" if g.label else "", g.x, g.y, g.candidates)
            self._goal_commands = 0
            self._goal_budget = goal_budget(math.hypot(g.x - pose.x, g.y - pose.y), self.config.decision.plus) \
                if self.policy.plus_switches else None
        self.decisions += 1
        self._toward_goal = 0

    def _give_up_goal(self) -> None:
        if self.goal is not None:
            log.info("step %d: giving up goal (%.2f, %.2f): blocked or stuck", self.task.steps,
                     self.goal.x, self.goal.y)
            self.unreachable.add(self.goal.x, self.goal.y, self.task.steps)
        self.goal, self._blocked = None, 0
        self._recent.clear()

    def _stuck(self, step: Step, pose: Pose | None) -> bool:
        """True when the last ``stuck_steps`` navigation commands kept the robot in place."""
        if step.reason is not Reason.NAVIGATE or pose is None:
            self._recent.clear()
            return False
        self._recent.append((pose.x, pose.y))
        n = self.config.stuck_steps
        if len(self._recent) < n:
            return False
        xy = np.array(self._recent[-n:])
        del self._recent[:-n]
        return bool(np.ptp(xy, axis=0).max() < 0.1)

    def _nav_map(self, snapshot: MapSnapshot) -> NavMap:
        """The snapshot's obstacles, after a recovery less the cells the robot drove over, plus
        the bumps (the freshest evidence, so they win; copied only when there is a change)."""
        nav = NavMap.from_snapshot(snapshot)
        bumps = self.bumps.points(self.task.steps)
        if not bumps and not (self._trail_free and self.trail):
            return nav
        obstacle = nav.obstacle.copy()
        if self._trail_free and self.trail:
            obstacle &= ~self._swept(nav)
        rows, cols = _cells_inside(nav, bumps)
        if self._bump_radius_m > 0 and len(rows):
            bumped = np.zeros(obstacle.shape, bool)
            bumped[rows, cols] = True
            obstacle |= inflate(bumped, self._bump_radius_m, nav.grid.resolution)
        obstacle[rows, cols] = True
        return NavMap(obstacle, nav.explored, nav.grid)

    @property
    def _bump_radius_m(self) -> float:
        """How far round a bump the map is taken as blocked: a point (the paper's; the navigator's
        0.25 m moves are checked against it), and with careful paths as far as keeps the navigator's
        paths ``careful_clearance_m`` off it with the whole footprint (a path followed past a point
        cleared by the navigator's radius alone may graze the obstacle it marks)."""
        c = self.config
        if c.motion != "continuous" or c.careful_path_m == 0:
            return 0.0
        return max(0.0, ROBOT.radius_m + c.careful_clearance_m - c.navigation.robot_radius)

    def _swept(self, nav: NavMap) -> np.ndarray:
        """The cells the robot's footprint swept along its trail, plus a cell (mapped obstacles
        are up to a cell thicker than real ones; the band reaches one more): it drove there, so
        nothing stood there then (an obstacle since is bumped into again)."""
        return nav.grid.band(np.array(self.trail, float), math.ceil(ROBOT.radius_m / nav.grid.resolution) + 1)

    def _boxed_in(self, snapshot: MapSnapshot, pose: Pose) -> bool:
        """No goal to drive to and cut off from most of what was explored, not yet recovering."""
        return self.goal is None and self.boxed is None and self.navigator.reachable_share(
            self._nav_map(snapshot), pose) < self.config.boxed_in_share

    def _recover(self, pose: Pose) -> Step:
        """Boxed in: forget every bump and unreachable goal (evidence of a map that has changed),
        take the cells it drove over as free (the way in is the way out), look around again."""
        self.boxed = BoxedIn(self.task.steps, pose.x, pose.y)
        if self._goalless_since is None:
            self._goalless_since = self.task.steps
        log.warning("step %d: %s (it reaches under %.0f %% of the explored area): recovering",
                    self.task.steps, self.boxed, 100 * self.config.boxed_in_share)
        for memory in (self.bumps, self.unreachable):
            memory.clear()
        self.visited.clear()
        self.rejected.clear()
        self._trail_free, self._idle = True, 0
        self._scan_left = self.config.initial_turns
        return Step(Action.TURN_LEFT, Reason.SCAN)

    def _object_seen(self, snapshot: MapSnapshot, remaining: list[str]) -> bool:
        """A confirmed object of a remaining target that is not known to be unreachable."""
        seen = np.array([(o.x, o.y) for o in snapshot.objects if o.confirmed and o.label in remaining])
        avoided = np.array(self._avoided()).reshape(-1, 2)
        return bool(len(seen)) and bool(away(seen, avoided, self.config.decision.avoid_radius_m).any())

    def _avoided(self) -> list[tuple[float, float]]:
        """Goals not to choose: those found unreachable (for a while) and the objects a close look
        did not bear out (for the rest of the task)."""
        return self.unreachable.points(self.task.steps) + self.rejected

    def _goal_expired(self) -> bool:
        """Time to decide again. A candidate is the POMDP's macro action MoveTo(candidate): it is
        kept until reached (deciding again on the way made the robot flip-flop between
        candidates and look at none). A frontier moves as the map grows and an object's estimate
        is refined: those are decided again every ``redecide_every`` commands (keeping one until it
        was explored cost success: docs/notes/ovamos-plus.md)."""
        goal = self.goal
        return goal is not None and goal.kind is not GoalKind.CANDIDATE \
            and self._toward_goal >= self.config.redecide_every

    def _snap_radius(self, goal: Decision) -> float | None:
        """An object is driven to from the nearest free place within its STOP distance: an object
        in the middle of a bed is farther than the default snap radius from every free cell, and
        was never reached. The agent STOPs on entering that distance; arriving at a snapped
        place at its edge can leave the robot just outside, and the object is then given up
        like any goal the map does not let it reach (a fixed radius did no better:
        docs/notes/ovamos-plus.md)."""
        if goal.kind is not GoalKind.OBJECT:
            return None
        nav = self.config.navigation
        return max(nav.snap_radius_m, self.config.object_stop_m)

    def _confirmed_at(self, snapshot: MapSnapshot, goal: Decision) -> ObjectInstance | None:
        """The confirmed ``goal.label`` the map still holds at the goal (None: none any more): a
        STOP is irrevocable, and the views on the way in may have shown a detection to be a false one."""
        radius = self.config.decision.avoid_radius_m
        return next((o for o in snapshot.objects if o.confirmed and o.label == goal.label
                     and math.hypot(o.x - goal.x, o.y - goal.y) <= radius), None)

    def _look_turn(self, obj: ObjectInstance, pose: Pose, goal: Decision) -> Action | None:
        """ovamos-plus's look before a STOP (``look_before_stop`` turns): None to STOP now (no look
        wanted, a hit came since the robot arrived, or the turns are spent without the map
        counting ``look_views`` views of its place: too close to see it, say), STOP to leave
        the object alone (that many views, none with a hit), else the turn to make. The idea: a
        look-alike is confirmed from detections at any distance, mostly from afar, and the right
        object is detected again from close by. The robot turns to face it, then swings 30
        degrees off and back, so each frame is a new view (79 degree field of view: the object
        stays in it). Off by default: large objects fill the image from that close and are
        rarely detected there (numbers in services/planner/plus.py)."""
        plus = self.config.decision.plus
        if not self.policy.plus_switches or plus.look_before_stop == 0:
            return None
        if self._look is None or self._look[0] is not goal:
            self._look = (goal, obj.hits, obj.views, 0)
        _, hits, views, used = self._look
        if obj.hits > hits:
            return None
        if obj.views - views >= plus.look_views:
            return Action.STOP
        if used >= plus.look_before_stop:
            return None
        self._look = (goal, hits, views, used + 1)
        off = (math.atan2(goal.y - pose.y, goal.x - pose.x) - pose.yaw + math.pi) % (2 * math.pi) - math.pi
        if abs(math.degrees(off)) <= self.config.navigation.turn_deg / 2:
            return Action.TURN_LEFT
        return Action.TURN_LEFT if off > 0 else Action.TURN_RIGHT

    def _wander(self) -> Step:
        """The random baseline's step: forward half the time, else a turn (seeded per step)."""
        rng = np.random.default_rng([self.config.decision.seed, self.task.steps])
        actions = (Action.MOVE_FORWARD, Action.MOVE_FORWARD, Action.TURN_LEFT, Action.TURN_RIGHT)
        return Step(actions[int(rng.integers(len(actions)))], Reason.WANDER)

    def _idle_turn(self, snapshot: MapSnapshot, pose: Pose) -> Step:
        """Turn in place with nowhere to go: boxed in, recover; else, after a full turn, give the
        goals once found unreachable, visited or rejected another chance (the map has changed
        since), then fail."""
        if self._goalless_since is None:
            self._goalless_since = self.task.steps
        if self._boxed_in(snapshot, pose):
            return self._recover(pose)
        self._idle += 1
        if self._idle > self.config.max_idle_turns:
            if not self._avoided() and not self.visited:
                self.task.fail("nothing left to explore")
                self.task.explain(explain(self.misses()))
                return Step(None, Reason.OVER)
            self.unreachable.clear()
            self.visited.clear()
            self.rejected.clear()
            self._idle = 0
        return Step(Action.TURN_LEFT, Reason.IDLE)


def _cells_inside(nav: NavMap, points: list[tuple[float, float]]) -> tuple[np.ndarray, np.ndarray]:
    """(rows, cols) of the grid cells of world ``points`` that lie on the grid."""
    if not points:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    rows, cols = nav.grid.to_cell(*np.array(points).T)
    inside = (rows >= 0) & (rows < nav.grid.rows) & (cols >= 0) & (cols < nav.grid.cols)
    return rows[inside], cols[inside]
