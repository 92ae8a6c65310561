"""Baselines and ablations: the PointNetGPD evaluator (crop, network, training, checkpoints), the methods
`pointnetgpd`, `s1+pointnetgpd` and `gpd+s2` on a tiny simulated scene, and the out-of-process
`contact-graspnet` adapter (its setup's default location with real files, the conversion of its
predictions to our gripper and the choice of grasp; real inference when its environment exists)."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import nnx

from envs.camera import CameraConfig, observe
from envs.objects import tiny_object_set
from envs.scene import workspace_bounds
from eval import baselines, cgn_setup, contact_graspnet
from eval.declutter import (
    DeclutterConfig,
    closing_region_objects,
    make_benchmark_scene,
    run_scene,
)
from sgjax.samplers.gpd import GPDConfig
from eval.methods import METHODS, MethodUnavailable, make_method, method_names
from sgjax.stage2 import crops, ernet
from sgjax.geometry import gripper, pointcloud
from sgjax.stage2 import pointnetgpd as pg
from sgjax_cli import main
from sgjax.stage2.ernet import ERNet, ERNetConfig
from sgjax.stage2.scene_cloud import SceneCloudConfig
from sgjax.geometry.gripper import GripperSpec
from train import dataset
from train.label import LabelConfig
from train import train_pointnetgpd as tp

SPEC = GripperSpec()
TINY = pg.PointNetGPDConfig.tiny()
SCENE = DeclutterConfig(camera=CameraConfig(width=320, height=240), nthread=1)
# Small shapes: 32 x 7 GPD samples over 3 depths x 2 placements, 64 candidate slots, a 4096-point scene.
CONFIG = baselines.BaselineConfig(gpd=GPDConfig(num_samples=32, max_points=1024, depth_steps=3, lateral_steps=2),
                                  max_candidates=64, scene_cloud=SceneCloudConfig(max_points=4096), stage1_batch_sizes=(1,))
# Jitted once here: op-by-op (eager) execution of these compiles every primitive on its own.
crop_closing = jax.jit(crops.crop_closing_regions, static_argnames=("spec", "n_points"))
crop_enlarged = jax.jit(crops.crop_regions, static_argnames=("spec", "n_points"))
prepare = jax.jit(pg.prepare_inputs, static_argnames=("spec", "config"))


def random_poses(rng, m, centre=(0.0, 0.0, 0.0)):
    """m random grasp poses with their closing regions around `centre`."""
    poses = np.tile(np.eye(4), (m, 1, 1))
    for i in range(m):
        q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        poses[i, :3, :3] = q * np.sign(np.linalg.det(q))
        poses[i, :3, 3] = np.asarray(centre) - poses[i, :3, 2] * 0.025 + rng.normal(0, 0.005, 3)
    return poses.astype(np.float32)


# ---------------------------------------------------------------------------------------------
# The evaluator.


def test_crop_is_exactly_the_closing_region():
    rng = np.random.default_rng(0)
    scene = rng.uniform(-0.06, 0.06, (900, 3)).astype(np.float32)
    scene_mask = rng.random(900) > 0.1
    poses, widths = random_poses(rng, 6), rng.uniform(0.03, 0.08, 6).astype(np.float32)
    region = crop_closing(scene, poses, widths, SPEC, n_points=TINY.n_points, scene_mask=scene_mask)
    inside = np.asarray(gripper.points_in_closing_region(scene, poses, widths, SPEC)) & scene_mask
    assert (np.asarray(region.count) == inside.sum(1)).all() and 5 < inside.sum(1).min() and inside.sum(1).max() < TINY.n_points
    for i in range(6):
        got = np.asarray(region.points[i])[np.asarray(region.mask[i])]
        world = got @ poses[i, :3, :3].T + poses[i, :3, 3]  # back to the world: the same points, in scene order
        np.testing.assert_allclose(world, scene[inside[i]], atol=1e-6)
        assert np.asarray(crops.in_closing_region_local(got[None], widths[i : i + 1], SPEC)).all()
    # Truncation keeps the first n_points region points in scene order.
    short = crop_closing(scene, poses, widths, SPEC, n_points=8, scene_mask=scene_mask)
    np.testing.assert_array_equal(np.asarray(short.points), np.asarray(region.points)[:, :8])
    np.testing.assert_array_equal(np.asarray(short.count), np.asarray(region.count))

    # Training crops (enlarged region in the grasp frame, as labelled) give the same points.
    enlarged = crop_enlarged(scene, poses, widths, SPEC, dataset.REGION_POINTS, scene_mask)
    inputs = prepare(enlarged.points, enlarged.mask, widths, SPEC, TINY)
    for i in range(6):
        a = np.asarray(inputs.points[i])[np.asarray(inputs.mask[i])]
        b = np.asarray(region.points[i])[np.asarray(region.mask[i])]
        np.testing.assert_allclose(a, b, atol=1e-6)


def test_network_shapes_masking_and_scores():
    rng = np.random.default_rng(1)
    model = pg.PointNetGPD(TINY, rngs=nnx.Rngs(0))
    points = rng.normal(0, 0.01, (5, TINY.n_points, 3)).astype(np.float32)
    mask = np.arange(TINY.n_points)[None] < np.array([[64], [10], [1], [30], [0]])
    logits = model(pg.PointNetGPDInputs(jnp.asarray(points), jnp.asarray(mask)))
    assert logits.shape == (5, 2) and np.isfinite(np.asarray(logits)).all()
    # Padding rows and the point order do not matter (masked max-pool).
    noisy = np.where(mask[..., None], points, 9.0)
    order = rng.permutation(TINY.n_points)
    for other in (noisy, points[:, order]):
        other_mask = mask if other is noisy else mask[:, order]
        again = model(pg.PointNetGPDInputs(jnp.asarray(other), jnp.asarray(other_mask)))
        np.testing.assert_allclose(np.asarray(again), np.asarray(logits), atol=1e-5)

    # score on a world cloud: fixed shapes, invalid candidates (empty region, NaN or too wide) score 0.
    scene = rng.uniform(-0.05, 0.05, (2000, 3)).astype(np.float32)
    poses = random_poses(rng, 4)
    poses[1, :3, 3] = [1.0, 1.0, 1.0]  # nothing there
    widths = np.array([0.06, 0.06, np.nan, 0.2], np.float32)
    graphdef, state = nnx.split(model)
    out = pg.score(graphdef, state, scene, poses, widths, np.ones(2000, bool))
    assert out.prob.shape == out.valid.shape == out.count.shape == (4,)
    np.testing.assert_array_equal(np.asarray(out.valid), [True, False, False, False])
    assert float(out.prob[0]) > 0 and np.all(np.asarray(out.prob[1:]) == 0)
    shuffled = scene[np.asarray(jax.random.permutation(jax.random.key(0), 2000))]  # score's default key
    region = crop_closing(shuffled, poses[:1], widths[:1], SPEC, n_points=TINY.n_points)
    expected = pg.probability(model(pg.PointNetGPDInputs(region.points, region.mask)))
    np.testing.assert_allclose(float(out.prob[0]), float(expected[0]), rtol=1e-5)
    compiled = pg.score._cache_size()
    pg.score(graphdef, state, scene + 0.001, poses, widths, np.ones(2000, bool))
    assert pg.score._cache_size() == compiled  # same shapes: no recompile


def test_pointnetgpd_overfits_a_tiny_batch():
    samples = dataset.synthetic_samples(32, seed=0)
    config = tp.default_config(batch_size=16, lr=1e-2, model=TINY)  # as the CLI run below: one compile
    graphdef, params = nnx.split(pg.PointNetGPD(TINY, rngs=nnx.Rngs(0)))
    tx, train_step, _ = tp.make_steps(graphdef, config)
    params, opt_state = jax.device_put((params, tx.init(params)), jax.devices()[0])
    weight = (np.arange(16) < 8).astype(np.float32)
    batch = jax.device_put(dataset.make_batch(samples, np.arange(16), weight))
    losses = []
    for step in range(80):
        params, opt_state, stats = train_step(params, opt_state, batch, jax.random.key(step), jnp.float32(1.0))
        losses.append(float(stats["loss"] / stats["n"]))
    assert float(stats["n"]) == 8.0 and float(stats["correct"]) == 8.0
    assert np.mean(losses[-5:]) < 0.4 * losses[0], losses[::10]
    assert train_step._cache_size() == 1


@pytest.fixture(scope="module")
def pointnetgpd_run(tmp_path_factory):
    """A tiny PointNetGPD trained for 2 epochs through the CLI on synthetic shards: its run directory."""
    root = tmp_path_factory.mktemp("pointnetgpd")
    args = ["train", "--network", "pointnetgpd", "--model", "tiny", "--data", str(root / "data"), "--out",
            str(root / "run"), "--batch-size", "16", "--lr", "1e-2", "--held-out", "0.25", "--quiet"]
    assert main([*args, "--synthetic", "48", "--epochs", "1"]) == 0
    assert main([*args, "--epochs", "2"]) == 0  # resumes after epoch 1
    return root / "run"


def test_checkpoint_round_trip_and_clear_errors(pointnetgpd_run, tmp_path):
    model, meta = pg.load_model(pointnetgpd_run)
    assert meta["network"] == "pointnetgpd" and meta["epochs_done"] == 2
    assert model.config == pg.PointNetGPDConfig.tiny() and [r["epoch"] for r in meta["history"]] == [1, 2]
    record = json.loads((pointnetgpd_run / "metrics.json").read_text())["history"][-1]
    assert record["held_out"]["samples"] > 0 and record["train"]["refine_accuracy"] is None
    assert (pointnetgpd_run / "curves.png").exists()
    first, _ = pg.load_model(pointnetgpd_run, epoch=1)
    assert not np.array_equal(np.asarray(first.head.layers[0].kernel[...]), np.asarray(model.head.layers[0].kernel[...]))
    # The restored network scores the stored samples as the trained one did (same held-out accuracy).
    samples = dataset.read_shards(pointnetgpd_run.parent / "data")
    out = pg.score_regions(*nnx.split(model), samples["region"], samples["region_mask"], samples["width"])
    assert out.prob.shape == (48,) and np.asarray(out.valid).mean() > 0.9

    with pytest.raises(FileNotFoundError, match="sgjax train --network pointnetgpd"):
        pg.load_model(tmp_path / "nowhere")
    with pytest.raises(TypeError, match="PointNetGPDConfig"):
        tp.train(samples, tmp_path / "x", tp.default_config(model=ERNetConfig.tiny()))


def test_missing_default_checkpoints_name_the_path_and_command(monkeypatch, tmp_path):
    from sgjax.stage2 import checkpoint

    monkeypatch.setattr(checkpoint, "POINTNETGPD_DEFAULT_DIR", tmp_path / "pointnetgpd_default")
    monkeypatch.setattr(checkpoint, "ERNET_DEFAULT_DIR", tmp_path / "ernet_default")
    for name in ("pointnetgpd", "s1+pointnetgpd"):
        with pytest.raises(FileNotFoundError, match=r"pointnetgpd_default.*sgjax train --network pointnetgpd"):
            make_method(name, config=CONFIG)
    with pytest.raises(FileNotFoundError, match=r"ernet_default.*sgjax train"):
        make_method("gpd+s2", config=CONFIG)
    with pytest.raises(ValueError, match="does not take option"):
        make_method("pointnetgpd", small_db=True)


# ---------------------------------------------------------------------------------------------
# The methods on a tiny scene.


@pytest.fixture(scope="module")
def objects():
    return tiny_object_set()


@pytest.fixture(scope="module")
def observation(objects):
    scene = make_benchmark_scene(objects, 2, 0, 0, SCENE)
    obs = observe(scene, SCENE.camera, seed=0)
    return obs.points, obs.point_labels, np.asarray(SCENE.camera.position, np.float64)


def check_grasp(decision, points, labels):
    pose = decision.pose
    assert pose.shape == (4, 4) and decision.reason == ""
    np.testing.assert_allclose(pose[:3, :3].T @ pose[:3, :3], np.eye(3), atol=1e-9)
    assert 0 < decision.width <= SPEC.max_opening
    assert decision.timing["total_s"] == pytest.approx(decision.timing["stage1_s"] + decision.timing["stage2_s"])
    assert closing_region_objects(points, labels, pose, decision.width, SPEC)  # an object between the fingers


def expected_pointnetgpd(method, points, labels, view, seed):
    """The candidate the method should execute: recomputed from its parts."""
    cands = method.generator(points, labels, view, seed)
    scene, mask, _ = pointcloud.scene_cloud(points, CONFIG.scene_cloud.max_points, CONFIG.scene_cloud.voxel, None, None, seed)
    out = pg.score(method.graphdef, method.state, scene, cands.poses, cands.widths, mask, key=jax.random.key(seed))
    prob = np.where(np.asarray(out.valid) & (np.arange(len(cands.widths)) < cands.n), np.asarray(out.prob), -1)
    return cands, int(np.argmax(prob)), float(prob.max())


def test_pointnetgpd_method(pointnetgpd_run, objects, observation):
    points, labels, view = observation
    method = make_method("pointnetgpd", model=str(pointnetgpd_run), config=CONFIG)
    assert method.name == "pointnetgpd" and METHODS["pointnetgpd"].unavailable_reason() is None
    first = method.plan(points, labels, view, seed=3)
    compiled = pg.score._cache_size()
    second = method.plan(points, labels, view, seed=4)
    assert pg.score._cache_size() == compiled  # no recompile across calls
    for seed, decision in ((3, first), (4, second)):
        check_grasp(decision, points, labels)
        cands, best, prob = expected_pointnetgpd(method, points, labels, view, seed)
        assert decision.info["generator"] == "gpd" and decision.info["index"] == best
        np.testing.assert_allclose(decision.pose, cands.poses[best], atol=1e-6)
        assert decision.score == pytest.approx(prob) and decision.width == pytest.approx(cands.widths[best])
    # The harness's memory: the grasps to avoid are left out before scoring, the rest keep their order.
    avoided = method.plan(points, labels, view, seed=3, avoid=first.pose[None])
    cands = method.generator(points, labels, view, 3)
    near = gripper.near_grasps(cands.poses[: cands.n].astype(np.float64), first.pose[None], SPEC, xp=np)
    assert near.any() and avoided.info["avoided"] == near.sum()
    assert not gripper.near_grasps(avoided.pose[None], first.pose[None], SPEC, xp=np)[0]
    kept = baselines.without_avoided(cands, first.pose[None], SPEC)
    assert kept.n == cands.n - near.sum() and kept.poses.shape == cands.poses.shape
    np.testing.assert_array_equal(kept.poses[: kept.n], cands.poses[: cands.n][~near])
    gone = baselines.without_avoided(cands, cands.poses[: cands.n], SPEC)
    assert gone.n == 0 and gone.reason.startswith(f"all {cands.n} candidates are the same grasp")
    # Through the benchmark harness.
    run = run_scene(method, objects, 2, seed=0, index=0, config=SCENE, setting="tiny-2")
    assert 1 <= len(run.log["attempts"]) <= run.log["objects"] + 5
    assert all(a["info"]["generator"] == "gpd" for a in run.log["attempts"])


def test_the_gpd_budget_grows_with_the_objects_in_view(observation):
    """GPD-style samples and scored slots scale with ceil(objects in view / objects_per_budget); objects
    with fewer than min_points points are not in view; 0 keeps the budget fixed."""
    from sgjax.samplers import gpd as gpd_sampler

    points, labels, view = observation
    cfg = CONFIG.gpd
    labels_of = lambda counts: np.concatenate([np.full(c, i) for i, c in enumerate(counts)] + [np.full(5, -1)])
    assert gpd_sampler.budget_factor(labels_of([50] * 10), cfg) == 1
    assert gpd_sampler.budget_factor(labels_of([50] * 11), cfg) == 2
    assert gpd_sampler.budget_factor(labels_of([50] * 10 + [cfg.min_points - 1] * 5), cfg) == 1
    assert gpd_sampler.budget_factor(labels_of([50] * 25), dataclasses.replace(cfg, objects_per_budget=0)) == 1
    in_view = len([i for i, c in zip(*np.unique(labels, return_counts=True)) if i >= 0 and c >= cfg.min_points])
    assert in_view == 2
    one = dataclasses.replace(CONFIG, gpd=dataclasses.replace(cfg, objects_per_budget=1))  # two objects: twice
    cands = baselines.gpd_candidates(points, labels, view, 3, one)
    fixed = baselines.gpd_candidates(points, labels, view, 3, dataclasses.replace(CONFIG, gpd=dataclasses.replace(cfg, objects_per_budget=0)))
    assert cands.info["sampled"] == 2 * fixed.info["sampled"] == 2 * cfg.num_samples * cfg.num_angles
    assert len(cands.widths) == 2 * len(fixed.widths) == 2 * CONFIG.max_candidates
    with pytest.raises(ValueError, match="objects_per_budget"):
        dataclasses.replace(cfg, objects_per_budget=-1)


def rigged_ernet(eval_bias, refine_bias):
    tiny = ERNetConfig.tiny(backbone=dataclasses.replace(ERNetConfig.tiny().backbone, sampler="random"))
    model = ERNet(tiny, rngs=nnx.Rngs(0))
    for head, bias in ((model.eval_head, eval_bias), (model.refine_head, refine_bias)):
        last = head.layers[-1]
        last.kernel[...] = jnp.zeros_like(last.kernel[...])
        last.bias[...] = jnp.asarray(bias, jnp.float32)
    return model


def test_gpd_with_stage2_follows_the_decision_policy(observation):
    """gpd+s2 decides as the planner: the best evaluation > 0.7; else a refinement, by default re-scored at
    its refined pose (the geometric mean of the two heads, `sgjax.planner.rescored_refinements`) and
    executed only once it passes the generator's collision test; else no grasp, and why."""
    points, labels, view = observation
    evaluated = make_method("gpd+s2", model=rigged_ernet([-2.0, 2.0], [-3.0, -3.0, -3.0]), config=CONFIG)
    decision = evaluated.plan(points, labels, view, seed=5)
    check_grasp(decision, points, labels)
    cands = evaluated.generator(points, labels, view, 5)
    assert decision.info["kind"] == "evaluated" and decision.score == pytest.approx(0.982, abs=1e-3)
    np.testing.assert_allclose(decision.pose, cands.poses[decision.info["index"]], atol=1e-6)
    # Evaluation 0.69 everywhere (below 0.7), refinement 0.95 for variant 1: re-scored, sqrt(0.95 x 0.69)
    # = 0.81 passes, so the candidate is refined (deepened, rotated 0 deg), and its refined pose is free.
    refined = make_method("gpd+s2", model=rigged_ernet([0.0, 0.8], [-3.0, 3.0, -3.0]), config=CONFIG)
    compiled = ernet.score._cache_size()
    decision = refined.plan(points, labels, view, seed=5)
    assert ernet.score._cache_size() == compiled  # same network shapes, same compile (the re-scoring too)
    p_eval, p_refine = 1 / (1 + np.exp(-0.8)), 1 / (1 + np.exp(-3.0))  # softmax of (0, 0.8); sigmoid of 3
    assert decision.info["kind"] == "refined" and decision.info["refine_variant"] == 1
    assert decision.score == pytest.approx(np.sqrt(p_eval * p_refine), abs=1e-3)
    # The refined pose, backed off the table along its approach where deepening reached into it (as the planner).
    expected = np.asarray(gripper.refined_pose(cands.poses[decision.info["index"]], 1, SPEC))
    np.testing.assert_allclose(decision.pose[:3, :3], expected[:3, :3], atol=1e-5)
    back = expected[:3, 3] - decision.pose[:3, 3]
    np.testing.assert_allclose(back, np.dot(back, expected[:3, 2]) * expected[:3, 2], atol=1e-6)
    assert 0.0 <= np.dot(back, expected[:3, 2]) <= CONFIG.stage1.max_lift + 1e-6
    # With the candidates before the first whose refinement collides left out (as failed grasps), the
    # policy meets that one first: it passes over the refinements that collide (ties: lowest index first)
    # and executes the first that does not.
    hits = [baselines._RefinedCollisions(cands, points, labels, CONFIG, 5)(i)[0][1] for i in range(cands.n)]
    k = hits.index(True)
    decision = refined.plan(points, labels, view, seed=5, avoid=cands.poses[:k])
    kept = baselines.without_avoided(cands, cands.poses[:k], SPEC)
    collides = baselines._RefinedCollisions(kept, points, labels, CONFIG, 5)
    index = decision.info["index"]
    assert decision.info["kind"] == "refined" and not collides(index)[0][1]
    assert decision.info["refinements_rejected"] == sum(collides(i)[0][1] for i in range(index)) >= 1
    np.testing.assert_allclose(decision.pose, collides(index)[1][1], atol=1e-6)
    # The paper's rule (the refine head alone) refines what the re-scoring sinks: evaluation 0.018.
    low = rigged_ernet([2.0, -2.0], [-3.0, 3.0, -3.0])
    sunk = make_method("gpd+s2", model=low, config=CONFIG).plan(points, labels, view, seed=5)
    assert sunk.pose is None and "best re-scored refinement 0.13 <= 0.7" in sunk.reason
    paper = make_method("gpd+s2", model=low, config=dataclasses.replace(CONFIG, refine_rescore=0)).plan(points, labels, view,
                                                                                                       seed=5)
    assert paper.info["kind"] == "refined" and paper.score == pytest.approx(p_refine, abs=1e-3)
    # Neither above 0.7 (or refinement off): no grasp, and the reason says why.
    never = make_method("gpd+s2", model=low, config=dataclasses.replace(CONFIG, use_refinement=False))
    decision = never.plan(points, labels, view, seed=5)
    assert decision.pose is None and "refinement disabled" in decision.reason
    with pytest.raises(ValueError, match="refine_rescore"):
        dataclasses.replace(CONFIG, refine_rescore=-1)


