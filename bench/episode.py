"""One search episode in one process: the services' cores wired together without Zenoh.

The loop is the lock-step loop of the distributed system (command -> executed ->
frame -> perception -> map fused -> next command), with the same classes the
services run: :class:`SceneRenderer` and :class:`SimRobot` (the simulated robot
service), :class:`SimPerception` through a :class:`PerceptionResult` (the
perception service), :meth:`MapState.apply` (the mapping service) and
:class:`SearchAgent` (the planner service). A run of the distributed system in
lock-step with the kinematic robot follows the same trajectory.

On a wheeled ``base`` a primitive is the real base controller driving that base's simulated
device in simulated time (:mod:`ovamos.services.sim.wheels`): it lands where the wheels took it, the
camera sees from the true pose and the planner decides on the base's odometry, as in
``ovamos demo --base B``. With odometry errors (``motion.odometry``) frames are posed by odometry
and the planner's pose is odometry placed in the map (by localization's ``map_T_odom``, when the
map localizes); STOPs are judged where the robot truly is.

The protocol is the paper's: targets from the episode, a STOP counts when a true
instance of its target is within 1 m (the ground truth's geodesic check), the
episode succeeds when every target was found within the step limit, and MSPL
weighs success by the shortest tour through all targets over the path driven.
"""

from __future__ import annotations

import time
import zlib
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import partial
from typing import Any

from pydantic import BaseModel, ConfigDict, Field, field_validator

from ovamos.bench.continuous import RESEND_S, search_continuously, step_kind
from ovamos.bench.funnel import FunnelRecorder, StopRecord, TargetFunnel
from ovamos.bench.policies import planner_policy
from ovamos.bench.trajectory import TrajectoryErrors, trajectory_errors
from ovamos.services.base_driver.config import DriverConfig
from ovamos.services.mapping.config import MappingConfig
from ovamos.services.mapping.localization import Localizer
from ovamos.services.mapping.state import MapState
from ovamos.services.planner.agent import AgentConfig, Reason, SearchAgent, Step
from ovamos.services.planner.continuous import PathStep
from ovamos.services.planner.policies import OVAMOS
from ovamos.services.planner.task import SearchTask
from ovamos.services.sim.robot import MotionConfig, SimRobot
from ovamos.services.sim.wheels import Motion, SerialSimRobot, WheeledSimRobot, base_motion, frame_pose, wheeled
from ovamos.shared.messages import MapSnapshot, PerceptionResult, PlanCommand, TaskStatus
from ovamos.shared.motion import Action, Pose, to_odom
from ovamos.shared.simtime import SimClock
from ovamos.world.episodes import EpisodeSpec
from ovamos.world.evaluator import GroundTruth, spl
from ovamos.world.perception import FrameLabels, SimPerception, SimPerceptionConfig
from ovamos.world.prior import ObjectPrior
from ovamos.world.render import SceneRenderer
from ovamos.world.scene import Scene


class StepLatency(BaseModel):
    """What a stepwise step costs besides its motion, the robot standing still: the frame taken after
    the command, perception, fusion and the decision. Defaults are assumptions for a GPU laptop
    (the stack's own timings on this CPU-only machine are slower), so the search time is the base's
    motion as simulated plus these: configure them to a deployment's measured latencies."""

    model_config = ConfigDict(extra="forbid")
    frame_s: float = Field(default=0.033, ge=0, description="the next frame of a 30 Hz camera")
    perception_s: float = Field(default=0.08, ge=0, description="detection and scoring of one frame")
    mapping_s: float = Field(default=0.02, ge=0, description="fusing the frame into the map")
    decision_s: float = Field(default=0.05, ge=0, description="the planner's decision step")

    @property
    def total_s(self) -> float:
        return self.frame_s + self.perception_s + self.mapping_s + self.decision_s

    @classmethod
    def totalling(cls, total_s: float | None) -> StepLatency:
        """The defaults scaled to ``total_s`` a step (``bench search --step-latency``: a deployment's
        measured figure, or a sensitivity run), their proportions kept; None: the defaults."""
        default = cls()
        if total_s is None:
            return default
        k = total_s / default.total_s
        return cls(frame_s=default.frame_s * k, perception_s=default.perception_s * k,
                   mapping_s=default.mapping_s * k, decision_s=default.decision_s * k)


