"""E-RNet: crop geometry against sgjax.geometry.gripper, input preparation, losses, shapes, scoring, bad input."""

from __future__ import annotations

import json

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
from flax import nnx

from sgjax.stage2 import crops, ernet
from sgjax.geometry import gripper
from sgjax.stage2.ernet import ERNet, ERNetConfig
from sgjax.geometry.gripper import GripperSpec
from sgjax.geometry.rotations import random_rotation
from sgjax.geometry.superquadric import pose_matrix

SPEC = GripperSpec()
TINY = ERNetConfig.tiny()


def random_poses(seed: int, m: int) -> np.ndarray:
    k1, k2 = jax.random.split(jax.random.key(seed))
    rotation = random_rotation(k1, (m,))
    return np.array(pose_matrix(rotation, jax.random.uniform(k2, (m, 3), minval=-0.05, maxval=0.05)), np.float32)


def scene_near(poses: np.ndarray, n: int, seed: int) -> np.ndarray:
    """Points spread over the candidates' regions (gripper frame box around each region) in world."""
    rng = np.random.default_rng(seed)
    which = rng.integers(0, len(poses), n)
    local = rng.uniform([-0.06, -0.04, -0.01], [0.06, 0.04, 0.07], (n, 3))
    return np.einsum("nij,nj->ni", poses[which, :3, :3], local).astype(np.float32) + poses[which, :3, 3]


crop = jax.jit(crops.crop_regions, static_argnums=(3, 4))
in_closing = jax.jit(gripper.points_in_closing_region, static_argnums=3)
in_enlarged = jax.jit(gripper.points_in_enlarged_region, static_argnums=3)
to_local = jax.jit(gripper.to_gripper_frame)
N_SCENE, M = 2000, 4  # one compile of `score` serves every scoring test
prepare = jax.jit(ernet.prepare_inputs, static_argnums=(3, 4), static_argnames=("noise_std",))


def test_local_region_tests_match_gripper():
    poses = random_poses(0, 6)
    widths = np.array([0.02, 0.04, 0.06, 0.08, 0.07, 0.05], np.float32)
    world = scene_near(poses, N_SCENE, 0)
    local = np.asarray(to_local(world[None], poses))  # [M, N, 3]
    closing = np.asarray(in_closing(world[None], poses, widths, SPEC))
    enlarged = np.asarray(in_enlarged(world[None], poses, widths, SPEC))
    assert closing.any() and (enlarged & ~closing).any()
    np.testing.assert_array_equal(np.asarray(crops.in_closing_region_local(local, widths, SPEC)), closing)
    np.testing.assert_array_equal(np.asarray(crops.in_enlarged_region_local(local, widths, SPEC)), enlarged)


@pytest.mark.parametrize("seed,width,capacity", [(1, 0.07, 1024), (2, 0.08, 32)])
def test_crop_is_exactly_the_enlarged_region(seed, width, capacity):
    poses = random_poses(seed, 6)
    widths = np.full(6, width, np.float32)
    scene = scene_near(poses, N_SCENE, seed)
    region = crop(scene, poses, widths, SPEC, capacity)
    inside = np.asarray(in_enlarged(scene[None], poses, widths, SPEC))
    truncated = 0
    for m in range(6):
        found = np.flatnonzero(inside[m])
        assert int(region.count[m]) == len(found)
        mask = np.asarray(region.mask[m])
        assert mask.sum() == min(capacity, len(found))
        truncated += len(found) > capacity
        # The first region points in scene order, in the gripper frame; padding rows are 0.
        local = np.asarray(to_local(scene[found[:capacity]], poses[m]))
        np.testing.assert_allclose(np.asarray(region.points[m])[mask], local, atol=1e-6)
        assert np.all(np.asarray(region.points[m])[~mask] == 0.0)
    assert truncated == (6 if capacity == 32 else 0)


