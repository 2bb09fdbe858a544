"""Hosts as Linux network namespaces for the laptop + robot tests (real TCP between two stacks).

Three namespaces, ``laptop``, ``robot`` and ``intruder``, joined pairwise by veth pairs whose ends
have addresses in 127.0.0.0/8 with ``route_localnet`` on (docs/design.md, "Deployment and Zenoh": no address outside
the loopback range is ever used). Each namespace also has its own ``lo``, so both hosts' routers
keep their shipped loopback ports. :meth:`Hosts.cut` / :meth:`Hosts.restore` take the laptop-robot
link down and up (``ip link set``). Everything is removed by :meth:`Hosts.destroy`, which the
fixtures call in a ``finally``.
"""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Sequence
from dataclasses import dataclass, field

# (namespace a, address a, namespace b, address b) per veth pair
LINKS = {
    "lr": ("laptop", "127.100.0.1", "robot", "127.100.0.2"),       # the robot network
    "ir": ("intruder", "127.100.1.1", "robot", "127.100.1.2"),     # an intruder near the robot
    "il": ("intruder", "127.100.2.1", "laptop", "127.100.2.2"),    # ... and near the laptop
}


def _ip(*args: str, check: bool = True) -> subprocess.CompletedProcess:
    return subprocess.run(["ip", *args], capture_output=True, text=True, timeout=30, check=check)


def unavailable_reason() -> str | None:
    """Why network namespaces cannot be made here (None when they can)."""
    if sys.platform != "linux":
        return "network namespaces are a Linux feature"
    name = f"ovamos-probe-{os.getpid()}"
    try:
        done = _ip("netns", "add", name, check=False)
    except (OSError, subprocess.SubprocessError) as exc:
        return f"cannot run `ip netns add`: {exc}"
    if done.returncode != 0:
        return f"`ip netns add` failed (root and CAP_SYS_ADMIN are needed): {done.stderr.strip()}"
    _ip("netns", "del", name, check=False)
    return None


@dataclass
class Hosts:
    prefix: str
    names: dict[str, str] = field(default_factory=dict)   # role -> namespace
    veths: dict[str, tuple[str, str]] = field(default_factory=dict)  # link -> (end in a, end in b)

    @classmethod
    def create(cls, prefix: str) -> Hosts:
        hosts = cls(prefix)
        try:
            hosts._create()
        except BaseException:
            hosts.destroy()
            raise
        return hosts

    def _create(self) -> None:
        for role in ("laptop", "robot", "intruder"):
            ns = self.names[role] = f"{self.prefix}-{role}"
            _ip("netns", "add", ns)
            self.sysctl(role, "net.ipv4.conf.all.route_localnet=1", "net.ipv4.conf.default.route_localnet=1")
            _ip("-n", ns, "link", "set", "lo", "up")
        tag = self.prefix[-6:]
        for link, (a, addr_a, b, addr_b) in LINKS.items():
            end_a, end_b = f"{link}a{tag}", f"{link}b{tag}"  # <= 15 characters, unique per run
            _ip("link", "add", end_a, "type", "veth", "peer", "name", end_b)
            self.veths[link] = (end_a, end_b)
            for role, end, addr in ((a, end_a, addr_a), (b, end_b, addr_b)):
                _ip("link", "set", end, "netns", self.names[role])
                self.sysctl(role, f"net.ipv4.conf.{end}.route_localnet=1")
                _ip("-n", self.names[role], "addr", "add", f"{addr}/24", "dev", end)
                _ip("-n", self.names[role], "link", "set", end, "up")

    def sysctl(self, role: str, *settings: str) -> None:
        subprocess.run(["ip", "netns", "exec", self.names[role], "sysctl", "-q", "-w", *settings],
                       check=True, capture_output=True, timeout=30)

    def argv(self, role: str, argv: Sequence[str]) -> list[str]:
        """``argv`` run inside ``role``'s namespace."""
        return ["ip", "netns", "exec", self.names[role], *argv]

    def _link(self, up: bool) -> None:
        end = self.veths["lr"][0]
        _ip("-n", self.names["laptop"], "link", "set", end, "up" if up else "down")

    def cut(self) -> None:
        """Take the laptop-robot link down (both ends lose carrier)."""
        self._link(False)

    def restore(self) -> None:
        self._link(True)

    def destroy(self) -> None:
        """Delete the namespaces (their veth ends go with them); never raises."""
        for ns in self.names.values():
            try:
                _ip("netns", "del", ns, check=False)
            except (OSError, subprocess.SubprocessError):
                pass
