"""Service configs from TOML tables: a nested table overrides its owner's defaults."""

from __future__ import annotations

import importlib
import tomllib
from pathlib import Path

import pytest

from hdmap.cli.service import SERVICES, service_config
from hdmap.mapping.estimator import EstimatorConfig
from hdmap.runtime.config import ConfigError, from_mapping
from hdmap.runtime.service import Batching
from services.matcher.service import MatcherConfig

ROOT = Path(__file__).resolve().parents[2]


def test_nested_table_keeps_the_fields_own_default() -> None:
    # the matcher gates with the plug-in meat; a table that sets another estimator knob
    # must not switch that back to the class default
    cfg = from_mapping(MatcherConfig, {"estimator": {"min_clusters": 6}}, "matcher")
    assert cfg.estimator.min_clusters == 6
    assert cfg.estimator.integrated_meat is False
    assert EstimatorConfig().integrated_meat is True
    assert from_mapping(MatcherConfig, {}, "matcher") == MatcherConfig()


def test_deploy_file_gives_the_solver_the_integrated_meat_and_the_matcher_the_plug_in() -> None:
    with open(ROOT / "deploy" / "services.toml", "rb") as f:
        table = tomllib.load(f)
    solver = service_config("solver", table["solver"])[1]
    matcher = service_config("matcher", table["matcher"])[1]
    assert solver.estimator.integrated_meat and solver.estimator.min_clusters == 5
    assert not matcher.estimator.integrated_meat


def test_matcher_refuses_to_close_passes_its_pending_pool_may_still_link() -> None:
    with pytest.raises(ConfigError, match=r"matcher\.close_passes_after_s: must exceed"):
        from_mapping(MatcherConfig, {"close_passes_after_s": 600.0}, "matcher")
    assert from_mapping(MatcherConfig, {"close_passes_after_s": 0.0}, "matcher")


def test_deploy_file_batching_is_each_service_s_default() -> None:
    with open(ROOT / "deploy" / "services.toml", "rb") as f:
        table = tomllib.load(f)
    for name in ("ingest", "matcher", "solver", "publisher"):
        batching, _cfg = service_config(name, table[name])
        module, cls, _c = SERVICES[name]
        own = getattr(importlib.import_module(module), cls).batch_linger_s
        assert batching == Batching(linger_s=own), name


def test_deploy_file_gaps_are_the_defaults_and_a_bad_one_names_its_key() -> None:
    from hdmap.cli.service import gap_policy
    from hdmap.runtime.log_policy import GapPolicy

    with open(ROOT / "deploy" / "services.toml", "rb") as f:
        table = tomllib.load(f)
    assert gap_policy("matcher", table["matcher"]) == GapPolicy()
    assert gap_policy("solver", table["solver"]) == GapPolicy()  # no table: the defaults
    with pytest.raises(ConfigError, match=r"matcher\.gaps\.timeout_s"):
        gap_policy("matcher", {"gaps": {"timeout_s": "soon"}})
    with pytest.raises(ConfigError, match=r"gaps\.timeout_s: seconds"):
        gap_policy("matcher", {"gaps": {"timeout_s": -1.0}})


def test_a_choice_outside_its_literal_names_the_key_and_the_choices() -> None:
    cfg = from_mapping(MatcherConfig, {"gate": {"landmark_scale": "cost"}})
    assert cfg.gate.landmark_scale == "cost"
    with pytest.raises(ConfigError, match=r"gate\.landmark_scale: expected one of 'off'"):
        from_mapping(MatcherConfig, {"gate": {"landmark_scale": "on"}})
    with pytest.raises(ConfigError, match="range_scale: expected one of"):
        from_mapping(EstimatorConfig, {"range_scale": 1})
