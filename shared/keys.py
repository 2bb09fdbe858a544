"""Every Zenoh key expression the system uses, built in one place.

All keys live under ``ovamos/<robot_id>/`` so that several robots can share one
Zenoh network and a subscriber can select one robot (or all, with ``*``).
Services never write key strings themselves: a renamed key is a one-line change here.
"""

from __future__ import annotations

from typing import NamedTuple

ROOT = "ovamos"
ANY = "*"

# Characters with a meaning in Zenoh key expressions; an id containing one would
# silently widen or break a key.
_FORBIDDEN = set("/*$?#")


class KeyExprError(ValueError):
    """An id that cannot be a single key chunk, or a key that is not one of ours."""


def check_chunk(value: str, what: str) -> str:
    """Return ``value`` if it can be one chunk of a key expression, else raise."""
    if not value or value != value.strip() or _FORBIDDEN & set(value) or value.startswith("@"):
        raise KeyExprError(f"{what} {value!r} is not usable in a Zenoh key: it must be non-empty, "
                           f"without spaces around it, not start with '@' (a verbatim chunk, "
                           f"which '*' never matches) and without any of '/*$?#'")
    return value


def _robot(robot_id: str) -> str:
    if robot_id != ANY:
        check_chunk(robot_id, "robot id")
    return f"{ROOT}/{robot_id}"


def rgbd(robot_id: str) -> str:
    """RGB-D frames with intrinsics and camera pose (binary)."""
    return f"{_robot(robot_id)}/sensors/rgbd"


def camera_state(robot_id: str) -> str:
    """The camera service's health: streaming, or why not (JSON)."""
    return f"{_robot(robot_id)}/camera/state"


def odom(robot_id: str) -> str:
    return f"{_robot(robot_id)}/odom"


def perception_result(robot_id: str) -> str:
    return f"{_robot(robot_id)}/perception/result"


def map_snapshot(robot_id: str) -> str:
    """Published snapshots, and the queryable that answers on-demand snapshot requests."""
    return f"{_robot(robot_id)}/map/snapshot"


def plan_command(robot_id: str) -> str:
    return f"{_robot(robot_id)}/plan/command"


def unknown_targets(robot_id: str) -> str:
    """Perception's word on the robot's targets it can never see (JSON)."""
    return f"{_robot(robot_id)}/perception/unknown_targets"


def plan_trace(robot_id: str) -> str:
    """The planner's decision trace: options weighed and the goal chosen, per decision (JSON)."""
    return f"{_robot(robot_id)}/plan/trace"


def driver_state(robot_id: str) -> str:
    return f"{_robot(robot_id)}/driver/state"


def estop(robot_id: str) -> str:
    """Emergency stop requests that engage it, from any service, the gateway or a person's
    handheld tool (the secure routers let an ``operator`` certificate put here and nothing else)."""
    return f"{_robot(robot_id)}/driver/estop"


def estop_clear(robot_id: str) -> str:
    """Requests that clear a latched e-stop: a key of its own, so the access control can let the
    laptop (the gateway's confirmed clear) release the robot while an e-stop-only credential cannot."""
    return f"{_robot(robot_id)}/driver/estop/clear"


def task_current(robot_id: str) -> str:
    return f"{_robot(robot_id)}/task/current"


def task_events(robot_id: str) -> str:
    return f"{_robot(robot_id)}/task/events"


def _service_key(kind: str, robot_id: str, service: str, instance: str) -> str:
    parts = [_robot(robot_id), kind]
    for value, what in ((service, "service"), (instance, "instance")):
        parts.append(value if value == ANY else check_chunk(value, what))
    return "/".join(parts)


def alive(robot_id: str, service: str = ANY, instance: str = ANY) -> str:
    """Liveliness token of one service instance, or a selector over many with ``*``."""
    return _service_key("alive", robot_id, service, instance)


def ready(robot_id: str, service: str = ANY, instance: str = ANY) -> str:
    """Liveliness token of an instance that has finished starting (its models loaded): replicas
    share work among the ready ones, so a loading replica is not handed frames it cannot take."""
    return _service_key("ready", robot_id, service, instance)


def stats(robot_id: str, service: str = ANY, instance: str = ANY) -> str:
    """Queryable answering a service instance's message counters (for ``ovamos status``)."""
    return _service_key("stats", robot_id, service, instance)


def bench(robot_id: str, name: str) -> str:
    """Keys private to benchmarks (``ovamos bench``), kept apart from the system's."""
    return f"{_robot(robot_id)}/bench/{check_chunk(name, 'bench key')}"


def robot_all(robot_id: str) -> str:
    """Every key of one robot (used by the monitor)."""
    return f"{_robot(robot_id)}/**"


def robot_of(key: str) -> str:
    """The robot id of one of our keys (``ovamos/<robot_id>/...``)."""
    parts = str(key).split("/")
    if len(parts) < 3 or parts[0] != ROOT:
        raise KeyExprError(f"not an ovamos key: {key!r}")
    return parts[1]


class ServiceKey(NamedTuple):
    robot_id: str
    service: str
    instance: str


def parse_service_key(key: str) -> ServiceKey:
    """Split an ``alive``, ``ready`` or ``stats`` key back into its robot, service and instance."""
    parts = str(key).split("/")
    if len(parts) != 5 or parts[0] != ROOT or parts[2] not in ("alive", "ready", "stats"):
        raise KeyExprError(f"not an ovamos alive/ready/stats key: {key!r}")
    return ServiceKey(parts[1], parts[3], parts[4])