@pytest.mark.slow  # Stage 1's compile (shared with the planner tests in a full run)
def test_stage1_with_pointnetgpd(pointnetgpd_run, observation):
    points, labels, view = observation
    method = make_method("s1+pointnetgpd", model=str(pointnetgpd_run), small_db=True, config=CONFIG)
    decision = method.plan(points, labels, view, seed=6)
    check_grasp(decision, points, labels)
    cands, best, prob = expected_pointnetgpd(method, points, labels, view, 6)
    assert decision.info["generator"] == "stage1" and decision.info["index"] == best
    assert decision.score == pytest.approx(prob)
    np.testing.assert_allclose(decision.pose, cands.poses[best], atol=1e-6)
    assert cands.n == min(cands.found, CONFIG.max_candidates) and set(cands.target[: cands.n]) <= {0, 1}
    # More candidates than slots: every object keeps its best-matched ones (round-robin by rank).
    obj, row = baselines.round_robin([5, 2, 0, 3], 6)
    assert sorted(zip(obj.tolist(), row.tolist())) == [(0, 0), (0, 1), (1, 0), (1, 1), (3, 0), (3, 1)]


@pytest.mark.slow  # Stage 1's compile (shared with the planner tests in a full run)
def test_planner_with_pointnetgpd_in_place_of_ernet(pointnetgpd_run, observation):
    """The network ablation `supergrasp-pointnetgpd`: SuperGrasp's planner whose Stage 2 is PointNetGPD.
    Every candidate's evaluation is PointNetGPD's probability at its pose on the planner's scene cloud,
    there are no refinements, and the executed grasp passes the planner's threshold."""
    from eval.supergrasp import PlannerMethod
    from sgjax.planner import Planner, PlannerConfig

    points, labels, view = observation
    method = make_method("supergrasp-pointnetgpd", model=str(pointnetgpd_run), small_db=True)
    assert method.name == "supergrasp-pointnetgpd" and not method.config.use_refinement
    plan = method.full_plan(points, labels, view, seed=7)
    s = plan.scores
    m = len(s["eval_prob"])
    assert m > 0 and not np.any(s["refine_prob"])
    cands = [plan.candidates[o] for o in s["object"]]
    poses = np.stack([c.poses[r] for c, r in zip(cands, s["object_candidate"])]).astype(np.float32)
    widths = np.asarray([c.widths[r] for c, r in zip(cands, s["object_candidate"])], np.float32)
    scene, mask = method.planner._scene(points, 7)
    graphdef, state = nnx.split(method.planner.model)
    expected = pg.score(graphdef, state, scene, poses, widths, mask, spec=SPEC, key=jax.random.key(7))
    np.testing.assert_allclose(s["eval_prob"], np.asarray(expected.prob), atol=1e-5)
    np.testing.assert_array_equal(s["valid"], np.asarray(expected.valid))
    if plan.pose is not None:
        assert plan.kind == "evaluated" and plan.score > method.config.eval_threshold
    # A network without a refinement head cannot run the refinement branch.
    with pytest.raises(ValueError, match="no refinement head"):
        Planner(model=method.planner.model, db=method.planner.stage1.db, config=PlannerConfig(use_refinement=True))
    assert isinstance(method, PlannerMethod)


