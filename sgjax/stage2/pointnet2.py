"""PointNet++ backbone ops and layers in JAX / Flax NNX: masked, fixed-shape, jit-friendly.

Qi et al., "PointNet++", NeurIPS 2017: farthest point sampling, ball query grouping, set abstraction
(SSG: one radius per level) and feature propagation (inverse-distance 3-NN interpolation + skip + MLP).

Every op takes padded batches `points[B, N, 3]` with `mask[B, N]` (True = real point) and keeps fixed
shapes, so a jitted caller compiles once per (B, N). Padded points are never sampled or grouped
(except where fewer real points than samples exist, handled deterministically, see each op), and
non-finite coordinates count as padding.

CPU speed notes (measured on the 2-core dev machine, see benchmarks/bench_ernet.py): pairwise work is
done on separate x/y/z planes (a trailing axis of 3 is ~50x slower in XLA:CPU), the "first k True"
selections pack flags into 32-bit words and select bits instead of running cumsum/sort/top_k over N,
and argmax is written as max + first-index-of-max, which vectorises.
"""

from __future__ import annotations

import dataclasses
import itertools
from collections.abc import Sequence
from typing import Literal

import jax
import jax.numpy as jnp
from flax import nnx
from jax import lax

_WORD = 32  # bits per packed word


# ---------------------------------------------------------------------------------------------
# Shape checks (static, run at trace time).


def _check_points(points, name: str = "points") -> jax.Array:
    points = jnp.asarray(points)
    if points.ndim != 3 or points.shape[-1] != 3:
        raise ValueError(f"{name} must have shape [B, N, 3], got {points.shape}")
    return points


def _check_mask(mask, points: jax.Array) -> jax.Array:
    """The mask as bool[B, N] with non-finite points removed (None: every finite point)."""
    finite = jnp.all(jnp.isfinite(points), axis=-1)
    if mask is None:
        return finite
    mask = jnp.asarray(mask)
    if mask.shape != points.shape[:-1]:
        raise ValueError(f"mask must have shape {points.shape[:-1]} (points {points.shape}), got {mask.shape}")
    return mask.astype(bool) & finite


