"""Baselines and ablations: the PointNetGPD evaluator (crop, network, training, checkpoints), the methods
`pointnetgpd`, `s1+pointnetgpd` and `gpd+s2` on a tiny simulated scene, and the out-of-process
`contact-graspnet` adapter (unavailable without its environment; its runner protocol and frame
conversion against a fake `cgn_pytorch`)."""

from __future__ import annotations

import dataclasses
import json
import sys
import textwrap

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import nnx

from envs.camera import CameraConfig, observe
from envs.objects import tiny_object_set
from envs.scene import workspace_bounds
from eval import baselines, contact_graspnet
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
        params, opt_state, stats = train_step(params, opt_state, batch, jax.random.key(step))
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


def rigged_ernet(eval_bias, refine_bias):
    tiny = ERNetConfig.tiny(backbone=dataclasses.replace(ERNetConfig.tiny().backbone, sampler="random"))
    model = ERNet(tiny, rngs=nnx.Rngs(0))
    for head, bias in ((model.eval_head, eval_bias), (model.refine_head, refine_bias)):
        last = head.layers[-1]
        last.kernel[...] = jnp.zeros_like(last.kernel[...])
        last.bias[...] = jnp.asarray(bias, jnp.float32)
    return model


def test_gpd_with_stage2_follows_the_decision_policy(observation):
    points, labels, view = observation
    evaluated = make_method("gpd+s2", model=rigged_ernet([-2.0, 2.0], [-3.0, -3.0, -3.0]), config=CONFIG)
    decision = evaluated.plan(points, labels, view, seed=5)
    check_grasp(decision, points, labels)
    cands = evaluated.generator(points, labels, view, 5)
    assert decision.info["kind"] == "evaluated" and decision.score == pytest.approx(0.982, abs=1e-3)
    np.testing.assert_allclose(decision.pose, cands.poses[decision.info["index"]], atol=1e-6)
    # Low evaluation, high refinement of variant 1: the candidate is refined (deepened, rotated 0 deg).
    refined = make_method("gpd+s2", model=rigged_ernet([2.0, -2.0], [-3.0, 3.0, -3.0]), config=CONFIG)
    compiled = ernet.score._cache_size()
    decision = refined.plan(points, labels, view, seed=5)
    assert ernet.score._cache_size() == compiled  # same network shapes, same compile
    assert decision.info["kind"] == "refined" and decision.info["refine_variant"] == 1
    expected = np.asarray(gripper.refined_pose(cands.poses[decision.info["index"]], 1, SPEC))
    np.testing.assert_allclose(decision.pose, expected, atol=1e-5)
    # Neither above 0.7 (or refinement off): no grasp, and the reason says why.
    never = make_method("gpd+s2", model=rigged_ernet([2.0, -2.0], [-3.0, 3.0, -3.0]),
                        config=dataclasses.replace(CONFIG, use_refinement=False))
    decision = never.plan(points, labels, view, seed=5)
    assert decision.pose is None and "refinement disabled" in decision.reason


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


# ---------------------------------------------------------------------------------------------
# Contact-GraspNet.


def test_contact_graspnet_is_unavailable_with_setup_instructions(monkeypatch, tmp_path):
    monkeypatch.delenv(contact_graspnet.ENV_VAR, raising=False)
    with pytest.raises(MethodUnavailable, match=r"not available yet: SGJAX_CGN_PYTHON is not set.*cgn-pytorch"):
        make_method("contact-graspnet")
    assert "contact-graspnet" not in method_names(available_only=True)
    monkeypatch.setenv(contact_graspnet.ENV_VAR, str(tmp_path / "no-python"))
    with pytest.raises(MethodUnavailable, match="is not an executable Python"):
        make_method("contact-graspnet")
    monkeypatch.setenv(contact_graspnet.ENV_VAR, sys.executable)  # sgjax's own env: no cgn_pytorch
    monkeypatch.setenv("PYTHONPATH", str(tmp_path))
    with pytest.raises(MethodUnavailable, match="has no cgn_pytorch module"):
        make_method("contact-graspnet")


FAKE_CGN = '''
"""A stand-in for cgn_pytorch: two grasps at the masked points' centroid, checking the input contract."""
import numpy as np

def from_pretrained(device="cuda"):
    assert device == "cpu"
    print("Initializing net...")  # as the real package does, on stdout
    return "model", None, None

def inference(model, pcd, threshold=0.5, obj_mask=None):
    assert pcd.ndim == 2 and pcd.shape[1] == 3 and np.abs(pcd.mean(0)).max() < 1e-4, "not mean-subtracted"
    assert obj_mask.ndim == 1 and obj_mask.dtype == np.float32 and threshold == 0.5
    print("inference on", len(pcd), "points")
    c = pcd[obj_mask > 0].mean(0)
    down = np.array([[1.0, 0, 0], [0, -1.0, 0], [0, 0, -1.0]])  # approach straight down, closing along x
    grasps = np.tile(np.eye(4), (2, 1, 1))
    grasps[:, :3, :3] = down
    grasps[:, :3, 3] = c - 0.1034 * down[:, 2]  # contact baseline at the centroid
    grasps[0, :3, 3] += [0.05, 0, 0]
    return grasps, np.array([0.6, 0.9]), None
'''


def test_contact_graspnet_runner_protocol_and_frames(monkeypatch, tmp_path):
    (tmp_path / "cgn_pytorch").mkdir()
    (tmp_path / "cgn_pytorch" / "__init__.py").write_text(textwrap.dedent(FAKE_CGN))
    monkeypatch.setenv(contact_graspnet.ENV_VAR, sys.executable)
    monkeypatch.setenv("PYTHONPATH", str(tmp_path))
    default = make_method("contact-graspnet")  # crops to the benchmark's workspace, as SuperGrasp does
    assert default.config.scene_bounds == workspace_bounds(LabelConfig().scene, LabelConfig().workspace_margin)
    # No voxel grid here, so the fake's centroid is exactly the box's.
    method = make_method("contact-graspnet", config=contact_graspnet.CGNConfig(voxel=0.0))
    rng = np.random.default_rng(0)
    table = np.c_[rng.uniform(-0.2, 0.2, (500, 2)), np.zeros(500)]
    box = rng.uniform([0.05, 0.05, 0.0], [0.09, 0.07, 0.06], (300, 3))
    points, labels = np.r_[table, box], np.r_[np.full(500, -1), np.zeros(300, int)]
    try:
        decision = method.plan(points, labels, (0.0, 0.0, 1.0), seed=7)
        again = method.plan(points, labels, (0.0, 0.0, 1.0), seed=7)  # the same runner process
    finally:
        method.close()
    assert decision.info["grasps"] == 2 and decision.score == pytest.approx(0.9)
    np.testing.assert_allclose(again.pose, decision.pose)
    # Same axes; the sgjax fingertips (origin + finger_length * z) at the contact baseline (the centroid).
    np.testing.assert_allclose(decision.pose[:3, :3], np.diag([1.0, -1.0, -1.0]), atol=1e-12)
    np.testing.assert_allclose(decision.pose[:3, 3] + SPEC.finger_length * decision.pose[:3, 2], box.mean(0), atol=1e-6)
    assert decision.width == SPEC.max_opening and decision.timing["stage1_s"] == 0.0


def test_runner_seeds_libc_rand():
    import ctypes
    import ctypes.util

    from eval.cgn_runner import seed_everything

    libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
    seed_everything(123)
    first = [libc.rand() for _ in range(3)]
    seed_everything(123)
    assert [libc.rand() for _ in range(3)] == first