@pytest.mark.slow  # Stage 1's compile (shared with the planner tests in a full run)
def test_planner_without_stage2_executes_stage1_order(observation):
    """`supergrasp-stage1` (w/o E-RNet): every candidate with scene points between its fingers scores 1, the
    others 0, and the planner executes the first passing one in Stage 1's order."""
    from sgjax.stage2 import crops

    points, labels, view = observation
    method = make_method("supergrasp-stage1", small_db=True)
    plan = method.full_plan(points, labels, view, seed=7)
    s = plan.scores
    assert len(s["eval_prob"]) > 0 and not np.any(s["refine_prob"])
    cands = [plan.candidates[o] for o in s["object"]]
    poses = np.stack([c.poses[r] for c, r in zip(cands, s["object_candidate"])]).astype(np.float32)
    widths = np.asarray([c.widths[r] for c, r in zip(cands, s["object_candidate"])], np.float32)
    scene, mask = method.planner._scene(points, 7)
    order = np.asarray(ernet.scene_order(len(scene), jax.random.key(7)))
    count = np.asarray(crops.crop_closing_regions(scene[order], poses, widths, SPEC, 1, mask[order]).count)
    np.testing.assert_array_equal(s["valid"], count > 0)
    np.testing.assert_array_equal(s["eval_prob"], (count > 0).astype(np.float32))
    first = int(np.flatnonzero(s["valid"])[0])
    assert plan.kind == "evaluated" and plan.candidate_index == first
    np.testing.assert_allclose(plan.pose, poses[first], atol=1e-5)


