"""Top-down grasps on the fitted superquadric (`sgjax.stage1.fit_grasps`) and their place in Stage 1."""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from sgjax.geometry.gripper import GripperSpec
from sgjax.geometry.superquadric import Superquadric, to_mesh
from sgjax.planner import PlannerConfig
from sgjax.stage1.fit_grasps import FitGraspConfig, fit_top_down_grasps
from sgjax.stage1.pipeline import Stage1, Stage1Config

SPEC = GripperSpec()
TABLE = jnp.array([0.0, 0.0, 1.0, 0.0])
CAMERA = np.array([0.0, -0.45, 0.55])


def lying(scale, eps, yaw_deg: float, centre_xy=(0.1, -0.05)) -> Superquadric:
    """A superquadric with its z axis up, resting on the table z = 0."""
    rotation = Rotation.from_euler("z", yaw_deg, degrees=True).as_matrix()
    return Superquadric.create(scale, eps, jnp.asarray(rotation, jnp.float32),
                               jnp.asarray([*centre_xy, scale[2]], jnp.float32))


# The grasps turned by 15 degrees about the normal as well (the default is straight across only).
TURNED = FitGraspConfig(yaws_deg=(-15.0, 0.0, 15.0))


def tips(poses) -> np.ndarray:
    """Fingertip centres [F, 3] of gripper poses [F, 4, 4]."""
    poses = np.asarray(poses)
    return poses[:, :3, 3] + SPEC.finger_length * poses[:, :3, 2]


def test_grasps_close_across_the_horizontal_axes_below_the_centre():
    scale = (0.045, 0.025, 0.0115)
    sq = lying(scale, (1.3, 0.8), 30.0)
    poses, widths, valid = (np.asarray(a) for a in fit_top_down_grasps(sq, TABLE, SPEC, TURNED))
    assert poses.shape == (6, 4, 4) and widths.shape == valid.shape == (6,)
    # Axis-major: the 9 cm x axis is wider than the gripper at every yaw, the 5 cm y axis is not.
    assert valid.tolist() == [False] * 3 + [True] * 3
    np.testing.assert_allclose(poses[:, :3, 2], np.tile([0.0, 0.0, -1.0], (6, 1)), atol=1e-6)  # straight down
    np.testing.assert_allclose(poses[:, 2, 0], 0.0, atol=1e-6)  # closing horizontally
    for p in poses:  # right-handed frames
        np.testing.assert_allclose(p[:3, :3].T @ p[:3, :3], np.eye(3), atol=1e-5)
        assert np.linalg.det(p[:3, :3]) == pytest.approx(1.0, abs=1e-5)
    # Fingertips centred on the fit, halfway between the table and its centre.
    np.testing.assert_allclose(tips(poses), np.tile([0.1, -0.05, 0.5 * scale[2]], (6, 1)), atol=1e-6)
    y_axis = np.asarray(sq.rotation)[:, 1]
    closing = poses[3:, :3, 0]
    angles = np.degrees(np.arccos(np.clip(np.abs(closing @ y_axis), 0.0, 1.0)))
    np.testing.assert_allclose(angles, [15.0, 0.0, 15.0], atol=1e-3)
    # Across the axis itself the width is the fit's (2 a_y) plus the contact margin on each side.
    assert widths[4] == pytest.approx(2 * scale[1] + 2 * SPEC.contact_threshold, abs=1e-6)
    # Off the axis the superellipse is wider, but less than its bounding box.
    box = 2 * (scale[0] * np.sin(np.radians(15)) + scale[1] * np.cos(np.radians(15))) + 2 * SPEC.contact_threshold
    assert widths[4] < widths[3] < box
    # The default: straight across each axis only, the same grasps as the turned set's middle ones.
    straight = [np.asarray(a) for a in fit_top_down_grasps(sq, TABLE, SPEC, FitGraspConfig())]
    assert FitGraspConfig().count == 2 and straight[0].shape == (2, 4, 4)
    for got, want in zip(straight, (poses[[1, 4]], widths[[1, 4]], valid[[1, 4]])):
        np.testing.assert_allclose(got, want, atol=1e-6)