class EpisodeConfig(BaseModel):
    """Everything an episode's outcome depends on besides the episode itself."""

    model_config = ConfigDict(extra="forbid")
    policy: str = Field(default=OVAMOS.name, description="the benchmark's name of the policy: a planner "
                        "policy or an ablation of ovamos-plus (bench/policies.py); results carry it")
    width: int = Field(default=320, ge=16, description="camera image width (pixels)")
    height: int = Field(default=240, ge=16)
    agent: AgentConfig = Field(default_factory=AgentConfig)
    mapping: MappingConfig = Field(default_factory=MappingConfig)
    perception: SimPerceptionConfig = Field(default_factory=SimPerceptionConfig)
    motion: MotionConfig = Field(default_factory=MotionConfig)
    base: Motion = Field(default="kinematic", description="kinematic: a primitive lands exactly; odrive, "
                         "kobuki, opencr: the base controller on that simulated base, in simulated time")
    latency: StepLatency = Field(default_factory=StepLatency, description="a step's cost besides its motion "
                                 "(the search time of a wheeled base)")
    frame_hz: float = Field(default=5.0, gt=0, description="continuous motion: the free-running camera's "
                            "frames that are perceived and fused (perception takes the newest)")

    @field_validator("policy")
    @classmethod
    def _known_policy(cls, name: str) -> str:
        planner_policy(name)
        return name


class EpisodeResult(BaseModel):
    """What the benchmark keeps of an episode (one JSONL line)."""

    episode_id: str
    policy: str
    scene_seed: int
    targets: tuple[str, ...]
    success: bool
    spl: float
    found: tuple[str, ...]          # targets whose STOP was correct
    steps: int
    path_m: float
    shortest_m: float
    state: str                      # the agent's view: done / failed
    reason: str = ""
    decisions: int
    blocked: int
    stops: list[StopRecord]
    trajectory: list[tuple[float, float, float]]
    believed: list[tuple[float, float, float]] | None = None  # where the robot thought it was at each
    # trajectory pose (odometry placed in the map): kept where odometry errs, with its errors
    odometry: TrajectoryErrors | None = None
    localization: dict[str, int] | None = None  # the map's localizer: matches by verdict
    funnel: list[TargetFunnel] = []  # per target: how far its search got (older files: none)
    search_s: float | None = None  # wheeled bases: simulated seconds from the first command to the last
    time_by_step: dict[str, float] | None = None  # wheeled bases: those seconds by kind of step (step_kind)
    seconds: float


@dataclass
class TaskRun:
    """One task's search on a world, and what the result keeps of it."""

    task: SearchTask
    agent: SearchAgent
    funnel: FunnelRecorder
    trajectory: list[tuple[float, float, float]]
    believed: list[tuple[float, float, float]]
    on_step: Callable[[int, Step], None] | None = None
    stops: list[StopRecord] = field(default_factory=list)
    time_by_step: Counter[str] = field(default_factory=Counter)  # wheeled bases: simulated s by step_kind

    def stop_at(self, world: EpisodeWorld, step: Step, true: Pose) -> None:
        """The ground truth's word on a STOP made at the true pose ``true``."""
        if step.goal is None or step.goal.label is None:
            return
        outcome = world.truth.stop(step.goal.label, true.x, true.y)  # where the robot really is
        self.stops.append(StopRecord(step=self.task.steps + 1, label=step.goal.label, x=true.x, y=true.y,
                                     success=outcome.success, distance_m=outcome.distance))

    def booked(self, world: EpisodeWorld, step: Step) -> None:
        """After the agent booked ``step``: where the robot now truly is, and the caller's hook."""
        p, b = world.robot.pose, world.pose()
        self.trajectory.append((p.x, p.y, p.yaw))
        self.believed.append((b.x, b.y, b.yaw))
        if self.on_step is not None:
            self.on_step(self.task.steps, step)


def scene_mapping(scene: Scene, base: MappingConfig | None = None) -> MappingConfig:
    """A map grid that covers the scene with a margin (:meth:`MappingConfig.covering`)."""
    return (base or MappingConfig()).covering(scene.width, scene.depth)


def episode_config(policy: str, base: EpisodeConfig | None = None) -> EpisodeConfig:
    """``base`` with the benchmark's policy ``policy`` set where the agent reads it: a planner
    policy, or an ablation (:data:`ovamos.bench.policies.ABLATIONS`): its planner policy and switches."""
    base = base or EpisodeConfig()
    planner, changes = planner_policy(policy)
    decision = base.agent.decision.model_copy(update={
        "policy": planner.name, "plus": base.agent.decision.plus.model_copy(update=changes)})
    agent = base.agent.model_copy(update={"decision": decision})
    return base.model_copy(update={"policy": policy, "agent": agent})