# ---------------------------------------------------------------------------------------------
# Contact-GraspNet.


def _venv(path):
    """A real, bare virtual environment at `path` (no pip: seconds)."""
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(path)], check=True)
    return cgn_setup.env_python(path)


def test_contact_graspnet_is_unavailable_with_setup_instructions(monkeypatch, tmp_path):
    monkeypatch.delenv(contact_graspnet.ENV_VAR, raising=False)
    monkeypatch.setenv("SGJAX_CACHE", str(tmp_path / "cache"))  # no environment at the default location
    with pytest.raises(MethodUnavailable, match=r"not available yet: SGJAX_CGN_PYTHON is not set .*"
                       r"run `sgjax baselines setup contact-graspnet`"):
        make_method("contact-graspnet")
    assert "contact-graspnet" not in method_names(available_only=True)
    monkeypatch.setenv(contact_graspnet.ENV_VAR, str(tmp_path / "no-python"))
    with pytest.raises(MethodUnavailable, match="is not an executable Python"):
        make_method("contact-graspnet")
    monkeypatch.setenv(contact_graspnet.ENV_VAR, sys.executable)  # sgjax's own env: no cgn_pytorch
    monkeypatch.setenv("PYTHONPATH", str(tmp_path))
    with pytest.raises(MethodUnavailable, match="has no cgn_pytorch module"):
        make_method("contact-graspnet")


