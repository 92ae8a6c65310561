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
    LabelConfig(per_source=(("stage1", 6), ("gpd", 3)), n_objects=3, object_set="tiny", held_out_objects=()),
    Stage1Config(match=MatchConfig(K1=30, K2=4)),
    PlannerConfig(),  # with its nested optional configs (fit grasps, neighbours' fits, the robust choice)
    PlannerConfig(robust=None, fit_grasps=None),
])
def test_saved_configs_come_back_equal(config):
    saved = json.loads(json.dumps(dataclasses.asdict(config)))  # lists where the config holds tuples
    back = from_dict(type(config), saved)
    assert back == config and type(back) is type(config)


def test_optional_nested_configs_and_missing_fields():
    planner = PlannerConfig(stage1=Stage1Config(match=MatchConfig(K2=7)), robust=None)
    back = from_dict(PlannerConfig, json.loads(json.dumps(dataclasses.asdict(planner))))
    assert back.stage1.match == MatchConfig(K2=7) and back.robust is None and back == planner
    # A config saved before a field existed: the field takes its default.
    saved = dataclasses.asdict(MatchConfig(K2=7))
    del saved["K1"]
    assert from_dict(MatchConfig, saved) == MatchConfig(K2=7)


def test_retired_options_read_back_only_at_todays_behaviour():
    """A config saved while a since-retired option existed (`RETIRED_FIELDS`): its old default is dropped,
    any other value is refused by name, nested configs included."""
    saved = json.loads(json.dumps(dataclasses.asdict(PlannerConfig())))
    saved.update(lever_weight=0.0, fallback_for=[], prefer_fit_grasps=False)
    saved["stage1"]["match"].update(relabel_axes=False, relabel_extra=0)
    saved["neighbour_fits"].update(in_fallback="prefer", closing=False)
    saved["robust"]["must_pass"] = False
    assert from_dict(PlannerConfig, saved) == PlannerConfig()
    saved["stage1"]["match"]["relabel_extra"] = 5
    with pytest.raises(ValueError, match=r"PlannerConfig\.stage1\.match\.relabel_extra = 5: this option was retired"):
        from_dict(PlannerConfig, saved)
    with pytest.raises(ValueError, match="lever_weight = 2.0: this option was retired"):
        from_dict(PlannerConfig, {"lever_weight": 2.0})


def test_unknown_fields_and_wrong_kinds_are_named():
    with pytest.raises(ValueError, match=r"MatchConfig: unknown fields \['K3'\]"):
        from_dict(MatchConfig, {"K3": 1})
    with pytest.raises(ValueError, match=r"LabelConfig\.stage1\.match: unknown fields"):
        from_dict(LabelConfig, {"stage1": {"match": {"nope": 0}}})
    with pytest.raises(ValueError, match=r"LabelConfig\.trial: expected a mapping"):
        from_dict(LabelConfig, {"trial": 3})
    with pytest.raises(ValueError, match="K1 and K2"):  # the config's own checks still run
        from_dict(MatchConfig, {"K1": 0})
