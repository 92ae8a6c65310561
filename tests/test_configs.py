"""Config dataclasses back from their saved JSON (sgjax.utils.configs.from_dict)."""

from __future__ import annotations

import dataclasses
import json

import pytest

from sgjax.planner import PlannerConfig
from sgjax.stage1.matching import MatchConfig
from sgjax.stage1.pipeline import Stage1Config
from sgjax.utils.configs import from_dict
from train.label import LabelConfig


@pytest.mark.parametrize("config", [
    LabelConfig(),
    LabelConfig(per_source=(("stage1", 6), ("gpd", 3)), n_objects=3, object_set="tiny", held_out_objects=(), relabel_extra=2),
    Stage1Config(match=MatchConfig(K1=30, relabel_extra=4)),
    PlannerConfig(),  # with its nested optional configs (fit grasps, neighbours' fits, the robust choice)
    PlannerConfig(robust=None, fit_grasps=None),
])
def test_saved_configs_come_back_equal(config):
    saved = json.loads(json.dumps(dataclasses.asdict(config)))  # lists where the config holds tuples
    back = from_dict(type(config), saved)
    assert back == config and type(back) is type(config)


def test_optional_nested_configs_and_missing_fields():
    planner = PlannerConfig(fallback_match=MatchConfig(relabel_extra=5))
    back = from_dict(PlannerConfig, json.loads(json.dumps(dataclasses.asdict(planner))))
    assert back.fallback_match == MatchConfig(relabel_extra=5) and back == planner
    # A config saved before a field existed: the field takes its default.
    saved = dataclasses.asdict(MatchConfig(K2=7))
    del saved["relabel_extra"]
    assert from_dict(MatchConfig, saved) == MatchConfig(K2=7)


def test_unknown_fields_and_wrong_kinds_are_named():
    with pytest.raises(ValueError, match=r"MatchConfig: unknown fields \['K3'\]"):
        from_dict(MatchConfig, {"K3": 1})
    with pytest.raises(ValueError, match=r"LabelConfig\.stage1\.match: unknown fields"):
        from_dict(LabelConfig, {"stage1": {"match": {"nope": 0}}})
    with pytest.raises(ValueError, match=r"LabelConfig\.trial: expected a mapping"):
        from_dict(LabelConfig, {"trial": 3})
    with pytest.raises(ValueError, match="K1 and K2"):  # the config's own checks still run
        from_dict(MatchConfig, {"K1": 0})
