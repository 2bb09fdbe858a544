"""Key expressions: one robot's keys stay under ``ovamos/<robot_id>/``, and ids cannot widen them.

An id with a Zenoh wildcard or separator in it would make a publisher or a
subscriber silently cover other robots' keys, so ids are checked where keys
are built. Zenoh itself is the judge of what a key matches.
"""

from __future__ import annotations

from collections.abc import Callable

import pytest
import zenoh
from hypothesis import given, settings
from hypothesis import strategies as st

from ovamos.shared import keys
from ovamos.shared.keys import KeyExprError, ServiceKey, parse_service_key

SETTINGS = settings(max_examples=50, deadline=None)

ROBOT_KEYS: list[Callable[[str], str]] = [
    keys.rgbd, keys.odom, keys.perception_result, keys.map_snapshot, keys.plan_command,
    keys.driver_state, keys.task_current, keys.task_events, keys.robot_all,
    lambda r: keys.alive(r, "svc", "i0"), lambda r: keys.ready(r, "svc", "i0"),
    lambda r: keys.stats(r, "svc", "i0"), lambda r: keys.bench(r, "echo"),
]
ROBOT_KEY_IDS = ["rgbd", "odom", "perception_result", "map_snapshot", "plan_command", "driver_state",
                 "task_current", "task_events", "robot_all", "alive", "ready", "stats",
                 "bench"]

# A bare '*' is not here: it is the documented "every robot" selector (keys.rgbd("*")).
# '@x' is a Zenoh verbatim chunk, which '*' never matches: such an id would hide its keys.
BAD_IDS = ["", "a/b", "/a", "a/", "**", "a*", "*a", "@x", "@", "$", "a$*", "?", "a?b", "#", "a#b", " a", "a ", " ",
           "\ta", "a\n"]

# Ids that must be accepted: a single chunk without Zenoh syntax and without surrounding spaces.
# Left out here: '@'-prefixed ids (refused, see BAD_IDS) and the robot id "alive"
# (a known bug, see test_stats_key_of_a_robot_named_alive).
good_ids = st.text(st.characters(blacklist_categories=("Cs", "Cc", "Zs", "Zl", "Zp"),
                                 blacklist_characters="/*$?#"),
                   min_size=1, max_size=12).filter(
    lambda s: s == s.strip() and not s.startswith("@") and s != "alive")


def ke(key: str) -> zenoh.KeyExpr:
    return zenoh.KeyExpr(key)


@pytest.mark.parametrize("build", ROBOT_KEYS, ids=ROBOT_KEY_IDS)
def test_every_key_lives_under_the_robot_prefix(build: Callable[[str], str]) -> None:
    key = build("r1")
    assert key.startswith("ovamos/r1/")
    ke(key)  # a valid Zenoh key expression


@pytest.mark.parametrize("build", ROBOT_KEYS, ids=ROBOT_KEY_IDS)
@pytest.mark.parametrize("bad", BAD_IDS, ids=repr)
def test_bad_robot_ids_are_refused(build: Callable[[str], str], bad: str) -> None:
    with pytest.raises(KeyExprError):
        build(bad)


def test_keys_of_different_topics_are_distinct() -> None:
    """Two topics sharing a key would mix message types on one stream."""
    built = [build("r1") for build in ROBOT_KEYS]
    assert len(set(built)) == len(built)
    topics = [k for k, name in zip(built, ROBOT_KEY_IDS) if name != "robot_all"]
    for a in topics:
        for b in topics:
            if a != b:
                assert not ke(a).intersects(ke(b)), (a, b)


@SETTINGS
@given(good_ids, good_ids)
def test_a_robot_sees_only_its_own_keys(robot: str, other: str) -> None:
    """robot_all(r) covers every key of r and none of another robot's."""
    everything = ke(keys.robot_all(robot))
    for build in ROBOT_KEYS:
        key = build(robot)
        assert key.startswith(f"ovamos/{robot}/")
        assert everything.includes(ke(key))
        if other != robot:
            assert not everything.intersects(ke(build(other)))