class EpisodeWorld:
    """What outlives a task, as in a deployment: the robot where it stands, its camera, the
    perception and the map (with every object it confirmed). :func:`run_task` runs one task on it;
    a second task on the same world is a user's repeated request."""

    def __init__(self, scene: Scene, truth: GroundTruth, config: EpisodeConfig, start: Pose,
                 prior: ObjectPrior | None = None) -> None:
        self.truth, self.config = truth, config
        self.perception = SimPerception(FrameLabels.of(scene), prior or ObjectPrior.load(), config.perception)
        self.state = MapState(scene_mapping(scene, config.mapping))
        self.robot, self.wheels = _robot(start, truth, config)
        self.renderer = SceneRenderer(scene, config.width, config.height)
        self.scene = scene
        self.clock = None if self.wheels is None else self.wheels.clock  # simulated time on a wheeled base
        self.seq = 0  # frames taken, over all tasks (stepwise: one per command)
        self.commands = 0  # commands sent, over all tasks
        self.blocked = 0  # commands that ended blocked, over all tasks
        self.keep_alive: PlanCommand | None = None  # continuous: the path command re-sent to the driver
        if self.wheels is not None and config.agent.motion == "continuous":
            self.wheels.clock.every(RESEND_S, self._resend)

    def _resend(self) -> None:
        if self.keep_alive is not None and self.wheels is not None:
            self.wheels.driver.submit(self.keep_alive)  # a duplicate: the driver's keep-alive

    def observe(self, search: TaskRun, stamp: float, after_action: int) -> MapSnapshot:
        """Frame :attr:`seq` (the caller counts it) from where the robot truly is, posed by its
        odometry (as a camera service poses it), perceived for the task's remaining targets and
        fused (where localization places it, when the map localizes).

        Every frame for the remaining targets, the first view too: the services map it before the
        task reaches perception, which then re-scores it for the task's targets, and the map adds
        those values (MapState.apply: a frame counts once), to the same map."""
        true, task = self.robot.pose, search.task
        frame = self.renderer.render(true.x, true.y, true.yaw, seq=self.seq, stamp=stamp, after_action=after_action,
                                     posed_at=frame_pose(self.robot, self.wheels))
        remaining = task.remaining
        detections = self.perception.detect(frame, remaining)
        search.funnel.frame(task.steps, frame, self.perception.visible_classes(frame), detections)
        self.state.apply(frame, PerceptionResult.build(frame.seq, frame.stamp, self.perception.score(frame, remaining),
                                                       detections, frame.depth.shape))
        snapshot = self.state.snapshot(frame.stamp, with_confidence=False)
        search.funnel.map(task.steps, snapshot.objects)
        return snapshot

    def command(self, action: Action | None = None, drive: PathStep | None = None) -> PlanCommand:
        """The next command: a primitive, or a path step (the planner's, in the map) in the base's
        odometry frame, as the planner service sends it."""
        self.commands += 1
        path = {} if drive is None else drive.in_odom(partial(to_odom, self.state.map_T_odom))
        return PlanCommand(action_id=self.commands, stamp=float(self.commands), action=action, **path)

    def odometry(self) -> Pose:
        """What the base's odometry says: the kinematic base's wheels, a wheeled base's driver."""
        return self.robot.odom if self.wheels is None else self.wheels.odometry()

    def pose(self) -> Pose:
        """Where the planner believes the robot is: its odometry placed in the map."""
        return self.state.map_T_odom.compose(self.odometry())

    def execute(self, action: Action) -> bool:
        """Run one primitive; False when a move was blocked (counted in :attr:`blocked`)."""
        if self.wheels is None:
            self.commands += 1
            done = self.robot.apply(action)
        else:
            done = self.wheels.run_command(self.command(action)) != "blocked"
        self.blocked += not done
        return done

    def close(self) -> None:
        if self.wheels is not None:
            self.wheels.stop()
        self.renderer.close()


def _robot(start: Pose, truth: GroundTruth, config: EpisodeConfig) -> tuple[SimRobot, SerialSimRobot | WheeledSimRobot | None]:
    """The true robot and, on a wheeled base, what moves it (started, enabled, in simulated time)."""
    robot = SimRobot(start, truth.is_free, base_motion(config.motion, config.base, DriverConfig()))
    if config.base == "kinematic":
        return robot, None
    wheels = wheeled(robot, config.base, clock=SimClock()).start()
    wheels.wait_ready()
    return robot, wheels


def odometry_seed(spec: EpisodeSpec) -> int:
    """The seed of an episode's odometry errors: its own, whatever else runs beside it."""
    return zlib.crc32(f"odometry {spec.episode_id} {spec.scene_seed}".encode())


def run_episode(spec: EpisodeSpec, scene: Scene, truth: GroundTruth, config: EpisodeConfig,
                prior: ObjectPrior | None = None,
                on_step: Callable[[int, Step], None] | None = None) -> EpisodeResult:
    """One episode: a fresh world (robot at ``spec.start``, empty map) and one task on it."""
    config = episode_config(config.policy, config)
    config = config.model_copy(update={"motion": config.motion.model_copy(update={"odometry_seed": odometry_seed(spec)})})
    world = EpisodeWorld(scene, truth, config, spec.start, prior)
    try:
        return run_task(world, spec, on_step)
    finally:
        world.close()