def test_no_table_or_a_tall_object():
    sq = lying((0.03, 0.02, 0.0115), (1.0, 1.0), 0.0)
    assert not np.asarray(fit_top_down_grasps(sq, jnp.array([0.0, 0.0, 0.0, 1.0]), SPEC, FitGraspConfig())[2]).any()
    # A 20 cm tall object: the fingertips go no deeper than the fingers reach with the palm above its top.
    tall = lying((0.03, 0.02, 0.1), (1.0, 1.0), 0.0)
    cfg = FitGraspConfig(heights=(0.5,))
    poses, _, valid = fit_top_down_grasps(tall, TABLE, SPEC, cfg)
    assert np.asarray(valid).all()
    np.testing.assert_allclose(tips(poses)[:, 2], 0.2 - (SPEC.finger_length - cfg.palm_clearance), atol=1e-6)
    # The table clearance holds for a fit that barely rises above it.
    poses, _, _ = fit_top_down_grasps(lying((0.03, 0.02, 0.002), (1.0, 1.0), 0.0), TABLE, SPEC, cfg)
    np.testing.assert_allclose(tips(poses)[:, 2], cfg.min_clearance, atol=1e-6)


@pytest.mark.parametrize("kwargs, message", [({"heights": ()}, "at least one"), ({"heights": (0.0,)}, "fractions"),
                                             ({"min_clearance": -0.001}, ">= 0")])
def test_bad_configs_are_named(kwargs, message):
    with pytest.raises(ValueError, match=message):
        FitGraspConfig(**kwargs)


def test_the_planner_offers_them_in_the_plans_its_config_names(small_db):
    from sgjax.planner import Planner

    planner = Planner(db=small_db, config=PlannerConfig(stage1_batch_sizes=(1,)))
    assert PlannerConfig().stage1.fit_grasps is None  # Stage 1's own default: the paper's candidates
    assert planner.stage1.config.fit_grasps == FitGraspConfig()  # the planner's: in both plans
    assert planner._fallback_stage().config.fit_grasps == FitGraspConfig()
    assert PlannerConfig(fit_grasps=None).first_stage1.fit_grasps is None
    planner.config = PlannerConfig(fallback_filter=None)  # the paper's planner: no second plan at all
    assert planner._fallback_stage() is None


def lens_view(n: int = 900, seed: int = 0) -> np.ndarray:
    """A lens (pinched rim, 2.5 x 6 x 8 cm) lying on the table, its camera-facing surface sampled."""
    mesh = to_mesh(lying((0.04, 0.03, 0.0125), (1.4, 1.0), 20.0, centre_xy=(0.05, 0.0)), resolution=24)
    points, face = (np.asarray(a) for a in trimesh.sample.sample_surface(mesh, 8 * n, seed=seed))
    seen = np.sum(mesh.face_normals[face] * (CAMERA - points), 1) > 0
    rng = np.random.default_rng(seed)
    return points[seen][:n] + rng.normal(0.0, 0.0005, (min(n, int(seen.sum())), 3))


def test_stage1_offers_them_first_and_leaves_the_transferred_grasps_as_they_were(small_db):
    cloud = lens_view()
    plain = Stage1(small_db, Stage1Config())(cloud, viewpoint=CAMERA, support_plane=tuple(np.asarray(TABLE)))
    stage = Stage1(small_db, Stage1Config(fit_grasps=TURNED))
    with_fit = stage(cloud, viewpoint=CAMERA, support_plane=tuple(np.asarray(TABLE)))
    own = with_fit.primitive_id < 0
    assert own.any() and own[: own.sum()].all()  # first, ahead of every transferred grasp
    assert (with_fit.match_rank[own] == -1).all() and (with_fit.match_score[own] == 0).all()
    # They close low on the lens: below its widest section (its centre, 12.5 mm up), above the table.
    heights = tips(with_fit.poses[own])[:, 2]
    assert np.all((heights > 0.002) & (heights < 0.0125))
    # The transferred grasps are those of Stage 1 without them, in the same order.
    rest = ~own
    np.testing.assert_allclose(with_fit.poses[rest], plain.poses, atol=1e-6)
    np.testing.assert_array_equal(with_fit.primitive_id[rest], plain.primitive_id)
    added = with_fit.counts["transferred"] - plain.counts["transferred"]  # the fit's grasps that are valid
    assert own.sum() <= added <= TURNED.count // 2  # the lens's 8 cm axis is too wide to close across
    # The normal test (iii) would remove grasps the fit's own construction keeps.
    tested = Stage1(small_db, Stage1Config(fit_grasps=dataclasses.replace(TURNED, normal_test=True)), share=stage)
    again = tested(cloud, viewpoint=CAMERA, support_plane=tuple(np.asarray(TABLE)))
    assert (again.primitive_id < 0).sum() < own.sum()
    assert dataclasses.replace(FitGraspConfig(), normal_test=True) == FitGraspConfig(normal_test=True)
