"""The policy registry: the names configs and results carry, what sets each policy apart, the benchmark's rows."""

from __future__ import annotations

import tomllib

import pytest
from pydantic import ValidationError

from ovamos.bench.episode import EpisodeConfig, episode_config
from ovamos.bench.policies import ABLATIONS, DEFAULT_POLICIES, LABELS, PAPER, POLICY_ORDER, planner_policy
from ovamos.services.planner.config import PlannerServiceConfig
from ovamos.services.planner.decide import DecisionConfig
from ovamos.services.planner.plus import PlusConfig
from ovamos.services.planner.policies import OVAMOS_PLUS, POLICIES, Choice, policy_named

PLANNER_NAMES = ("random", "vlfm", "finder", "ovamos-greedy", "ovamos-nodecay", "ovamos", "ovamos-plus")


def test_the_registry_holds_the_names_configs_and_results_use_in_table_order() -> None:
    assert tuple(POLICIES) == PLANNER_NAMES == DEFAULT_POLICIES
    assert POLICY_ORDER == (*PLANNER_NAMES, "ovamos-plus-1frontier", "ovamos-plus-noverify",
                            "ovamos-plus-strictstop", "ovamos-plus-look", "ovamos-plus-budget")
    assert set(LABELS) == set(POLICY_ORDER) and set(PAPER) <= set(POLICIES)
    assert all(name == policy.name for name, policy in POLICIES.items())


def test_a_planner_config_names_its_policy_and_an_unknown_name_is_refused_naming_all() -> None:
    for name in PLANNER_NAMES:
        toml = tomllib.loads(f'[agent.decision]\npolicy = "{name}"\n')
        config = PlannerServiceConfig.model_validate(toml)
        assert config.agent.decision.policy == name
        assert config.model_dump(mode="json")["agent"]["decision"]["policy"] == name
    with pytest.raises(ValidationError, match="unknown policy 'ovamos-plus-look': one of " + ", ".join(PLANNER_NAMES)):
        DecisionConfig(policy="ovamos-plus-look")  # an ablation is a benchmark row, not a planner policy
    with pytest.raises(ValueError, match="unknown policy 'nope'"):
        policy_named("nope")


def test_what_sets_the_policies_apart() -> None:
    assert POLICIES["vlfm"].targets(["bed", "cup"]) == ["bed"]
    assert POLICIES["finder"].targets(["bed", "cup"]) == ["bed", "cup"]
    assert [p.name for p in POLICIES.values() if not p.decays] == ["vlfm", "finder", "ovamos-nodecay"]
    assert [p.name for p in POLICIES.values() if p.wanders] == ["random"]
    assert [p.name for p in POLICIES.values() if p.plus_switches] == ["ovamos-plus"]
    assert {p.name for p in POLICIES.values() if p.choice is Choice.BEST_FRONTIER} == {"vlfm", "finder"}


def test_an_ablation_runs_ovamos_plus_with_its_switches_and_results_carry_its_name() -> None:
    for name, ablation in ABLATIONS.items():
        assert planner_policy(name) == (OVAMOS_PLUS, ablation.plus)
        PlusConfig(**ablation.plus)  # every change is a PlusConfig field with a valid value
    config = episode_config("ovamos-plus-look")
    assert config.policy == "ovamos-plus-look"
    assert config.agent.decision.policy == "ovamos-plus" and config.agent.decision.plus.look_before_stop == 4
    assert episode_config("vlfm").agent.decision.plus == PlusConfig()
    with pytest.raises(ValueError, match="unknown policy 'nope': one of " + ", ".join(POLICY_ORDER)):
        planner_policy("nope")
    with pytest.raises(ValidationError, match="unknown policy 'nope'"):
        EpisodeConfig(policy="nope")