@SETTINGS
@given(good_ids, good_ids, good_ids)
def test_wildcard_selectors_match_every_instance(robot: str, service: str, instance: str) -> None:
    """``ovamos status`` finds every instance with the default '*' selectors."""
    alive, stats = keys.alive(robot, service, instance), keys.stats(robot, service, instance)
    for selector in (keys.alive(robot), keys.alive("*"), keys.alive(robot, service), keys.alive("*", service)):
        assert ke(selector).includes(ke(alive))
        assert not ke(selector).intersects(ke(stats))
    for selector in (keys.stats(robot), keys.stats("*"), keys.stats(robot, service)):
        assert ke(selector).includes(ke(stats))
        assert not ke(selector).intersects(ke(alive))


def test_selectors_with_wildcards() -> None:
    assert keys.alive("r1") == "ovamos/r1/alive/*/*"
    assert keys.alive("*") == "ovamos/*/alive/*/*"
    assert keys.alive("r1", "mapping") == "ovamos/r1/alive/mapping/*"
    assert keys.stats("r1") == "ovamos/r1/stats/*/*"
    assert keys.stats("*", "mapping", "i0") == "ovamos/*/stats/mapping/i0"
    assert keys.rgbd("*") == "ovamos/*/sensors/rgbd"
    assert keys.robot_all("r1") == "ovamos/r1/**"


def test_stats_of_a_service_named_alive() -> None:
    """A service or instance literally named 'alive' must not confuse stats()."""
    assert keys.stats("r1", "alive", "alive") == "ovamos/r1/stats/alive/alive"


def test_stats_key_of_a_robot_named_alive() -> None:
    """'alive' passes check_chunk, so it is a valid robot id and must get its own stats key."""
    assert keys.stats("alive", "svc", "i0") == "ovamos/alive/stats/svc/i0"


@pytest.mark.parametrize("bad", [b for b in BAD_IDS if b != "*"], ids=repr)
def test_bad_service_and_instance_ids_are_refused(bad: str) -> None:
    """Same rules as robot ids; only a bare '*' is allowed, as the documented wildcard."""
    for build in (lambda: keys.alive("r1", bad), lambda: keys.alive("r1", "svc", bad),
                  lambda: keys.stats("r1", bad), lambda: keys.stats("r1", "svc", bad),
                  lambda: keys.bench("r1", bad)):
        with pytest.raises(KeyExprError):
            build()


def test_bench_name_is_not_a_wildcard() -> None:
    with pytest.raises(KeyExprError):
        keys.bench("r1", "*")


def test_check_chunk_names_what_was_wrong() -> None:
    with pytest.raises(KeyExprError, match="robot id 'a/b'"):
        keys.rgbd("a/b")
    assert keys.check_chunk("ok-id_1", "x") == "ok-id_1"
    assert issubclass(KeyExprError, ValueError)


@SETTINGS
@given(good_ids, good_ids, good_ids, st.sampled_from([keys.alive, keys.ready, keys.stats]))
def test_parse_service_key_round_trip(robot: str, service: str, instance: str,
                                      build: Callable[[str, str, str], str]) -> None:
    key = build(robot, service, instance)
    assert parse_service_key(key) == ServiceKey(robot, service, instance)
    assert parse_service_key(ke(key)) == ServiceKey(robot, service, instance)


@pytest.mark.parametrize("key", [
    "", "ovamos", "ovamos/r1", "ovamos/r1/sensors/rgbd", "ovamos/r1/alive/svc",
    "ovamos/r1/alive/svc/i0/extra", "other/r1/alive/svc/i0", "OVAMOS/r1/alive/svc/i0",
    "ovamos/r1/bench/svc/i0", "ovamos/r1/task/current/x", "x/ovamos/r1/alive/svc",
])
def test_parse_service_key_rejects_foreign_keys(key: str) -> None:
    with pytest.raises(KeyExprError):
        parse_service_key(key)


@pytest.mark.parametrize("where", ["robot", "service", "instance"])
def test_verbatim_chunk_ids_are_not_silently_invisible(where: str) -> None:
    """An accepted id must produce a key the wildcard selectors find (or be refused)."""
    parts = {"robot": "r1", "service": "svc", "instance": "i0", where: "@x"}
    try:
        key = keys.alive(parts["robot"], parts["service"], parts["instance"])
    except KeyExprError:
        return
    assert ke(keys.alive("*")).intersects(ke(key))