def test_contact_graspnet_finds_the_setup_environment_by_default(monkeypatch, tmp_path):
    """The default location with real files: a venv without the setup's marker is an interrupted setup;
    with it, its python is used without any variable; SGJAX_CGN_PYTHON still overrides."""
    monkeypatch.delenv(contact_graspnet.ENV_VAR, raising=False)
    monkeypatch.setenv("SGJAX_CACHE", str(tmp_path / "cache"))
    prefix = tmp_path / "cache" / "envs" / "contact-graspnet"
    assert cgn_setup.default_prefix() == prefix and cgn_setup.state() == "absent"
    python = _venv(prefix)
    assert cgn_setup.state() == "incomplete" and cgn_setup.installed_python() is None
    assert contact_graspnet.interpreter() == (None, "")
    with pytest.raises(MethodUnavailable, match=r"incomplete \(an interrupted setup\); rerun `sgjax baselines setup"):
        make_method("contact-graspnet")
    (prefix / cgn_setup.MARKER).write_text("{}")
    assert cgn_setup.state() == "ready" and cgn_setup.installed_python() == python
    assert contact_graspnet.interpreter()[0] == str(python)
    # The found interpreter is the one probed: a cgn_pytorch on its path makes it available.
    monkeypatch.setenv("PYTHONPATH", str(tmp_path / "site"))
    assert "has no cgn_pytorch module" in contact_graspnet.missing()
    (tmp_path / "site" / "cgn_pytorch").mkdir(parents=True)
    (tmp_path / "site" / "cgn_pytorch" / "__init__.py").write_text("")
    contact_graspnet._probe.cache_clear()
    assert contact_graspnet.missing() is None
    monkeypatch.setenv(contact_graspnet.ENV_VAR, str(tmp_path / "elsewhere" / "python"))
    assert contact_graspnet.interpreter()[0] == str(tmp_path / "elsewhere" / "python")
    assert "is not an executable Python" in contact_graspnet.missing()


