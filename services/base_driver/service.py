"""The base driver service: ``plan/command``, ``driver/estop`` and ``driver/estop/clear`` in, ``odom`` and ``driver/state`` out.

A thin adapter over a *base* (the :class:`~ovamos.services.base_driver.controller.BaseController`
over the hardware interface ``driver.hardware`` names here, the simulated robot in
``ovamos.services.sim.service``): commands go to it as they
arrive (it executes an action id once, so the planner may re-send), and the
tick publishes odometry at ``odom_hz`` and the driver state at ``state_hz`` and
whenever it changes (odometry first, so a planner that sees a command completed
already has the pose it ended at).

It follows the planner's liveliness: once every planner token it saw is gone
(the link to the laptop is down, or the planner died), ``driver/state`` says
"planner unreachable" in its ``warnings`` until one is back.

An e-stop is engaged on ``driver/estop`` and released only on ``driver/estop/clear``: the
secure routers let a handheld e-stop credential (CN ``operator``) put on the first key alone,
so releasing the robot needs the laptop's. A clear sent on the engage key is refused and
counted (malformed, on its key), whoever sent it. The wheels do not
wait for that (a token is declared lost only after the link's lease, ~3 s): a
velocity command stops after ``deadman_s`` without renewal, and with
``driver.command_timeout_s`` a primitive stops too once the planner's copies of
it (its keep-alive) stop coming.

``simulated_axes`` runs simulated ODrives on the ``odrive_can`` hardware's virtual CAN
channel in this process: the whole driver, CAN frames included, without hardware.
"""

from __future__ import annotations

import time
from typing import Any, Protocol

from ovamos.services.base_driver.config import BaseDriverServiceConfig, DriverConfig, PublishingConfig
from ovamos.services.base_driver.controller import BaseController
from ovamos.services.base_driver.odrive.client import ODriveCanHardware
from ovamos.services.base_driver.odrive.config import SimAxisConfig
from ovamos.services.base_driver.odrive.sim import SimODrives
from ovamos.shared import keys
from ovamos.shared.bus import BusCore
from ovamos.shared.messages import DriverMode, DriverState, EStop, Odometry, PlanCommand
from ovamos.shared.service import Service

PLANNER_UNREACHABLE = "planner unreachable"


class Base(Protocol):
    """What the service needs of whatever moves the robot."""

    odom_session: str  # new when its odometry integration starts (see ovamos.shared.messages.OdomSession)

    def submit(self, command: PlanCommand) -> str: ...
    def engage_estop(self, source: str, reason: str = "") -> None: ...
    def clear_estop(self, source: str) -> None: ...
    def state(self) -> DriverState: ...
    def odometry(self) -> Odometry: ...
    @property
    def has_pose(self) -> bool: ...  # False: no odometry is published (nothing reported yet)
    def info(self) -> dict[str, object]: ...
    def stop(self) -> None: ...


class _SimulatedAxesDriver(BaseController):
    """The real driver plus simulated ODrives on its virtual channel, started and stopped together."""

    def __init__(self, config: DriverConfig, axes: SimAxisConfig) -> None:
        od = config.odrive
        self.odrives = SimODrives([od.left.node_id, od.right.node_id], od.can.channel, axes)
        super().__init__(config, ODriveCanHardware(config, self.odrives.open_driver_bus))

    def start(self) -> BaseController:
        self.odrives.start()
        return super().start()

    def stop(self) -> None:
        super().stop()
        self.odrives.stop()


class BaseDriverService(Service):
    name = "base_driver"
    Config = BaseDriverServiceConfig
    config: PublishingConfig

    def __init__(self, bus: BusCore, config: PublishingConfig) -> None:
        super().__init__(bus, config)
        self.tick_hz = config.tick_hz
        self._last_state: DriverState | None = None
        self._state_at = self._odom_at = -float("inf")
        self._planners: set[str] = set()   # live planner tokens
        self._planner_seen = False

    def make_base(self) -> Base:
        config = self.config
        assert isinstance(config, BaseDriverServiceConfig)
        if config.simulated_axes:
            return _SimulatedAxesDriver(config.driver, config.sim_axes).start()
        return BaseController(config.driver).start()

    def start(self) -> None:
        self.base = self.make_base()
        self.wire({"plan_command": self._on_command, "estop": self._on_estop,
                   "estop_clear": self._on_estop_clear})
        self.bus.watch_liveliness(keys.alive(self.bus.robot_id, "planner"), self._on_planner_token)

    def _on_planner_token(self, key: str, alive: bool) -> None:
        was = self.planner_unreachable
        (self._planners.add if alive else self._planners.discard)(key)
        self._planner_seen = self._planner_seen or alive
        if self.planner_unreachable != was:
            if self.planner_unreachable:
                self.log.warning("planner unreachable: %s gone (the link to the laptop is down, or the "
                                 "planner stopped)", key)
            else:
                self.log.info("planner reachable again (%s)", ", ".join(sorted(self._planners)))

    @property
    def planner_unreachable(self) -> bool:
        """A planner was alive and none is now."""
        return self._planner_seen and not self._planners

    def _on_command(self, command: PlanCommand) -> None:
        outcome = self.base.submit(command)
        if outcome != "duplicate":
            self.log.info("command %d (%s): %s", command.action_id, command.kind, outcome)

    def _on_estop(self, msg: EStop) -> None:
        if msg.engage:
            self.base.engage_estop(msg.source, msg.reason)
        else:
            self._refuse_estop(keys.estop(self.bus.robot_id), msg,
                               "a clear on driver/estop (clearing is on driver/estop/clear)")

    def _on_estop_clear(self, msg: EStop) -> None:
        if msg.engage:
            self._refuse_estop(keys.estop_clear(self.bus.robot_id), msg,
                               "an engage on driver/estop/clear (engaging is on driver/estop)")
        else:
            self.base.clear_estop(msg.source)

    def _refuse_estop(self, key: str, msg: EStop, what: str) -> None:
        """A request on the wrong key: counted as malformed on it and logged, the latch left as it is."""
        self.bus.counters.bump(key, "malformed")
        self.log.warning("e-stop request from %r refused: %s", msg.source, what)

    def tick(self) -> None:
        self.publish(self.base.state())

    def publish(self, state: DriverState) -> None:
        """Odometry at its rate, once the base has reported a pose; the state at its rate and
        whenever it changed (odometry first)."""
        if self.planner_unreachable:
            state = state.model_copy(update={"warnings": (*state.warnings, PLANNER_UNREACHABLE)})
        now = time.monotonic()
        changed = self._last_state is None or _content(state) != _content(self._last_state)
        state_due = changed or now - self._state_at >= 1.0 / self.config.state_hz
        if (state_due or now - self._odom_at >= 1.0 / self.config.odom_hz) and self.base.has_pose:
            self.out["odom"].put(self.base.odometry())
            self._odom_at = now
        if state_due:
            self.out["driver_state"].put(state)
            self._last_state, self._state_at = state, now

    def info(self) -> dict[str, Any]:
        info = dict(self.base.info()) if hasattr(self, "base") else {}
        info["planner_reachable"] = not self.planner_unreachable
        return info

    def stop(self) -> None:
        """Say the driver goes off on purpose, then release the base: the planner then takes the
        token's loss that follows for a shutdown, not for a lost link."""
        if hasattr(self, "base"):
            self.out["driver_state"].put(self.base.state().model_copy(update={"mode": DriverMode.OFF}))
            self.release()

    def release(self) -> None:
        """Release what moves the robot."""
        self.base.stop()


def _content(state: DriverState) -> dict[str, Any]:
    return state.model_dump(exclude={"stamp"})