def test_chunked_crops_equal_testing_every_point(monkeypatch):
    """Crops test each chunk of candidates against the scene points in a box around their regions
    (crops.CHUNK, SUBSET_FRACTIONS) or, when the box holds too many, against all: the same crops as the
    region tests on every point, for the three region kinds, a subset tier and the fallback."""
    rng = np.random.default_rng(5)
    scene = np.c_[rng.uniform(-0.3, 0.3, (6000, 2)), rng.uniform(0.0, 0.1, 6000)].astype(np.float32)
    scene[::97] = np.nan  # absent points are never cropped
    m = crops.CHUNK + 6
    poses = random_poses(6, m)
    poses[: crops.CHUNK, :3, 3] = poses[: crops.CHUNK, :3, 3] * 0.2 + [0.2, 0.2, 0.05]  # chunk 0: one spot
    poses[crops.CHUNK :, :3, 3] = rng.uniform([-0.3, -0.3, 0.0], [0.3, 0.3, 0.1], (6, 3))  # chunk 1: everywhere
    widths = rng.uniform(0.03, 0.08, m).astype(np.float32)
    local = np.asarray(to_local(scene[None], poses))  # [M, N, 3]
    tests = {
        "crop_closing_regions": (crops.in_closing_region_local(local, widths, SPEC), "closing"),
        "crop_regions": (crops.in_enlarged_region_local(local, widths, SPEC), "enlarged"),
        "crop_swept_regions": (crops.in_swept_hand_local(local, widths, SPEC, crops.HAND_SWEEP, crops.HAND_MARGIN)
                               | crops.in_enlarged_region_local(local, widths, SPEC), "swept"),
    }
    for name, (inside, kind) in tests.items():
        inside = np.asarray(inside) & np.isfinite(scene).all(-1)
        # The setup exercises both paths: chunk 0's box holds a small share of the scene, chunk 1's most.
        centre, half = (np.asarray(a) for a in crops._local_bounds(SPEC, widths, kind, crops.HAND_SWEEP, crops.HAND_MARGIN))
        world_c = np.einsum("mij,mj->mi", poses[:, :3, :3], centre) + poses[:, :3, 3]
        world_h = np.einsum("mij,mj->mi", np.abs(poses[:, :3, :3]), half)
        share = [np.all((scene >= (world_c - world_h)[s].min(0)) & (scene <= (world_c + world_h)[s].max(0)), -1).mean()
                 for s in (slice(0, crops.CHUNK), slice(crops.CHUNK, m))]
        assert share[0] <= min(crops.SUBSET_FRACTIONS) and share[1] > max(crops.SUBSET_FRACTIONS)
        assert np.all(inside.sum(1) <= np.all((scene[None] >= (world_c - world_h)[:, None]) & (scene[None] <= (world_c + world_h)[:, None]), -1).sum(1))
        region = getattr(crops, name)(scene, poses, widths, SPEC, 64)
        for k in range(m):
            found = np.flatnonzero(inside[k])
            assert int(region.count[k]) == len(found), (name, k)
            kept = np.asarray(region.points[k])[np.asarray(region.mask[k])]
            np.testing.assert_allclose(kept, local[k, found[:64]], atol=1e-6)
        monkeypatch.setattr(crops, "SUBSET_FRACTIONS", ())  # every chunk tests every point
        every = getattr(crops, name)(scene, poses, widths, SPEC, 64)
        monkeypatch.undo()
        for a, b in zip(jax.tree.leaves(region), jax.tree.leaves(every)):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_prepare_inputs_anchor_is_the_closing_region():
    poses = random_poses(3, 6)
    widths = np.linspace(0.03, 0.08, 6).astype(np.float32)
    region = crop(scene_near(poses, N_SCENE, 3), poses, widths, SPEC, 1024)
    inputs = prepare(region.points, region.mask, widths, SPEC, TINY)
    points, mask = np.asarray(inputs.points), np.asarray(inputs.mask)
    for m in range(6):
        real = np.asarray(region.points[m])[np.asarray(region.mask[m])]
        n = min(len(real), TINY.n_points)
        assert mask[m].sum() == n
        np.testing.assert_allclose(points[m][mask[m]], real[:n])  # the first real points (shuffled scene)
        closing = np.flatnonzero(np.asarray(crops.in_closing_region_local(points[m][None], widths[m : m + 1], SPEC))[0] & mask[m])
        am = np.asarray(inputs.anchor_mask[m])
        np.testing.assert_array_equal(np.asarray(inputs.anchor_index[m])[am], closing[: TINY.n_anchor])
        # Points outside the enlarged region never reach the crop.
        assert np.asarray(crops.in_enlarged_region_local(points[m][mask[m]][None], widths[m : m + 1], SPEC)).all()


