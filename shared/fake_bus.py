"""A fake bus: services' adapters wired in one process with no Zenoh, for tests.

NOT Zenoh and not a mock of it: a :class:`FakeNetwork` routes the bytes a
:class:`FakeBus` publishes to every subscription whose key expression
matches (``*`` one chunk, ``**`` any number), queries to queryables and
liveliness tokens to their watchers (with history, as Zenoh's), through the same :class:`~ovamos.shared.bus.BusCore` as the real bus. So messages are
encoded, validated and counted exactly as in production, handlers run from
each bus's inbox, and a test decides when they run (:meth:`FakeNetwork.pump`),
which makes the adapter's logic testable step by step without a router. The
real multi-process tests keep covering the Zenoh wiring itself.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from ovamos.shared.bus import BusCore

__all__ = ["FakeNetwork", "FakeBus", "key_matches"]

Reply = Callable[[bytes | bytearray], None]


def key_matches(expr: str, key: str) -> bool:
    """Whether the concrete ``key`` is in the key expression ``expr`` (``*`` and ``**`` only)."""
    def match(e: list[str], k: list[str]) -> bool:
        if not e:
            return not k
        if e[0] == "**":
            return any(match(e[1:], k[i:]) for i in range(len(k) + 1))
        return bool(k) and (e[0] == "*" or e[0] == k[0]) and match(e[1:], k[1:])
    return match(expr.split("/"), key.split("/"))


class FakeNetwork:
    """The buses of one test and what each declared."""

    def __init__(self) -> None:
        self.buses: list[FakeBus] = []
        self.tokens: list[str] = []
        self._watchers: list[tuple[str, Callable[[str, bool], None]]] = []
        self._subs: list[tuple[str, Callable[[str, Callable[[], bytes]], None]]] = []
        self._queryables: list[tuple[str, Callable[[Reply, Callable[[], None]], None]]] = []
        #: (service, kind, key) of every publisher, subscription, queryable and query declared or
        #: made: kind is the topology's (``outputs``, ``inputs``, ``answers``, ``queries``)
        self.used: set[tuple[str, str, str]] = set()

    def bus(self, robot_id: str, service: str, instance: str = "0") -> FakeBus:
        bus = FakeBus(self, robot_id, service, instance)
        self.buses.append(bus)
        return bus

    def pump(self, max_events: int = 100_000) -> int:
        """Run every bus's queued events, and those they cause, until all inboxes are empty."""
        ran = 0
        while ran < max_events:
            step = sum(bus.inbox.run_pending() for bus in self.buses)
            if step == 0:
                return ran
            ran += step
        raise RuntimeError(f"still busy after {max_events} events: a message loop between services?")

    def _announce(self, key: str, alive: bool) -> None:
        for expr, on_change in list(self._watchers):
            if key_matches(expr, key):
                on_change(key, alive)

    def _deliver(self, key: str, payload: bytes) -> None:
        for expr, on_payload in list(self._subs):
            if key_matches(expr, key):
                on_payload(key, lambda: payload)

    def _remove(self, table: list[Any], entry: Any) -> Callable[[], None]:
        def undeclare() -> None:
            if entry in table:
                table.remove(entry)
        return undeclare


class FakeBus(BusCore):
    """A bus on a :class:`FakeNetwork`; events run only when the test pumps the network."""

    def __init__(self, network: FakeNetwork, robot_id: str, service: str, instance: str) -> None:
        super().__init__(robot_id, service, instance)
        self.network = network

    def _publish(self, key: str, block: bool = False
                 ) -> tuple[Callable[[bytes | bytearray], None], Callable[[], None]]:
        self.network.used.add((self.service, "outputs", key))
        return (lambda payload: self.network._deliver(key, bytes(payload))), (lambda: None)

    def _listen(self, key_expr: str, on_payload: Callable[[str, Callable[[], bytes]], None]
                ) -> Callable[[], None]:
        self.network.used.add((self.service, "inputs", key_expr))
        entry = (key_expr, on_payload)
        self.network._subs.append(entry)
        return self.network._remove(self.network._subs, entry)

    def _answer(self, key: str, on_query: Callable[[Reply, Callable[[], None]], None]
                ) -> Callable[[], None]:
        self.network.used.add((self.service, "answers", key))
        entry = (key, on_query)
        self.network._queryables.append(entry)
        return self.network._remove(self.network._queryables, entry)

    def _ask(self, key: str, timeout_s: float, on_reply: Callable[[bytes], None],
             on_done: Callable[[], None]) -> None:
        """Every matching queryable answers when its bus is pumped; ``timeout_s`` is not simulated:
        the request ends when all have answered (at once when there is none)."""
        self.network.used.add((self.service, "queries", key))
        targets = [q for expr, q in self.network._queryables if key_matches(expr, key)]
        waiting = len(targets)
        if waiting == 0:
            on_done()
            return

        def finish() -> None:
            nonlocal waiting
            waiting -= 1
            if waiting == 0:
                on_done()

        for on_query in targets:
            on_query(lambda payload: on_reply(bytes(payload)), finish)

    def _token(self, key: str) -> Callable[[], None]:
        self.network.tokens.append(key)
        self.network._announce(key, True)

        def undeclare() -> None:
            if key in self.network.tokens:
                self.network.tokens.remove(key)
                self.network._announce(key, False)
        return undeclare

    def _watch_tokens(self, key_expr: str, on_change: Callable[[str, bool], None]) -> Callable[[], None]:
        for key in self.network.tokens:  # history, as Zenoh's liveliness subscriber gives
            if key_matches(key_expr, key):
                on_change(key, True)
        entry = (key_expr, on_change)
        self.network._watchers.append(entry)
        return self.network._remove(self.network._watchers, entry)
