"""Where a DDS process (rclpy, any ROS 2 library) may start on a development machine, and how to
get it there.

DDS finds its peers by multicast on every interface. On a shared machine that reaches whoever
else runs ROS 2 (and their robots). So every process of ours that loads DDS for tests, CI or the
demo runs in a network namespace holding nothing but loopback, with Fast DDS held to 127.0.0.1
by a profile without multicast (:data:`LOOPBACK_PROFILE`) and ROS's discovery range at
``LOCALHOST``: :func:`check_loopback_only` refuses anything else, before rclpy is imported, and
``python -m ovamos.shared.dds -- CMD ...`` runs ``CMD`` in such a namespace (its own ``/dev/shm`` too:
a killed DDS process leaves its shared-memory segments behind).

Both environment variables are set: Jazzy's Fast DDS 2.x reads ``FASTRTPS_DEFAULT_PROFILES_FILE``,
3.x ``FASTDDS_DEFAULT_PROFILES_FILE``; a profile Fast DDS cannot parse is only a warning to it
(it then goes on with multicast defaults), hence the check parses it here first.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import xml.etree.ElementTree as ET
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import NoReturn

from ovamos.shared.deploy import DEPLOY_DIR

__all__ = ["DdsNetworkError", "LOOPBACK_PROFILE", "PROFILE_VARS", "check_loopback_only", "loopback_env",
           "in_own_namespace", "rerun_in_loopback_namespace"]

LOOPBACK_PROFILE = DEPLOY_DIR / "ros2" / "fastdds-loopback.xml"
PROFILE_VARS = ("FASTRTPS_DEFAULT_PROFILES_FILE", "FASTDDS_DEFAULT_PROFILES_FILE")
RANGE_VAR = "ROS_AUTOMATIC_DISCOVERY_RANGE"
_CLEARED = ("ROS_STATIC_PEERS", "ROS_DISCOVERY_SERVER", "ROS_LOCALHOST_ONLY")  # would widen discovery
_NS = "{http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles}"


class DdsNetworkError(RuntimeError):
    """DDS may not start here: the namespace or the Fast DDS setup could reach beyond loopback."""


def check_loopback_only(environ: Mapping[str, str] = os.environ, interfaces: Sequence[str] | None = None) -> None:
    """Raise :class:`DdsNetworkError` unless this process may load DDS: the network namespace has
    no interface but ``lo``, both profile variables name a profile that holds Fast DDS to 127.0.0.1
    without multicast, and the discovery range is ``LOCALHOST``."""
    names = sorted(name for _, name in socket.if_nameindex()) if interfaces is None else sorted(interfaces)
    if names != ["lo"]:
        raise DdsNetworkError(
            f"refusing to start DDS: this network namespace has {', '.join(names)}, not only lo; DDS "
            "discovers by multicast on every interface. Run it with `python -m ovamos.shared.dds -- COMMAND`")
    for var in PROFILE_VARS:
        if not environ.get(var):
            raise DdsNetworkError(f"refusing to start DDS: {var} is not set (the loopback profile: {LOOPBACK_PROFILE})")
        _check_profile(Path(environ[var]), var)
    if environ.get(RANGE_VAR) != "LOCALHOST":
        raise DdsNetworkError(f"refusing to start DDS: {RANGE_VAR} is {environ.get(RANGE_VAR)!r}, not 'LOCALHOST'")
    for var in _CLEARED:
        if environ.get(var):
            raise DdsNetworkError(f"refusing to start DDS: {var} is set ({environ[var]!r}), which widens discovery")


def _check_profile(path: Path, var: str) -> None:
    """The profile parses, every address in it is 127.0.0.1, it has no multicast locator, and the
    built-in transports (which bind every interface) are off."""
    try:
        root = ET.parse(path).getroot()
    except (OSError, ET.ParseError) as exc:
        raise DdsNetworkError(f"refusing to start DDS: {var}={path} cannot be read as a profile: {exc}") from None
    where = f"{var}={path}"
    addresses = [el.text.strip() for el in root.iter(f"{_NS}address") if el.text]
    if not addresses or set(addresses) != {"127.0.0.1"}:
        raise DdsNetworkError(f"refusing to start DDS: {where} names addresses {addresses}, not only 127.0.0.1")
    if any("ulticast" in el.tag for el in root.iter()):
        raise DdsNetworkError(f"refusing to start DDS: {where} has a multicast setting")
    builtin = [el.text.strip().lower() for el in root.iter(f"{_NS}useBuiltinTransports") if el.text]
    if builtin != ["false"]:
        raise DdsNetworkError(f"refusing to start DDS: {where} does not turn the built-in transports off "
                              "(useBuiltinTransports false): they bind every interface")


def loopback_env(environ: Mapping[str, str] = os.environ, profile: Path = LOOPBACK_PROFILE) -> dict[str, str]:
    """``environ`` with the loopback profile and discovery range set and the widening variables
    removed: what a DDS process in a loopback-only namespace runs with."""
    env = {k: v for k, v in environ.items() if k not in _CLEARED}
    env.update({var: str(profile) for var in PROFILE_VARS})
    env[RANGE_VAR] = "LOCALHOST"
    env["RMW_IMPLEMENTATION"] = "rmw_fastrtps_cpp"
    return env


_INSIDE = "OVAMOS_DDS_NAMESPACE"  # set by main() once it runs in the namespace it made


def in_own_namespace() -> bool:
    """Whether this process runs in a namespace that ``python -m ovamos.shared.dds`` made."""
    return os.environ.get(_INSIDE) == "1"


def rerun_in_loopback_namespace(command: Sequence[str]) -> NoReturn:
    """Replace this process with ``python -m ovamos.shared.dds -- COMMAND``: ``command`` again, in a
    loopback-only namespace (for a command that finds itself where DDS may not start)."""
    os.execv(sys.executable, [sys.executable, "-m", "ovamos.shared.dds", "--", *command])


def main(argv: Sequence[str]) -> int:
    """``python -m ovamos.shared.dds -- COMMAND ...``: COMMAND in a new loopback-only network namespace
    (``unshare``: root, or user namespaces), with a private ``/dev/shm`` and the loopback env."""
    command = list(argv[1:] if argv[:1] == ["--"] else argv)
    if not command:
        print("usage: python -m ovamos.shared.dds -- COMMAND [ARG ...]", file=sys.stderr)
        return 2
    if not in_own_namespace():
        unshare = ["unshare", "--net", "--mount", "--propagation", "private", "--",
                   sys.executable, "-m", "ovamos.shared.dds", "--", *command]
        try:
            child = subprocess.Popen(unshare, env={**os.environ, _INSIDE: "1"})
        except OSError as exc:
            print(f"cannot run unshare: {exc}", file=sys.stderr)
            return 2
        for sig in (signal.SIGTERM, signal.SIGHUP):  # the command's to handle
            signal.signal(sig, lambda number, _frame: child.send_signal(number))
        signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C reaches the command itself (same group)
        return child.wait()
    for step in (["ip", "link", "set", "lo", "up"], ["mount", "-t", "tmpfs", "ovamos-dds-shm", "/dev/shm"]):
        done = subprocess.run(step, capture_output=True, text=True)
        if done.returncode != 0:
            print(f"{' '.join(step)} failed: {done.stderr.strip()}", file=sys.stderr)
            return 2
    env = loopback_env()
    try:
        check_loopback_only(env)
    except DdsNetworkError as exc:
        print(exc, file=sys.stderr)
        return 3
    os.execvpe(command[0], command, env)


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