def run_task(world: EpisodeWorld, spec: EpisodeSpec,
             on_step: Callable[[int, Step], None] | None = None) -> EpisodeResult:
    """Search for ``spec.targets`` on ``world`` from where its robot stands (``spec.start`` must be
    that pose: the shortest tour, and so the SPL, is measured from it), stepwise or continuously as
    the agent's ``motion`` says."""
    started = time.perf_counter()
    config, truth, robot = world.config, world.truth, world.robot
    task = SearchTask(spec.episode_id, list(spec.targets), max_steps=spec.max_steps)
    believed = world.pose()
    search = TaskRun(task, SearchAgent(task, config.agent), FunnelRecorder(world.scene, spec.targets),
                     [(robot.pose.x, robot.pose.y, robot.pose.yaw)], [(believed.x, believed.y, believed.yaw)], on_step)
    distance0, blocked0 = robot.distance, world.blocked  # a later task's path and bumps are its own
    began = None if world.clock is None else world.clock()
    if config.agent.motion == "continuous":
        search_continuously(world, search)
        search_s = None if began is None else round(world.clock() - began, 2)
    else:
        _search_stepwise(world, search)
        # the last command is the last STOP when every target was found: each step's motion as
        # simulated, plus the time it stood for its frame, perception, fusion and decision
        search_s = None if began is None else round(world.clock() - began + task.steps * config.latency.total_s, 2)
    stops = search.stops
    found = tuple(s.label for s in stops if s.success)
    success = set(found) >= set(spec.targets)
    shortest = truth.shortest_tour((spec.start.x, spec.start.y), spec.targets)
    return EpisodeResult(
        episode_id=spec.episode_id, policy=config.policy, scene_seed=spec.scene_seed,
        targets=spec.targets, success=success, spl=spl(success, shortest, robot.distance - distance0),
        found=found, steps=task.steps, path_m=round(robot.distance - distance0, 4), shortest_m=round(shortest, 4),
        state=task.state.value, reason=task.reason, decisions=search.agent.decisions,
        blocked=world.blocked - blocked0, stops=stops, funnel=search.funnel.result(stops),
        trajectory=_rounded(search.trajectory), **_odometry(config, search, world.state.localizer),
        search_s=search_s, time_by_step=None if world.clock is None else
        {kind: round(t, 2) for kind, t in sorted(search.time_by_step.items())},
        seconds=round(time.perf_counter() - started, 3))


def _rounded(poses: list[tuple[float, float, float]]) -> list[tuple[float, float, float]]:
    return [(round(x, 4), round(y, 4), round(yaw, 4)) for x, y, yaw in poses]


def _odometry(config: EpisodeConfig, search: TaskRun, localizer: Localizer | None) -> dict[str, Any]:
    """Where odometry errs, the believed trajectory and its errors against the true one (evo's);
    with localization, its matches. Nothing otherwise: those lines stay as they were."""
    kept: dict[str, Any] = {}
    if not config.motion.odometry.ideal:  # else the believed trajectory is the true one
        kept.update(believed=_rounded(search.believed),
                    odometry=trajectory_errors(search.trajectory, search.believed))
    if localizer is not None:
        kept.update(localization=dict(sorted(localizer.counters.items())))
    return kept


def _search_stepwise(world: EpisodeWorld, search: TaskRun) -> None:
    """The lock-step loop: a primitive, the frame after it, perception, fusion, the next decision."""
    task, agent, robot = search.task, search.agent, world.robot
    while task.state is TaskStatus.SEARCHING:
        true, seq = robot.pose, world.seq
        # lock-step as in the services: frame seq follows command seq (seq commands done)
        snapshot = world.observe(search, stamp=float(seq), after_action=seq)
        assert snapshot.has_seen_after(seq), "the map must have fused the frame after the last command"
        pose = world.pose()  # in the map as this frame's localization left it
        step = agent.next_step(snapshot, pose)
        if step.action is None:
            break
        before, began = robot.distance, None if world.clock is None else world.clock()
        blocked = not world.execute(step.action)
        if began is not None and world.clock is not None:  # its motion, then its standing time
            search.time_by_step[step_kind(step)] += world.clock() - began + world.config.latency.total_s
        if step.reason is Reason.FOUND:
            search.stop_at(world, step, true)
        agent.executed(step, robot.distance - before, blocked, pose)
        search.booked(world, step)
        world.seq += 1
