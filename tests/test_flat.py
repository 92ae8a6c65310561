"""Flat objects lying on the table get grasps on their fitted superquadric that hold them in simulation
(`sgjax.stage1.fit_grasps`, `PlannerConfig.fit_grasps`).

Each object of the "flat" set rests alone on its largest face, seen by the benchmark camera; Stage 1 as
the planner's second plan runs it (its looser filter, the fit's grasps) plans on the view, and every fit
grasp it keeps is executed in the benchmark's trial (lift, reorient, 1 N).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from envs.objects import load_object_set
from eval import single_object
from sgjax.geometry.pointcloud import table_plane
from sgjax.planner import FALLBACK_FILTER
from sgjax.stage1.fit_grasps import FitGraspConfig
from sgjax.stage1.pipeline import Stage1, Stage1Config

PLACEMENTS = 2


@pytest.fixture(scope="module")
def fit_grasp_outcomes(small_db) -> dict[str, list[np.ndarray]]:
    stage = Stage1(small_db, Stage1Config(filter=FALLBACK_FILTER, fit_grasps=FitGraspConfig()))
    rng = np.random.default_rng(0)
    found: dict[str, list[np.ndarray]] = {}
    for asset in load_object_set("flat"):
        for pose in single_object.placements(asset.extents, "standing", PLACEMENTS, rng):
            setup = single_object.alone(asset, pose, seed=int(rng.integers(2**31)))
            assert setup is not None, f"{asset.name} left the table while settling"
            points, labels = setup.obs.points, setup.obs.point_labels
            cands = stage(points[labels == 0], points[labels < 0], setup.viewpoint, 0, table_plane(points, labels))
            own = cands.primitive_id < 0
            found.setdefault(asset.name, []).append(single_object.success(setup, cands.poses[own], cands.widths[own]))
    return found


def test_every_flat_object_gets_fit_grasps_that_hold_it(fit_grasp_outcomes):
    names = {a.name for a in load_object_set("flat")}
    assert set(fit_grasp_outcomes) == names and len(names) >= 4
    for name, per_placement in fit_grasp_outcomes.items():
        assert len(per_placement) == PLACEMENTS
        assert all(len(ok) >= 1 for ok in per_placement), f"{name}: a placement got no fit grasp"
        assert all(ok.any() for ok in per_placement), f"{name}: no fit grasp held it ({per_placement})"
    rate = np.concatenate([ok for v in fit_grasp_outcomes.values() for ok in v]).mean()
    assert rate >= 0.7, {k: [ok.tolist() for ok in v] for k, v in fit_grasp_outcomes.items()}


def test_the_flat_set_is_named_and_complete():
    assets = load_object_set("flat")
    assert all(a.name.startswith("flat/") for a in assets)
    assert all(min(a.extents) <= 0.026 for a in assets)  # each rests on a face at most 2.6 cm tall
    assert [single_object.shape_class(a.name) for a in assets] == ["lens", "lens", "pebble", "puck", "tile"]
    assert dataclasses.replace(FitGraspConfig()) == FitGraspConfig()