def test_prepare_inputs_training_noise_and_shuffle():
    poses = random_poses(4, 6)
    widths = np.full(6, 0.08, np.float32)
    region = crop(scene_near(poses, N_SCENE, 4), poses, widths, SPEC, 1024)
    a = prepare(region.points, region.mask, widths, SPEC, TINY, key=jax.random.key(0), noise_std=0.002)
    b = prepare(region.points, region.mask, widths, SPEC, TINY, key=jax.random.key(0), noise_std=0.002)
    c = prepare(region.points, region.mask, widths, SPEC, TINY, key=jax.random.key(1), noise_std=0.002)
    np.testing.assert_array_equal(np.asarray(a.points), np.asarray(b.points))  # same key, same result
    assert not np.array_equal(np.asarray(a.points), np.asarray(c.points))
    for m in range(6):
        kept = np.asarray(a.points[m])[np.asarray(a.mask[m])]
        assert np.asarray(crops.in_enlarged_region_local(kept[None], widths[m : m + 1], SPEC)).all()
        # Each kept point is a source point moved by noise only (a few mm at most).
        src = np.asarray(region.points[m])[np.asarray(region.mask[m])]
        d = np.min(np.linalg.norm(kept[:, None] - src[None], axis=-1), axis=1)
        assert d.max() < 0.002 * 6 and d.mean() > 1e-4


def test_losses_match_paper_equations():
    rng = np.random.default_rng(0)
    logits = rng.normal(size=(9, 2)).astype(np.float32)
    labels = rng.integers(0, 2, 9)
    eps = 0.1
    log_p = logits - np.log(np.exp(logits).sum(-1, keepdims=True))
    expected = -np.mean((1 - eps) * log_p[np.arange(9), labels] + eps / 2 * log_p.sum(-1))
    np.testing.assert_allclose(ernet.evaluation_loss(logits, labels, eps), expected, rtol=1e-6)
    smoothed = optax.smooth_labels(jax.nn.one_hot(labels, 2), eps)
    np.testing.assert_allclose(ernet.evaluation_loss(logits, labels, eps), optax.softmax_cross_entropy(logits, smoothed).mean(), rtol=1e-6)
    z = rng.normal(size=(9, 3)).astype(np.float32)
    y = rng.integers(0, 2, (9, 3))
    sig = 1 / (1 + np.exp(-z))
    np.testing.assert_allclose(ernet.refinement_loss(z, y), -np.mean(y * np.log(sig) + (1 - y) * np.log(1 - sig)), rtol=1e-5)
    # Zero-weight rows (padding) do not count; all-zero weights give 0, not NaN.
    w = np.r_[np.ones(5), np.zeros(4)].astype(np.float32)
    np.testing.assert_allclose(ernet.evaluation_loss(logits, labels, eps, w), ernet.evaluation_loss(logits[:5], labels[:5], eps), rtol=1e-6)
    assert float(ernet.refinement_loss(z, y, np.zeros(9))) == 0.0
    out = ernet.ERNetOutput(jnp.asarray(logits), jnp.asarray(z))
    total, parts = ernet.ernet_loss(out, labels, y, ERNetConfig(lambda_eval=2.0, lambda_refine=0.5))
    np.testing.assert_allclose(total, 2.0 * parts["eval"] + 0.5 * parts["refine"], rtol=1e-6)


def test_anchor_feature_masked_max():
    f = jnp.asarray([[[1.0, -2.0], [3.0, -1.0], [9.0, 9.0]], [[1.0, 1.0], [2.0, 2.0], [3.0, 3.0]]])
    mask = jnp.asarray([[True, True, False], [False, False, False]])
    np.testing.assert_array_equal(ernet.anchor_feature(f, mask), [[3.0, -1.0], [0.0, 0.0]])


def test_paper_sizes_shapes():
    """960 / 345 points, N x 128 point features, 1 x 256 anchor feature (shape evaluation only)."""
    config = ERNetConfig.paper()
    model = ernet.abstract_model(config)
    m = 2
    inputs = ernet.ERNetInputs(
        jnp.zeros((m, 960, 3)), jnp.ones((m, 960), bool), jnp.zeros((m, 345), jnp.int32), jnp.ones((m, 345), bool),
        jnp.zeros((m, 0, 3)), jnp.zeros((m, 0), bool),
    )
    features = nnx.eval_shape(lambda mdl, i: mdl.backbone(i.points, i.mask), model, inputs)
    assert features.shape == (m, 960, 128)
    anchor = nnx.eval_shape(
        lambda mdl, i: ernet.anchor_feature(mdl.anchor_mlp(mdl.backbone(i.points, i.mask, i.anchor_index)), i.anchor_mask),
        model,
        inputs,
    )
    assert anchor.shape == (m, 256)
    out = nnx.eval_shape(lambda mdl, i: mdl(i), model, inputs)
    assert out.eval_logits.shape == (m, 2) and out.refine_logits.shape == (m, 3)


