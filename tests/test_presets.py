"""Named planner configurations (`sgjax.presets`) and how the benchmark runs them (`method@preset`)."""

from __future__ import annotations

import dataclasses

import pytest

from eval.methods import UnknownMethod, check_method, make_method
from eval.protocol import split_preset, with_preset
from sgjax import presets
from sgjax.planner import FALLBACK_FILTER, PlannerConfig
from sgjax.stage1.filters import FilterConfig


def test_default_is_todays_planner_and_paper_is_the_papers():
    assert presets.names()[0] == "default" and set(presets.names()) == set(presets.PRESETS)
    assert presets.get("default") == PlannerConfig()
    assert PlannerConfig().fallback_filter == FALLBACK_FILTER and PlannerConfig().robust is not None
    paper = presets.get("paper")
    # The paper's planner: its filters, its candidates, its choice, its refinement rule, one plan.
    assert paper.stage1.filter == FilterConfig(shadow_depth=0.0, obstacle_margin=0.0, hidden_contacts="accept")
    assert (paper.fit_grasps, paper.neighbour_fits, paper.robust, paper.fallback_filter) == (None, None, None, None)
    assert paper.refine_rescore == 0 and paper.use_refinement and paper.eval_threshold == paper.refine_threshold == 0.7
    assert paper.first_stage1 == paper.stage1 and paper.stage1.fit_grasps is None
    # Fields replaced on request; each call builds a fresh config.
    assert presets.get("paper", use_refinement=False) == dataclasses.replace(paper, use_refinement=False)
    with pytest.raises(ValueError, match="unknown planner preset 'nope'; known: default, paper"):
        presets.get("nope")


def test_benchmark_methods_name_their_preset(small_db):
    assert split_preset("supergrasp") == ("supergrasp", "default")
    assert split_preset("supergrasp-norefine@paper") == ("supergrasp-norefine", "paper")
    assert with_preset("supergrasp", "default") == "supergrasp" and split_preset(with_preset("gpd", "x")) == ("gpd", "x")
    method = make_method("supergrasp-norefine@paper", db=small_db)
    assert method.name == "supergrasp-norefine@paper"
    config = method.config  # the preset with the benchmark's workspace crop, without the refinement branch
    assert config == dataclasses.replace(presets.get("paper", use_refinement=False), scene_cloud=config.scene_cloud)
    assert config.scene_cloud.bounds is not None
    assert make_method("supergrasp", db=small_db).config == dataclasses.replace(PlannerConfig(),
                                                                                scene_cloud=config.scene_cloud)
    with pytest.raises(ValueError, match="unknown planner preset 'nope'"):
        check_method("supergrasp@nope")
    with pytest.raises(ValueError, match="'gpd' takes no planner preset"):
        check_method("gpd@paper")
    with pytest.raises(UnknownMethod):
        check_method("nothing@paper")