def test_setup_version_checks():
    assert cgn_setup.satisfied("torch==2.13.0", "2.13.0+cpu") and cgn_setup.satisfied("torch==2.13.0", "2.13.0")
    assert not cgn_setup.satisfied("torch==2.13.0", "2.13.1") and not cgn_setup.satisfied("torch==2.13.0", None)
    assert cgn_setup.satisfied("numpy<2", "1.26.4") and not cgn_setup.satisfied("numpy<2", "2.0.0rc1")
    assert cgn_setup.satisfied("scipy", "1.0") and not cgn_setup.satisfied("scipy", None)
    assert [cgn_setup.requirement_name(r) for r in ("numpy<2", "torch-cluster==1.6.3", "tqdm")] == [
        "numpy", "torch-cluster", "tqdm"]
    assert [s.requirements for s in cgn_setup.steps()] == [
        ("torch==2.13.0",), cgn_setup.DEPS, ("torch-cluster==1.6.3",), ("cgn-pytorch==0.4.3",)]
    cluster = cgn_setup.steps(max_jobs=3)[2]
    assert cluster.pip_args == ("--no-build-isolation", "--no-deps") and dict(cluster.env) == {
        "FORCE_ONLY_CPU": "1", "MAX_JOBS": "3"}


def _cgn_hand(rotation, contact, width, depth=contact_graspnet.PANDA_CONTACT_DEPTH):
    """A Panda hand pose placed as cgn_pytorch's CGN.build_6d_grasps places it: c - depth z + (w / 2) x."""
    hand = np.eye(4)
    hand[:3, :3] = rotation
    hand[:3, 3] = contact - depth * rotation[:, 2] + 0.5 * width * rotation[:, 0]
    return hand


