"""PointNet++ ops against brute-force NumPy references; layers against their naive definitions."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import nnx

from sgjax.stage2 import pointnet2 as pn
from sgjax.stage2.pointnet2 import BackboneConfig, SetAbstractionConfig

SMALL = BackboneConfig(
    set_abstraction=(SetAbstractionConfig(16, 0.02, 8, (16, 16)), SetAbstractionConfig(4, 0.05, 8, (16, 24))),
    feature_propagation=((24,), (24, 20)),
    sampler="random",  # FPS inside a layer is covered by test_set_abstraction_equals_naive_grouping
)


# Jitted entry points: one compile per shape instead of one per eager op.
fps = jax.jit(pn.farthest_point_sampling, static_argnums=2)
ball_query = jax.jit(pn.ball_query, static_argnums=(3, 4))
first_true = jax.jit(pn.first_true_indices, static_argnums=1)
interpolate = jax.jit(pn.three_nn_interpolate)
call = nnx.jit(lambda module, *args: module(*args))


def random_cloud(seed: int, b: int = 3, n: int = 70, keep: float = 0.7):
    rng = np.random.default_rng(seed)
    points = rng.uniform(-0.03, 0.03, (b, n, 3)).astype(np.float32)
    mask = rng.random((b, n)) < keep
    return points, mask


# ---------------------------------------------------------------------------------------------
# References.


def fps_reference(points: np.ndarray, mask: np.ndarray, s: int):
    """Documented FPS semantics, one cloud at a time."""
    out_index, out_valid = [], []
    for p, m in zip(points, mask):
        real = np.flatnonzero(m)
        if len(real) == 0:
            out_index.append(np.zeros(s, int))
            out_valid.append(np.zeros(s, bool))
            continue
        chosen = [real[0]]
        dist = np.full(len(p), np.inf, np.float32)
        while len(chosen) < min(s, len(real)):
            d = np.sum((p - p[chosen[-1]]) ** 2, -1, dtype=np.float32)
            dist = np.minimum(dist, d)
            candidates = np.where(m, dist, -1.0)
            candidates[chosen] = -0.5
            chosen.append(int(np.argmax(candidates)))
        first = min(chosen)
        out_index.append(np.array(chosen + [first] * (s - len(chosen))))
        out_valid.append(np.arange(s) < len(real))
    return np.stack(out_index), np.stack(out_valid)


def ball_query_reference(points, mask, centres, radius, k):
    index = np.zeros(centres.shape[:2] + (k,), int)
    count = np.zeros(centres.shape[:2], int)
    for b in range(len(points)):
        for s in range(centres.shape[1]):
            d2 = np.sum((points[b] - centres[b, s]) ** 2, -1)
            found = np.flatnonzero((d2 <= radius**2) & mask[b])
            count[b, s] = len(found)
            if len(found):
                index[b, s] = np.concatenate([found[:k], np.full(max(0, k - len(found)), found[0])])
    return index, count


# ---------------------------------------------------------------------------------------------
# Ops.


@pytest.mark.parametrize("seed,keep,n_samples", [(0, 0.7, 20), (1, 1.0, 70), (2, 0.1, 20)])
def test_fps_matches_reference(seed, keep, n_samples):
    points, mask = random_cloud(seed, keep=keep)
    mask[-1] = False  # a cloud without real points
    mask[0, :3] = True
    index, valid = fps(points, mask, n_samples)
    ref_index, ref_valid = fps_reference(points, mask, n_samples)
    np.testing.assert_array_equal(np.asarray(valid), ref_valid)
    np.testing.assert_array_equal(np.asarray(index), ref_index)
    # Padded points are never chosen while real ones remain; enough real points -> all distinct.
    for b in range(len(points)):
        v = np.asarray(valid[b])
        assert mask[b][np.asarray(index[b])[v]].all()
        assert len(set(np.asarray(index[b])[v].tolist())) == v.sum()


def test_fps_spreads_points():
    # Two tight clusters far apart: the second sample must come from the other cluster.
    rng = np.random.default_rng(0)
    a = rng.normal(0.0, 1e-3, (20, 3))
    b = rng.normal(0.0, 1e-3, (20, 3)) + [0.1, 0, 0]
    points = np.concatenate([a, b])[None].astype(np.float32)
    index, _ = fps(points, None, 2)
    assert int(index[0, 0]) < 20 <= int(index[0, 1])


def test_nan_points_count_as_padding():
    points, mask = random_cloud(3)
    bad = points.copy()
    bad[0, 5] = np.nan
    mask_nan = mask.copy()
    mask_nan[0, 5] = True
    index, valid = fps(bad, mask_nan, 20)
    expected = mask.copy()
    expected[0, 5] = False
    ref_index, ref_valid = fps(points, expected, 20)
    np.testing.assert_array_equal(np.asarray(index), np.asarray(ref_index))
    np.testing.assert_array_equal(np.asarray(valid), np.asarray(ref_valid))


def test_ball_query_matches_reference():
    points, mask = random_cloud(4, n=90)
    centres = np.concatenate([points[:, :10], np.full((3, 2, 3), 1.0, np.float32)], axis=1)  # 2 far away
    for radius, k in ((0.01, 4), (0.02, 16), (0.2, 8)):
        index, count = ball_query(points, mask, centres, radius, k)
        ref_index, ref_count = ball_query_reference(points, mask, centres, radius, k)
        np.testing.assert_array_equal(np.asarray(count), ref_count)
        np.testing.assert_array_equal(np.asarray(index), ref_index)
    # Never a point beyond the radius (not k-NN), never a padded point.
    index, count = ball_query(points, mask, centres, 0.01, 8)
    grouped = np.stack([points[b][np.asarray(index[b])] for b in range(3)])  # [B, S, K, 3]
    d = np.linalg.norm(grouped - centres[:, :, None, :], axis=-1)
    found = np.asarray(count) > 0
    assert (d[found] <= 0.01 + 1e-7).all()
    assert all(mask[b][np.asarray(index[b])[found[b]]].all() for b in range(3))


@pytest.mark.parametrize("n,k", [(40, 10), (100, 100), (3000, 50)])
def test_first_true_indices(n, k):
    rng = np.random.default_rng(n)
    flags = rng.random((4, n)) < np.array([[0.0], [0.05], [0.5], [1.0]])
    index, count = first_true(jnp.asarray(flags), k)
    for row, idx, c in zip(flags, np.asarray(index), np.asarray(count)):
        expected = np.flatnonzero(row)
        assert c == len(expected)
        np.testing.assert_array_equal(idx[: min(k, c)], expected[:k])
        assert (idx[min(k, c) :] == n).all()


def test_three_nn_interpolate_matches_reference():
    rng = np.random.default_rng(5)
    query = rng.uniform(-1, 1, (2, 30, 3)).astype(np.float32)
    coarse = rng.uniform(-1, 1, (2, 8, 3)).astype(np.float32)
    mask = np.ones((2, 8), bool)
    mask[0, :6] = False  # only 2 real coarse points in cloud 0
    features = rng.normal(size=(2, 8, 5)).astype(np.float32)
    out = np.asarray(interpolate(query, coarse, mask, features))
    for b in range(2):
        real = np.flatnonzero(mask[b])
        for q in range(30):
            d = np.linalg.norm(coarse[b, real] - query[b, q], axis=-1)
            nearest = np.argsort(d)[:3]
            w = 1.0 / (d[nearest] + 1e-8)
            expected = (w[:, None] * features[b, real[nearest]]).sum(0) / w.sum()
            np.testing.assert_allclose(out[b, q], expected, rtol=1e-4, atol=1e-5)
    empty = interpolate(query, coarse, np.zeros((2, 8), bool), features)
    assert np.all(np.asarray(empty) == 0.0)


# ---------------------------------------------------------------------------------------------
# Layers.


def test_set_abstraction_equals_naive_grouping():
    points, mask = random_cloud(6)
    features = np.random.default_rng(6).normal(size=(3, 70, 5)).astype(np.float32)
    config = SetAbstractionConfig(12, 0.02, 6, (8, 16))
    layer = pn.SetAbstraction(config, 5, "fps", rngs=nnx.Rngs(0))
    _, valid, out = call(layer, points, mask, features)

    @nnx.jit
    def naive(layer):  # gather groups, concatenate [relative xyz / r, features], MLP, max
        index, _ = pn.farthest_point_sampling(points, mask, 12)
        group, _ = pn.ball_query(points, mask, pn.gather(points, index), 0.02, 6)
        rel = (pn.gather(points, group) - pn.gather(points, index)[:, :, None]) / 0.02
        return jnp.max(layer.mlp(jnp.concatenate([rel, pn.gather(features, group)], -1)), axis=2)

    naive = naive(layer)
    v = np.asarray(valid)
    np.testing.assert_allclose(np.asarray(out)[v], np.asarray(naive)[v], rtol=1e-5, atol=1e-5)
    assert np.all(np.asarray(out)[~v] == 0.0)


def test_feature_propagation_equals_naive():
    rng = np.random.default_rng(7)
    query, coarse = rng.uniform(-1, 1, (2, 20, 3)), rng.uniform(-1, 1, (2, 6, 3))
    cf, skip = rng.normal(size=(2, 6, 7)), rng.normal(size=(2, 20, 3))
    mask = np.ones((2, 6), bool)
    layer = pn.FeaturePropagation(10, (12, 9), rngs=nnx.Rngs(1))
    query, coarse, cf, skip = (np.asarray(a, np.float32) for a in (query, coarse, cf, skip))
    naive = nnx.jit(lambda mlp: mlp(jnp.concatenate([pn.three_nn_interpolate(query, coarse, mask, cf), skip], -1)))
    np.testing.assert_allclose(call(layer, query, coarse, mask, cf, skip), naive(layer.mlp), rtol=1e-5, atol=1e-5)


@pytest.fixture(scope="module")
def backbone():
    """(run, state): the SMALL backbone as one jitted function of (state, points, mask, query)."""
    graphdef, state = nnx.split(pn.PointNet2(SMALL, rngs=nnx.Rngs(0)))

    @jax.jit
    def run(state, points, mask, query=None):
        return nnx.merge(graphdef, state)(points, mask, query)

    return run, state


def test_backbone_query_equals_full_then_gather(backbone):
    run, state = backbone
    points, mask = random_cloud(8)
    full = run(state, points, mask)
    assert full.shape == (3, 70, 20)
    query = np.random.default_rng(8).integers(0, 70, (3, 11))
    np.testing.assert_allclose(run(state, points, mask, query), pn.gather(full, jnp.asarray(query)), rtol=1e-5, atol=1e-6)


def test_padding_does_not_change_real_features(backbone):
    run, state = backbone
    points, mask = random_cloud(9)
    moved = points.copy()
    moved[~mask] = np.random.default_rng(9).uniform(-0.03, 0.03, (int((~mask).sum()), 3))
    moved[0, np.flatnonzero(~mask[0])[0]] = np.nan
    a, b = run(state, points, mask), run(state, moved, mask)
    np.testing.assert_allclose(np.asarray(a)[mask], np.asarray(b)[mask], rtol=1e-5, atol=1e-6)
    assert np.isfinite(np.asarray(b)).all()


def test_no_recompile_and_random_sampler(backbone):
    run, state = backbone
    sizes = []
    for seed in (10, 11, 12):
        points, mask = random_cloud(seed)
        assert np.isfinite(np.asarray(run(state, points, mask))).all()
        sizes.append(run._cache_size())
    assert sizes[0] == sizes[1] == sizes[2]
    index, valid = jax.jit(pn.random_sampling, static_argnums=2)(points, mask, 16)
    np.testing.assert_array_equal(np.asarray(index)[0][np.asarray(valid)[0]], np.flatnonzero(mask[0])[:16])


def test_bad_shapes_raise():
    with pytest.raises(ValueError, match=r"points must have shape \[B, N, 3\]"):
        pn.farthest_point_sampling(np.zeros((4, 3)), None, 2)
    with pytest.raises(ValueError, match="mask must have shape"):
        pn.ball_query(np.zeros((1, 4, 3)), np.ones((1, 5), bool), np.zeros((1, 2, 3)), 0.1, 2)
    with pytest.raises(ValueError, match="one non-empty feature propagation"):
        BackboneConfig(SMALL.set_abstraction, ((8,),))