def _planes(points: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
    """points[..., 3] -> x, y, z planes [...], non-finite coordinates replaced by 0 (they are masked)."""
    points = jnp.where(jnp.isfinite(points), points, 0.0)
    return points[..., 0], points[..., 1], points[..., 2]


# ---------------------------------------------------------------------------------------------
# Selection helpers.


def argmax_first(values: jax.Array) -> jax.Array:
    """Index of the first maximum along the last axis: [..., N] -> int32[...] (vectorises on CPU)."""
    n = values.shape[-1]
    top = jnp.max(values, axis=-1, keepdims=True)
    return jnp.min(jnp.where(values == top, jnp.arange(n, dtype=jnp.int32), n), axis=-1)


def argmin_first(values: jax.Array) -> jax.Array:
    """Index of the first minimum along the last axis: [..., N] -> int32[...]."""
    n = values.shape[-1]
    low = jnp.min(values, axis=-1, keepdims=True)
    return jnp.min(jnp.where(values == low, jnp.arange(n, dtype=jnp.int32), n), axis=-1)


def pack_flags(flags: jax.Array) -> jax.Array:
    """bool[..., N] -> uint32[..., ceil(N/32)]: bit j of word w is flags[..., 32 w + j] (zero-padded)."""
    n = flags.shape[-1]
    words = -(-n // _WORD)
    flags = jnp.pad(flags, [(0, 0)] * (flags.ndim - 1) + [(0, words * _WORD - n)])
    bits = flags.reshape(*flags.shape[:-1], words, _WORD).astype(jnp.uint32)
    return jnp.sum(bits << jnp.arange(_WORD, dtype=jnp.uint32), axis=-1, dtype=jnp.uint32)


def interleave(values: jax.Array, fill=0) -> jax.Array:
    """[..., N] -> [..., 32, W] with out[..., j, w] = values[..., 32 w + j] (N padded with `fill`).

    Flags computed elementwise on interleaved inputs pack with `pack_interleaved`, a reduction over a
    major axis that vectorises (packing along the minor axis, as `pack_flags` does, is ~3x slower)."""
    n = values.shape[-1]
    words = -(-n // _WORD)
    values = jnp.pad(values, [(0, 0)] * (values.ndim - 1) + [(0, words * _WORD - n)], constant_values=fill)
    return jnp.swapaxes(values.reshape(*values.shape[:-1], words, _WORD), -1, -2)


def pack_interleaved(flags: jax.Array) -> jax.Array:
    """bool[..., 32, W] (flags of `interleave`d inputs) -> uint32[..., W], the same words as
    `pack_flags` of the original order."""
    bits = flags.astype(jnp.uint32) << jnp.arange(_WORD, dtype=jnp.uint32)[:, None]
    return jnp.sum(bits, axis=-2, dtype=jnp.uint32)


def _select_bit(word: jax.Array, rank: jax.Array) -> jax.Array:
    """Position of the rank-th (0-based) set bit of each uint32 word (rank < popcount): int32."""
    pos = jnp.zeros(rank.shape, jnp.int32)
    for step in (16, 8, 4, 2, 1):
        below = (jnp.uint32(1) << (pos + step).astype(jnp.uint32)) - jnp.uint32(1)
        count = lax.population_count(word & below).astype(jnp.int32)
        pos = jnp.where(count <= rank, pos + step, pos)
    return pos


def first_true_indices(flags: jax.Array, k: int) -> tuple[jax.Array, jax.Array]:
    """Indices of the first k True entries along the last axis, in order.

    flags bool[..., N] -> (index int32[..., k], count int32[...]), where count is the total number of
    True entries (may exceed k). Slots j >= count hold N (out of range: mask them with j < count).
    """
    return first_set_bits(pack_flags(flags), flags.shape[-1], k)


def first_set_bits(words: jax.Array, n: int, k: int) -> tuple[jax.Array, jax.Array]:
    """`first_true_indices` of flags already packed by `pack_flags`: words uint32[..., W] for n flags."""
    per_word = lax.population_count(words).astype(jnp.int32)
    inclusive = jnp.cumsum(per_word, axis=-1)
    count = inclusive[..., -1]
    slots = jnp.arange(k, dtype=jnp.int32)
    n_words = words.shape[-1]
    if n_words <= 64:  # compare-all is cheaper than a search over a handful of words
        word = jnp.sum(inclusive[..., None, :] <= slots[:, None], axis=-1, dtype=jnp.int32)
    else:
        flat = inclusive.reshape(-1, n_words)
        word = jax.vmap(lambda row: jnp.searchsorted(row, slots, side="right", method="scan_unrolled"))(flat)
        word = word.reshape(*inclusive.shape[:-1], k).astype(jnp.int32)
    word = jnp.minimum(word, n_words - 1)
    before = jnp.take_along_axis(inclusive - per_word, word, axis=-1)
    bit = _select_bit(jnp.take_along_axis(words, word, axis=-1), slots - before)
    index = jnp.where(slots < count[..., None], word * _WORD + bit, n)
    return index, count


def gather(values: jax.Array, index: jax.Array) -> jax.Array:
    """Per-batch gather along axis 1: values[B, N, ...], index int[B, *I] -> [B, *I, ...]."""
    b, batch_index = index.shape[0], index.shape[1:]
    flat = index.reshape(b, -1)
    out = jnp.take_along_axis(values, flat.reshape(b, -1, *([1] * (values.ndim - 2))), axis=1)
    return out.reshape(b, *batch_index, *values.shape[2:])


# ---------------------------------------------------------------------------------------------
# Sampling and grouping.


def farthest_point_sampling(points: jax.Array, mask: jax.Array | None, n_samples: int) -> tuple[jax.Array, jax.Array]:
    """Masked farthest point sampling.

    points[B, N, 3], mask[B, N] (None: all finite points) -> (index int32[B, S], valid bool[B, S]).
    Starts at the first real point (PointNet++ starts at index 0) and repeatedly takes the real point
    farthest from those chosen, ties to the lowest index. Padded points are never chosen. With fewer
    than S real points, every real point is chosen once, the remaining slots repeat the lowest-index
    chosen point and are marked valid=False; with none, index 0 and valid=False everywhere.
    """
    points = _check_points(points)
    mask = _check_mask(mask, points)
    x, y, z = _planes(points)
    n = points.shape[1]
    arange = jnp.arange(n, dtype=jnp.int32)
    # Distances to the chosen set: +inf for unvisited real points, -0.5 once chosen (so a real point is
    # never chosen twice while others remain), -1 for padding (never chosen while real points remain).
    dist = jnp.where(mask, jnp.inf, -1.0).astype(x.dtype)
    first = argmax_first(mask.astype(jnp.int32))

    def visit(carry, _):
        dist, last = carry
        at = last[:, None]
        px, py, pz = (jnp.take_along_axis(c, at, axis=1) for c in (x, y, z))
        d = (x - px) ** 2 + (y - py) ** 2 + (z - pz) ** 2
        dist = jnp.where(arange == at, -0.5, jnp.where(dist < 0, dist, jnp.minimum(dist, d)))
        return (dist, argmax_first(dist)), last

    _, index = lax.scan(visit, (dist, first), None, length=n_samples)
    index = index.T
    valid = jnp.arange(n_samples) < jnp.sum(mask, axis=-1, keepdims=True)
    return index, valid


def random_sampling(points: jax.Array, mask: jax.Array | None, n_samples: int) -> tuple[jax.Array, jax.Array]:
    """The first S real points in index order: a uniform random sample when the points are shuffled.

    Same contract as `farthest_point_sampling` (slots beyond the number of real points repeat the
    first one and are valid=False). E-RNet's input preparation shuffles points, so this is random
    sampling at no cost; it replaces FPS in the CPU config (see ernet.ERNetConfig).
    """
    points = _check_points(points)
    mask = _check_mask(mask, points)
    index, count = first_true_indices(mask, n_samples)
    valid = jnp.arange(n_samples) < count[:, None]
    index = jnp.where(valid, index, jnp.where(count[:, None] > 0, index[:, :1], 0))
    return index, valid


def ball_query(
    points: jax.Array, mask: jax.Array | None, centres: jax.Array, radius: float, n_neighbours: int
) -> tuple[jax.Array, jax.Array]:
    """PointNet++ ball query: for each centre, the first K real points (index order) within radius.

    points[B, N, 3], mask[B, N], centres[B, S, 3] -> (index int32[B, S, K], count int32[B, S]), count
    being the number of real points within the radius (may exceed K). As in PointNet++, slots beyond
    the count repeat the first point found, so max-pooling over K is unaffected; a centre with no
    point within the radius gets index 0 and count 0 (mask it). Not k-nearest-neighbours: points
    beyond the radius are never returned.
    """
    points = _check_points(points)
    centres = _check_points(centres, "centres")
    if centres.shape[0] != points.shape[0]:
        raise ValueError(f"centres batch {centres.shape[0]} != points batch {points.shape[0]}")
    mask = _check_mask(mask, points)
    # Padding and absent points become NaN, so every distance test with them is False.
    x, y, z = (interleave(jnp.where(mask, c, jnp.nan), jnp.nan)[:, None] for c in _planes(points))  # [B, 1, 32, W]
    cx, cy, cz = (c[..., None, None] for c in _planes(centres))  # [B, S, 1, 1]
    within = (cx - x) ** 2 + (cy - y) ** 2 + (cz - z) ** 2 <= radius * radius
    index, count = first_set_bits(pack_interleaved(within), points.shape[1], n_neighbours)
    slots = jnp.arange(n_neighbours)
    fill = jnp.where(count[..., None] > 0, index[..., :1], 0)
    return jnp.where(slots < count[..., None], index, fill), count


def three_nn_interpolate(
    query: jax.Array, points: jax.Array, mask: jax.Array | None, features: jax.Array
) -> jax.Array:
    """Inverse-distance weighted mean of the features of the 3 nearest real points (PointNet++ FP).

    query[B, Q, 3], points[B, S, 3], mask[B, S], features[B, S, C] -> [B, Q, C]. Weights are
    1 / (euclidean distance + 1e-8), normalised; with fewer than 3 real points only those count, with
    none the result is 0.
    """
    query, points = _check_points(query, "query"), _check_points(points)
    mask = _check_mask(mask, points)
    qx, qy, qz = _planes(query)
    x, y, z = _planes(points)
    d2 = (qx[..., None] - x[:, None]) ** 2 + (qy[..., None] - y[:, None]) ** 2 + (qz[..., None] - z[:, None]) ** 2
    d2 = jnp.where(mask[:, None, :], d2, jnp.inf)
    # The 3-NN weights as a dense [B, Q, S] matrix (3 non-zeros per row): one batched matmul instead of
    # gathering 3 x C features per query (memory-bound on CPU).
    arange = jnp.arange(d2.shape[-1], dtype=jnp.int32)
    weights = jnp.zeros(d2.shape, d2.dtype)
    for _ in range(3):
        pick = arange == argmin_first(d2)[..., None]
        nearest = jnp.min(d2, axis=-1, keepdims=True)
        inverse = jnp.where(jnp.isfinite(nearest), 1.0 / (jnp.sqrt(nearest) + 1e-8), 0.0)
        weights = jnp.where(pick, inverse, weights)
        d2 = jnp.where(pick, jnp.inf, d2)
    weights = weights / jnp.maximum(jnp.sum(weights, -1, keepdims=True), 1e-30)
    return jnp.einsum("bqs,bsc->bqc", weights, features)


# ---------------------------------------------------------------------------------------------
# Layers.


@dataclasses.dataclass(frozen=True)
class SetAbstractionConfig:
    """One SSG set abstraction level: sample `n_centroids`, group `n_neighbours` within `radius` (m),
    shared MLP of widths `mlp` on [relative xyz / radius, features], max-pool over the group."""

    n_centroids: int
    radius: float
    n_neighbours: int
    mlp: tuple[int, ...]

    def __post_init__(self):
        object.__setattr__(self, "mlp", tuple(int(c) for c in self.mlp))
        if self.n_centroids < 1 or self.n_neighbours < 1 or not self.radius > 0 or not self.mlp:
            raise ValueError(f"invalid set abstraction config {self}")


@dataclasses.dataclass(frozen=True)
class BackboneConfig:
    """PointNet++ (SSG) backbone: set abstraction levels (fine to coarse), then one feature propagation
    MLP per level (applied coarse to fine; the last one's width is the per-point feature size).

    sampler: "fps" (farthest point sampling, PointNet++) or "random" (the first real points of the
        shuffled input; no sequential loop).
    coord_scale: metres -> network units for the raw xyz fed to the last feature propagation.
    """

    set_abstraction: tuple[SetAbstractionConfig, ...]
    feature_propagation: tuple[tuple[int, ...], ...]
    sampler: Literal["fps", "random"] = "fps"
    coord_scale: float = 0.05

    def __post_init__(self):
        object.__setattr__(self, "set_abstraction", tuple(self.set_abstraction))
        object.__setattr__(self, "feature_propagation", tuple(tuple(int(c) for c in m) for m in self.feature_propagation))
        if not self.set_abstraction:
            raise ValueError("a backbone needs at least one set abstraction level")
        if len(self.feature_propagation) != len(self.set_abstraction) or not all(self.feature_propagation):
            raise ValueError("need one non-empty feature propagation MLP per set abstraction level")
        if self.sampler not in ("fps", "random"):
            raise ValueError(f"sampler must be 'fps' or 'random', got {self.sampler!r}")
        counts = [sa.n_centroids for sa in self.set_abstraction]
        if counts != sorted(counts, reverse=True):
            raise ValueError(f"set abstraction levels must not grow: {counts}")

    @property
    def feature_dim(self) -> int:
        return self.feature_propagation[-1][-1]


class SharedMLP(nnx.Module):
    """Linear + ReLU layers applied to the last axis ("1x1 convolutions"): [..., C_in] -> [..., C_out]."""

    def __init__(self, in_features: int, widths: Sequence[int], *, rngs: nnx.Rngs, final_relu: bool = True):
        sizes = [in_features, *widths]
        self.layers = nnx.List([nnx.Linear(a, b, rngs=rngs) for a, b in itertools.pairwise(sizes)])
        self.final_relu = final_relu

    def __call__(self, x: jax.Array) -> jax.Array:
        for i, layer in enumerate(self.layers):
            x = layer(x)
            if self.final_relu or i < len(self.layers) - 1:
                x = jax.nn.relu(x)
        return x


class SetAbstraction(nnx.Module):
    """Sample centroids, ball-query groups, shared MLP, max-pool: one PointNet++ SSG level.

    The first MLP layer on [(p_j - c) / r, f_j] is linear, so it is evaluated as a per-point term
    (W_xyz p_j / r + W_f f_j + b, N rows) minus a per-centroid term (W_xyz c / r, S rows) and gathered:
    the same values as running it on the S x K grouped rows, at N / (S K) of the cost.
    """

    def __init__(self, config: SetAbstractionConfig, in_features: int, sampler: str, *, rngs: nnx.Rngs):
        self.config = config
        self.sampler = sampler
        self.mlp = SharedMLP(3 + in_features, config.mlp, rngs=rngs)

    def __call__(self, points: jax.Array, mask: jax.Array, features: jax.Array | None):
        """points[B, N, 3], mask[B, N], features[B, N, C] | None -> (centres[B, S, 3], valid[B, S],
        features[B, S, C']); invalid centroids carry zero features."""
        c = self.config
        sample = farthest_point_sampling if self.sampler == "fps" else random_sampling
        index, valid = sample(points, mask, c.n_centroids)
        centres = gather(points, index)
        group, count = ball_query(points, mask, centres, c.radius, c.n_neighbours)
        first, rest = self.mlp.layers[0], self.mlp.layers[1:]
        w_xyz, w_feat = first.kernel[...][:3], first.kernel[...][3:]
        per_point = (points / c.radius) @ w_xyz + first.bias[...]
        if features is not None:
            per_point = per_point + features @ w_feat
        h = jax.nn.relu(gather(per_point, group) - ((centres / c.radius) @ w_xyz)[:, :, None, :])  # [B, S, K, C1]
        for layer in rest:
            h = jax.nn.relu(layer(h))
        pooled = jnp.max(h, axis=2)
        valid = valid & (count > 0)
        return centres, valid, jnp.where(valid[..., None], pooled, 0.0)


class FeaturePropagation(nnx.Module):
    """3-NN interpolation from a coarse level to query points, concatenated with skip features, MLP.

    Interpolation is linear with weights summing to 1, so the first layer's coarse-feature part is
    applied to the S coarse rows before interpolating (same values, fewer rows when Q > S).
    """

    def __init__(self, in_features: int, widths: Sequence[int], *, rngs: nnx.Rngs):
        self.mlp = SharedMLP(in_features, widths, rngs=rngs)

    def __call__(self, query, coarse_points, coarse_mask, coarse_features, skip):
        """query[B, Q, 3], coarse_*[B, S, ...], skip[B, Q, C_skip] -> [B, Q, C_out]."""
        first, rest = self.mlp.layers[0], self.mlp.layers[1:]
        kernel, c = first.kernel[...], coarse_features.shape[-1]
        projected = three_nn_interpolate(query, coarse_points, coarse_mask, coarse_features @ kernel[:c])
        h = jax.nn.relu(projected + skip @ kernel[c:] + first.bias[...])
        for layer in rest:
            h = jax.nn.relu(layer(h))
        return h


class PointNet2(nnx.Module):
    """PointNet++ SSG backbone giving per-point features.

    __call__(points[B, N, 3], mask[B, N], query_index[B, Q] | None) -> features[B, N or Q, F].
    With `query_index` the last feature propagation runs only at those points: the result equals
    `gather(self(points, mask), query_index)` (the layer is pointwise) at a fraction of the cost.
    The raw xyz (divided by coord_scale) are the level-0 skip features.
    """

    def __init__(self, config: BackboneConfig, *, rngs: nnx.Rngs):
        self.config = config
        sa_layers, widths = [], [0]
        for sa in config.set_abstraction:
            sa_layers.append(SetAbstraction(sa, widths[-1], config.sampler, rngs=rngs))
            widths.append(sa.mlp[-1])
        self.set_abstraction = nnx.List(sa_layers)
        fp_layers, below = [], widths[-1]
        levels = len(config.set_abstraction)
        for i, mlp in enumerate(config.feature_propagation):
            skip = widths[levels - 1 - i] if i < levels - 1 else 3
            fp_layers.append(FeaturePropagation(below + skip, mlp, rngs=rngs))
            below = mlp[-1]
        self.feature_propagation = nnx.List(fp_layers)

    def __call__(self, points: jax.Array, mask: jax.Array | None = None, query_index: jax.Array | None = None):
        points = _check_points(points)
        mask = _check_mask(mask, points)
        points = jnp.where(mask[..., None], points, 0.0)  # no NaN from padding can reach a product
        xyz, masks, feats = [points], [mask], [None]
        for layer in self.set_abstraction:
            p, m, f = layer(xyz[-1], masks[-1], feats[-1])
            xyz.append(p)
            masks.append(m)
            feats.append(f)
        levels = len(self.set_abstraction)
        f = feats[-1]
        for i, layer in enumerate(self.feature_propagation[:-1]):
            level = levels - 1 - i  # propagate from level + 1 to level
            f = layer(xyz[level], xyz[level + 1], masks[level + 1], f, feats[level])
        query = points if query_index is None else gather(points, query_index)
        return self.feature_propagation[-1](query, xyz[1], masks[1], f, query / self.config.coord_scale)