def test_contact_graspnet_conversion_geometry():
    """Fingertips on the Panda's fingertip line (0.112204 - 0.1034 m beyond the contact baseline), the
    closing region centred between the two contacts (the width is signed: w < 0 puts the hand on the
    contact's -x side), the hand open to min(|w| + 5 mm, stroke)."""
    rng = np.random.default_rng(3)
    rotations = np.stack([np.linalg.qr(rng.normal(size=(3, 3)))[0] for _ in range(5)])
    rotations[:, :, 2] *= np.sign(np.linalg.det(rotations))[:, None]  # proper rotations
    contacts = rng.uniform(-0.1, 0.1, (5, 3))
    widths = np.array([0.0, 0.02, -0.05, 0.075, -0.08])
    offset = np.array([0.3, -0.2, 0.1])
    hands = np.stack([_cgn_hand(r, c, w) for r, c, w in zip(rotations, contacts, widths)])
    poses, opening = contact_graspnet.cgn_to_sgjax(hands, contacts, widths, offset, SPEC)
    np.testing.assert_allclose(poses[:, :3, :3], rotations, atol=1e-12)
    np.testing.assert_allclose(opening, [0.005, 0.025, 0.055, 0.08, 0.08])
    beyond = 0.112204 - 0.1034
    for pose, c, w, width in zip(poses, contacts + offset, widths, opening):
        other = c + w * pose[:3, 0]  # the second contact, across the predicted width
        local = (np.stack([c, other]) - pose[:3, 3]) @ pose[:3, :3]  # gripper frame
        # Centred: the contacts at x = -+w/2 on the closing axis (on either side), on the plane y = 0 ...
        np.testing.assert_allclose(local[:, 0], [-w / 2, w / 2], atol=1e-12)
        np.testing.assert_allclose(local[:, 1], 0.0, atol=1e-12)
        # ... and 8.8 mm behind the fingertips (z = finger_length), inside the open hand's closing region.
        np.testing.assert_allclose(local[:, 2], SPEC.finger_length - beyond, atol=1e-12)
        if width > abs(w):  # (at |w| = stroke the contacts lie on the fingers' faces)
            assert np.asarray(gripper.points_in_closing_region(np.stack([c, other]), pose, width, SPEC)).all()
        # The Panda hand frame maps to the same place: its fingertip line is ours.
        hand = _cgn_hand(pose[:3, :3], c, w)
        panda_tips = hand[:3, 3] + 0.112204 * hand[:3, 2]
        np.testing.assert_allclose(pose[:3, 3] + SPEC.finger_length * pose[:3, 2], panda_tips, atol=1e-12)
    with pytest.raises(ValueError, match="contacts and widths must be finite"):
        contact_graspnet.cgn_to_sgjax(hands[:1], contacts[:1], [np.nan], offset, SPEC)
    with pytest.raises(ValueError, match="got 5 grasps, 5 contacts and 4 widths"):
        contact_graspnet.cgn_to_sgjax(hands, contacts, widths[:4], offset, SPEC)


def test_contact_graspnet_chooses_the_most_confident_grasp_clear_of_the_table():
    config = contact_graspnet.CGNConfig()
    down = np.diag([1.0, -1.0, -1.0])  # approach straight down, closing along x
    side = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])  # approach along +x, closing along -z
    # A 4 cm-wide object on a table at z = 0: a top-down grasp 1.5 cm deep, and a side grasp across its
    # height whose lower finger reaches below the table top (CGN's training tolerated 2 cm of it).
    contacts = np.array([[-0.02, 0.0, 0.045], [0.0, 0.0, 0.04], [0.0, 0.0, 0.035], [0.3, 0.0, 0.01]])
    widths = np.array([0.04, 0.04, 0.04, 0.02])
    rotations = np.stack([down, side, down, down])
    hands = np.stack([_cgn_hand(r, c, w) for r, c, w in zip(rotations, contacts, widths)])
    poses, opening = contact_graspnet.cgn_to_sgjax(hands, contacts, widths, np.zeros(3), SPEC)
    heights = np.asarray(gripper.lowest_height(poses.astype(np.float32), opening.astype(np.float32), SPEC,
                                               np.array([0.0, 0.0, 1.0, 0.0])))
    assert heights[0] > 0.003 and heights[1] < 0.0 and heights[2] > 0.003
    confidence = np.array([0.7, 0.95, 0.6, 0.99])
    on_object = np.array([True, True, True, False])  # the last contact lies on the table
    best, reason, counts = contact_graspnet.choose(poses, opening, confidence, on_object, 0.0, config)
    assert (best, reason, counts) == (0, "", {"grasps": 3, "table": 1, "avoided": 0})
    # No table seen: the side grasp is the most confident one.
    assert contact_graspnet.choose(poses, opening, confidence, on_object, -np.inf, config)[0] == 1
    # The memory of failed grasps leaves the top-down grasp out; then the next one clear of the table.
    best, _, counts = contact_graspnet.choose(poses, opening, confidence, on_object, 0.0, config, avoid=poses[:1])
    assert best == 2 and counts["avoided"] == 1
    best, reason, _ = contact_graspnet.choose(poses, opening, confidence, on_object, 0.0, config, avoid=poses[[0, 2]])
    assert best is None and reason == "all 2 grasps clear of the table are the same grasp as one that already failed"
    best, reason, _ = contact_graspnet.choose(poses[1:2], opening[1:2], confidence[1:2], on_object[1:2], 0.0, config)
    assert best is None and reason == "all 1 grasps come closer than 3 mm to the table"
    best, reason, _ = contact_graspnet.choose(poses, opening, confidence * 0.5, on_object, 0.0, config)
    assert best is None and reason == "Contact-GraspNet found no grasp on an object above confidence 0.5"
    table = np.c_[np.zeros((5, 2)), [0.0, 0.001, -0.001, 0.0, 0.002]]
    assert contact_graspnet.table_height(np.r_[table, [[0, 0, 0.05]]], [-1] * 5 + [0]) == 0.0
    assert contact_graspnet.table_height(table, [0] * 5) == -np.inf
    # Backing off along the approach (CGNConfig.table_backoff): a top-down grasp 5 mm too low moves up
    # until it clears; the side grasp (approach horizontal) cannot, nor a grasp that needs more than allowed.
    lowered = poses.copy()
    lowered[0, 2, 3] -= heights[0] + 0.002  # its lowest point 2 mm below the table top
    moved = contact_graspnet.back_off(lowered, opening, 0.0, SPEC, 0.003, 0.02)
    np.testing.assert_allclose(moved[1:3], lowered[1:3])  # the side grasp; the one clear of the table
    np.testing.assert_allclose(moved[0, :3, :3], lowered[0, :3, :3])
    assert moved[0, 2, 3] - lowered[0, 2, 3] == pytest.approx(0.005, abs=2e-4)
    assert contact_graspnet.clears_table(moved[[0, 2, 3]], opening[[0, 2, 3]], 0.0, SPEC, 0.003).all()
    kept = contact_graspnet.back_off(lowered, opening, 0.0, SPEC, 0.003, 0.004)  # the first needs 5 mm
    np.testing.assert_allclose(kept[:3], lowered[:3])
    with pytest.raises(ValueError, match="CGNConfig.opening must be 'full' or 'predicted', got 'wide'"):
        contact_graspnet.CGNConfig(opening="wide")


