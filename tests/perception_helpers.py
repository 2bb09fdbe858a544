"""Shared pieces of the perception tests: rendered frames, services run in threads, and a fake
bus with liveliness tokens."""

from __future__ import annotations

import math
import threading
from collections.abc import Callable

from services.perception.config import PerceptionServiceConfig
from services.perception.service import PerceptionService
from services.sim.render import SceneRenderer
from shared.bus import Subscription
from shared.fake_bus import FakeBus, FakeNetwork, key_matches
from shared.messages import RgbdFrame
from shared.service import run_service
from shared.zconfig import build_config
from tests.sim_scenes import two_rooms

ROBOT = "r1"


def render_frames(count: int, width: int = 160, height: int = 120) -> list[RgbdFrame]:
    """Frames from the kitchen of :func:`two_rooms`, turning from the fridge (west) round."""
    with SceneRenderer(two_rooms(), width, height) as renderer:
        return [renderer.render(1.5, 3.0, math.pi + i * math.pi / 4, seq=i, stamp=float(i))
                for i in range(count)]


class RunningPerception:
    """A perception service instance on its own Zenoh session, in a thread of this process."""

    def __init__(self, endpoint: str, config: PerceptionServiceConfig, instance: str = "0") -> None:
        self.stop = threading.Event()
        self.thread = threading.Thread(target=run_service, args=(
            PerceptionService, build_config(connect=[endpoint]), config),
            kwargs={"robot_id": ROBOT, "instance": instance, "stop": self.stop})
        self.thread.start()

    def close(self) -> None:
        self.stop.set()
        self.thread.join(30)
        assert not self.thread.is_alive()


class LivelyNetwork(FakeNetwork):
    """A :class:`FakeNetwork` whose buses also have liveliness tokens (replica membership).

    Like Zenoh's: a watcher hears of the tokens declared before it (history) and
    of every later declaration and withdrawal, through its bus's inbox.
    """

    def __init__(self) -> None:
        super().__init__()
        self.tokens: list[str] = []
        self.watchers: list[tuple[str, LivelyFakeBus, Callable[[str, bool], None]]] = []

    def bus(self, robot_id: str, service: str, instance: str = "0") -> LivelyFakeBus:
        bus = LivelyFakeBus(self, robot_id, service, instance)
        self.buses.append(bus)
        return bus

    def _announce(self, key: str, alive: bool) -> None:
        for expr, bus, handler in list(self.watchers):
            if key_matches(expr, key):
                bus._tell(expr, handler, key, alive)


class LivelyFakeBus(FakeBus):
    """A :class:`FakeBus` with :meth:`watch_liveliness` and :meth:`declare_token`, as on the real bus."""

    network: LivelyNetwork

    def _tell(self, expr: str, handler: Callable[[str, bool], None], key: str, alive: bool) -> None:
        self.inbox.put(self._guard(lambda _: handler(key, alive), expr), None)

    def watch_liveliness(self, key_expr: str, handler: Callable[[str, bool], None]) -> None:
        entry = (key_expr, self, handler)
        for key in self.network.tokens:
            if key_matches(key_expr, key):
                self._tell(key_expr, handler, key, True)
        self.network.watchers.append(entry)
        self._declared.append(Subscription(self.network._remove(self.network.watchers, entry)))

    def declare_token(self, key: str) -> Subscription:
        self.network.tokens.append(key)
        self.network._announce(key, True)

        def undeclare() -> None:
            if key in self.network.tokens:
                self.network.tokens.remove(key)
                self.network._announce(key, False)

        handle = Subscription(undeclare)
        self._declared.append(handle)
        return handle