def test_config_round_trip_and_checks():
    for config in (ERNetConfig.paper(), ERNetConfig.light(), TINY, ERNetConfig.tiny(hand_points=8)):
        assert ERNetConfig.from_dict(config.to_dict()) == config
        assert ERNetConfig.from_dict(json.loads(json.dumps(config.to_dict()))) == config  # as a checkpoint stores it
    with pytest.raises(ValueError, match="unknown fields.*bogus"):
        ERNetConfig.from_dict({**TINY.to_dict(), "bogus": 1})
    with pytest.raises(ValueError, match="n_anchor"):
        ERNetConfig(n_points=10, n_anchor=20)
    with pytest.raises(ValueError, match="3 layers"):
        ERNetConfig(eval_hidden=(8,))


@pytest.fixture(scope="module")
def tiny_model():
    model = ERNet(TINY, rngs=nnx.Rngs(0))
    return nnx.split(model)


def test_score_batch_and_masks(tiny_model):
    graphdef, state = tiny_model
    poses = random_poses(5, M)
    widths = np.full(M, 0.07, np.float32)
    scene = scene_near(poses[:2], N_SCENE, 5)
    poses[2, :3, 3] += 5.0  # far from every point: empty region
    poses[3, 0, 0] = np.nan  # broken pose
    keep = np.ones(N_SCENE, bool)
    out = ernet.score(graphdef, state, scene, poses, widths, keep)
    assert out.eval_prob.shape == (M,) and out.refine_prob.shape == (M, 3)
    valid = np.asarray(out.valid)
    np.testing.assert_array_equal(valid, [True, True, False, False])
    assert np.isfinite(np.asarray(out.eval_prob)).all() and np.isfinite(np.asarray(out.refine_prob)).all()
    assert np.all(np.asarray(out.eval_prob)[~valid] == 0) and np.all(np.asarray(out.refine_prob)[~valid] == 0)
    assert ((np.asarray(out.eval_prob)[valid] > 0) & (np.asarray(out.eval_prob)[valid] < 1)).all()

    # NaN scene points are ignored: the same result as masking them out.
    noisy = scene.copy()
    noisy[::7] = np.nan
    masked = keep.copy()
    masked[::7] = False
    a = ernet.score(graphdef, state, noisy, poses, widths, keep)
    b = ernet.score(graphdef, state, scene, poses, widths, masked)
    np.testing.assert_array_equal(np.asarray(a.eval_prob), np.asarray(b.eval_prob))
    assert np.isfinite(np.asarray(a.eval_prob)).all()

    # A candidate's score does not depend on the other candidates in the batch.
    flipped = ernet.score(graphdef, state, scene, poses[::-1].copy(), widths, keep)
    np.testing.assert_allclose(np.asarray(flipped.eval_prob)[::-1], out.eval_prob, rtol=1e-5)
    np.testing.assert_allclose(np.asarray(flipped.refine_prob)[::-1], out.refine_prob, rtol=1e-5)


def test_score_no_recompile(tiny_model):
    graphdef, state = tiny_model
    widths = np.full(M, 0.06, np.float32)
    keep = np.ones(N_SCENE, bool)
    sizes = []
    for seed in (10, 11, 12):
        poses = random_poses(seed, M)
        jax.block_until_ready(ernet.score(graphdef, state, scene_near(poses, N_SCENE, seed), poses, widths, keep))
        sizes.append(ernet.score._cache_size())
    assert sizes[0] == sizes[1] == sizes[2]


def test_score_regions_matches_score(tiny_model):
    graphdef, state = tiny_model
    poses = random_poses(6, M)
    widths = np.full(M, 0.07, np.float32)
    scene = scene_near(poses, N_SCENE, 6)
    out = ernet.score(graphdef, state, scene, poses, widths, np.ones(N_SCENE, bool))
    order = np.asarray(jax.random.permutation(jax.random.key(0), N_SCENE))
    region = crop(scene[order], poses, widths, SPEC, TINY.n_points)
    again = ernet.score_regions(graphdef, state, region.points, region.mask, widths)
    np.testing.assert_allclose(again.eval_prob, out.eval_prob, rtol=1e-5)
    np.testing.assert_array_equal(again.valid, out.valid)