@pytest.mark.skipif(contact_graspnet.missing() is not None,
                    reason="Contact-GraspNet's environment is not set up: run `sgjax baselines setup contact-graspnet`")
def test_contact_graspnet_real_inference_on_a_small_cloud(observation):
    """The real cgn-pytorch model out of process on a rendered tiny scene: the runner's replies follow
    the model's own geometry (hand = contact - 0.1034 z + w/2 x with the signed width w clamped to
    [-16, 8] cm, the model called with gripper_width 0.16), and the executed grasp is converted and chosen
    by the rules, repeatably."""
    points, labels, view = observation
    default = make_method("contact-graspnet").config  # the measured defaults (docs/benchmark.md)
    assert default.scene_bounds == workspace_bounds(LabelConfig().scene, LabelConfig().workspace_margin)
    assert (default.voxel, default.opening, default.threshold, default.table_backoff) == (0.003, "full", 0.5, 0.02)
    keep = np.random.default_rng(0).choice(len(points), 20000, replace=False)
    method = make_method("contact-graspnet", config=contact_graspnet.CGNConfig(voxel=0.0))
    try:
        raw = method.predict(points[keep], labels[keep] >= 0, seed=1)
        decision = method.plan(points, labels, view, seed=1)
        again = method.plan(points, labels, view, seed=1)
    finally:
        method.close()
    assert len(raw["confidence"]) >= 2048 and (np.diff(raw["confidence"]) <= 0).all()
    x, z, w = raw["grasps"][:, :3, 0], raw["grasps"][:, :3, 2], raw["widths"]
    shift = raw["grasps"][:, :3, 3] - (raw["contacts"] - 0.1034 * z)  # the hand's offset from the contact
    along = np.sum(shift * x, axis=1)
    np.testing.assert_allclose(shift, along[:, None] * x, atol=1e-5)  # along the closing axis only ...
    np.testing.assert_allclose(along, w / 2, atol=1e-5)  # ... by half the signed width
    assert -0.16 - 1e-6 <= w.min() and w.max() <= 0.08 + 1e-6
    on = raw["contacts"][raw["on_object"]]  # object flags: the contacts are object points
    assert len(on) and np.linalg.norm(on[:, None] - points[labels >= 0][None], axis=-1).min(1).max() < 1e-5
    assert decision.pose is not None, decision.reason
    np.testing.assert_allclose(again.pose, decision.pose)
    info = decision.info
    assert info["grasps"] >= 1 and decision.score > 0.5 and abs(info["table_z"]) < 0.002
    # The executed grasp: its contact baseline centred, 8.8 mm behind the fingertips, the hand fully open.
    contact, w = np.asarray(info["contact"]), info["predicted_width"]
    centre = decision.pose[:3, 3] + (SPEC.finger_length - (0.112204 - 0.1034)) * decision.pose[:3, 2]
    gap = contact + 0.5 * w * decision.pose[:3, 0] - centre  # 0, or backed off along the approach (<= 2 cm)
    back = gap @ decision.pose[:3, 2]
    np.testing.assert_allclose(gap, back * decision.pose[:3, 2], atol=1e-9)
    assert -1e-9 <= back <= 0.02 + 1e-9
    assert decision.width == SPEC.max_opening
    assert contact_graspnet.clears_table(decision.pose[None], [decision.width], info["table_z"], SPEC, 0.003).all()
    check_grasp(decision, points, labels)


def test_runner_seeds_libc_rand():
    import ctypes
    import ctypes.util

    from eval.cgn_runner import seed_everything

    libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
    seed_everything(123)
    first = [libc.rand() for _ in range(3)]
    seed_everything(123)
    assert [libc.rand() for _ in range(3)] == first