def test_bad_inputs_raise_clear_errors(tiny_model):
    graphdef, state = tiny_model
    poses = random_poses(7, M)
    widths = np.full(M, 0.05, np.float32)
    scene = scene_near(poses, N_SCENE, 7)
    keep = np.ones(N_SCENE, bool)
    with pytest.raises(ValueError, match=r"scene must have shape \[N, 3\]"):
        ernet.score(graphdef, state, scene[:, :2], poses, widths)
    with pytest.raises(ValueError, match=r"poses must have shape \[M, 4, 4\]"):
        ernet.score(graphdef, state, scene, poses[:, :3], widths)
    with pytest.raises(ValueError, match="widths must have shape"):
        ernet.score(graphdef, state, scene, poses, widths[:1])
    with pytest.raises(ValueError, match="scene_mask must have shape"):
        ernet.score(graphdef, state, scene, poses, widths, keep[:5])
    with pytest.raises(ValueError, match="n_refinements"):
        ernet.score(graphdef, state, scene, poses, widths, spec=GripperSpec(refine_angles_deg=(0.0, 10.0)))
    with pytest.raises(ValueError, match="region points must have shape"):
        prepare(np.zeros((2, 5)), None, widths, SPEC, TINY)
    # Out-of-range widths make invalid candidates, never NaN.
    out = ernet.score(graphdef, state, scene, poses, np.array([0.5, -1.0, np.nan, 0.05], np.float32), keep)
    np.testing.assert_array_equal(np.asarray(out.valid)[:3], [False, False, False])
    assert np.all(np.asarray(out.eval_prob)[:3] == 0) and np.isfinite(np.asarray(out.eval_prob)).all()


def _box_scene(rng, obstacle: bool) -> np.ndarray:
    """A 4 cm cube at the origin's closing region (points on its surface, world = gripper frame) and,
    with `obstacle`, a neighbour's face in the path of the right finger 2-4 cm before the grasp."""
    cube = rng.uniform(-0.02, 0.02, (1500, 3))
    axis = rng.integers(0, 3, 1500)
    cube[np.arange(1500), axis] = np.sign(cube[np.arange(1500), axis]) * 0.02
    cube[:, 2] += 0.03  # between the fingertips (z 0..0.05)
    if not obstacle:
        return cube.astype(np.float32)
    wall = np.stack([rng.uniform(0.036, 0.05, 300), rng.uniform(-0.01, 0.01, 300), rng.uniform(-0.04, -0.02, 300)], -1)
    return np.concatenate([cube, wall]).astype(np.float32)


def test_swept_input_sees_what_the_fingers_would_hit():
    """An obstacle in the right finger's approach path lies outside the enlarged region: the paper's
    input cannot see it (identical scores), the swept input crops it as hand points and its scores change."""
    spec = ernet.DEFAULT_SPEC
    poses, widths = np.eye(4, dtype=np.float32)[None], np.asarray([0.07], np.float32)
    clear = _box_scene(np.random.default_rng(0), False)
    blocked = _box_scene(np.random.default_rng(0), True)  # the same cube, the wall appended
    wall = blocked[len(clear):]
    assert not np.asarray(crops.in_enlarged_region_local(wall[None], widths, spec)).any()
    assert np.asarray(crops.in_swept_hand_local(wall[None], widths, spec, crops.HAND_SWEEP, crops.HAND_MARGIN)).all()
    swept = crops.crop_swept_regions(blocked, poses, widths, spec, 4096)
    assert int(swept.count[0]) == int(crops.crop_regions(blocked, poses, widths, spec, 4096).count[0]) + len(wall)

    with pytest.raises(ValueError, match="unknown crop 'hand'"):
        crops.crop_function("hand")
    for config, changes in ((TINY, False), (ERNetConfig.tiny(hand_points=32), True)):
        crop = crops.crop_function(config.crop)  # the network's own input, as Stage 2 and training crop it
        graphdef, state = nnx.split(ERNet(config, rngs=nnx.Rngs(0)))
        a, b = (crop(scene, poses, widths, spec, 4096) for scene in (clear, blocked))
        sa = ernet.score_regions(graphdef, state, a.points, a.mask, widths, spec=spec)
        sb = ernet.score_regions(graphdef, state, b.points, b.mask, widths, spec=spec)
        assert bool(sa.valid[0]) and bool(sb.valid[0])
        assert (abs(float(sa.eval_prob[0]) - float(sb.eval_prob[0])) > 1e-6) == changes
        inputs = ernet.prepare_inputs(b.points, b.mask, widths, spec, config)
        assert int(inputs.hand_mask.sum()) == (min(config.hand_points, len(wall)) if changes else 0)
        # The whole Stage 2 (crop of a shuffled scene, network) runs on either input.
        assert bool(ernet.score(graphdef, state, blocked, poses, widths, spec=spec).valid[0])
