"""EMS: probabilistic superquadric recovery (Liu et al., CVPR 2022; the paper's [ems]), batched in JAX.

Model: each point is either an inlier, Gaussian in its radial distance to the surface with variance
sigma^2, or an outlier, uniform over the cloud's bounding volume with prior weight w0.
  E-step  posterior inlier probability p_i of every point;
  M-step  bounded Levenberg-Marquardt on sum_i p_i d_i^2 over (eps1, eps2, log a, rotation, t);
  sigma^2 update from the weighted residuals;
  S-step  the "similar" superquadrics (the z axis swapped with x or with y, and the 45 deg dual) each run
          a few EM iterations from where the fit stands, and the one of highest likelihood is kept.
Everything runs a fixed number of iterations on fixed shapes, so B clouds padded to N points are
one jit-compiled call, and calls of the same padded size never recompile.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np

from sgjax import pointcloud
from sgjax.rotations import proper, rot_z, so3_exp
from sgjax.superquadric import (
    EPS_MAX,
    EPS_MIN,
    Superquadric,
    canonicalize,
    duality_factor,
    prefer_square,
    signed_radial_distance_local,
    tangent_radial_distance_local,
)


@dataclasses.dataclass(frozen=True)
class EMSConfig:
    """Fixed iteration counts and model constants (static under jit: one compile per config)."""

    n_starts: int = 3  # initial frames: z along the longest, middle, shortest principal axis (1..3)
    upright_start: bool = True  # one more start: z along world +z, x along the horizontal principal axis
    warmup_iterations: int = 8  # EM iterations of each start
    switch_iterations: int = 3  # EM iterations each similar candidate gets in the S-step
    final_iterations: int = 4  # EM iterations of the best candidate on the finer subset
    lm_steps: int = 1  # Levenberg-Marquardt steps per M-step (a generalised EM step suffices)
    search_points: int = 128  # points used while searching (starts and S-step); 0: all
    fit_points: int = 384  # points used in the final iterations; 0: all
    outlier_ratio: float = 0.2  # prior w0 of the uniform outlier component
    init_sigma: float = 0.3  # initial noise std, relative to the cloud's RMS radius
    min_sigma: float = 2e-3  # floor of the noise std, relative to the cloud's RMS radius
    max_scale: float = 4.0  # upper bound of each semi-axis, relative to the cloud's largest radius
    residual: str = "tangent"  # "tangent": radial distance projected on the normal; "radial": plain EMS


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class FitResult:
    """Batched EMS output; leading axis B on every field.

    scale[B, 3], epsilon[B, 2], rotation[B, 3, 3], translation[B, 3]: the fitted superquadric in the
    input frame (canonical frame, see `canonicalize`); inlier_ratio[B]: mean posterior inlier
    probability; sigma[B]: fitted noise std (metres); status[B]: `pointcloud` status code;
    valid[B]: status == OK. Invalid clouds get scale 0, eps 1, identity rotation, zero translation.
    """

    scale: jax.Array
    epsilon: jax.Array
    rotation: jax.Array
    translation: jax.Array
    inlier_ratio: jax.Array
    sigma: jax.Array
    status: jax.Array
    valid: jax.Array

    @property
    def superquadric(self) -> Superquadric:
        return Superquadric(self.scale, self.epsilon, self.rotation, self.translation)

    def __getitem__(self, index) -> "FitResult":
        return jax.tree_util.tree_map(lambda x: x[index], self)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class _State:
    """One cloud's fit in normalised coordinates (centroid at 0, RMS radius 1)."""

    eps: jax.Array  # [2]
    log_a: jax.Array  # [3]
    rot: jax.Array  # [3, 3]
    t: jax.Array  # [3]
    sigma2: jax.Array  # []
    lam: jax.Array  # [] LM damping


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class _Cloud:
    """One normalised cloud and the constants of its likelihood."""

    pts: jax.Array  # [N, 3]
    w: jax.Array  # [N] 1 for real points, 0 for padding
    log_outlier: jax.Array  # [] log(w0 * p0), p0 = 1 / bounding volume
    log_a_max: jax.Array  # []
    t_max: jax.Array  # []


_LOG_A_MIN = float(np.log(1e-3))


def _distance_fn(kind: str):
    return tangent_radial_distance_local if kind == "tangent" else signed_radial_distance_local


def _residual(s: _State, pts: jax.Array, kind: str) -> jax.Array:
    """Signed distances of points[N, 3] to the state's surface: -> [N]."""
    return _distance_fn(kind)((pts - s.t) @ s.rot, jnp.exp(s.log_a), s.eps)


def _jacobian(s: _State, pts: jax.Array, kind: str) -> jax.Array:
    """Jacobian [N, 11] of the residuals w.r.t. (eps, log a, rotation increment w, translation).

    Forward mode runs per point over the 8 inputs (local x, log a, eps), which XLA vectorises far
    better than 11 tangents over the whole cloud; rotation and translation follow by the chain rule:
    local = (p - t) R (I + [w]x) gives d local = l x dw - R^T dt, so dr/dw = g x l and dr/dt = -R g.
    """
    distance = _distance_fn(kind)

    def one(local, log_a, eps):
        return distance(local[None], jnp.exp(log_a), eps)[0]

    local = (pts - s.t) @ s.rot
    per_point = jax.jacfwd(one, argnums=(0, 1, 2))
    g_local, g_log_a, g_eps = jax.vmap(lambda l: per_point(l, s.log_a, s.eps))(local)
    return jnp.concatenate([g_eps, g_log_a, jnp.cross(g_local, local), -g_local @ s.rot.T], axis=-1)


def _apply(s: _State, delta: jax.Array, c: _Cloud) -> _State:
    """State after an increment, projected onto the box constraints."""
    return dataclasses.replace(
        s,
        eps=jnp.clip(s.eps + delta[0:2], EPS_MIN, EPS_MAX),
        log_a=jnp.clip(s.log_a + delta[2:5], _LOG_A_MIN, c.log_a_max),
        rot=s.rot @ so3_exp(delta[5:8]),
        t=jnp.clip(s.t + delta[8:11], -c.t_max, c.t_max),
    )


def _lm_step(s: _State, r: jax.Array, c: _Cloud, weights: jax.Array, kind: str) -> tuple[_State, jax.Array]:
    """One Levenberg-Marquardt step on sum_i weights_i r_i^2, kept only if the cost falls.

    r[N] are the residuals at s; returns the new state and its residuals.
    """
    jac = _jacobian(s, c.pts, kind)
    wr = weights * r
    cost = jnp.sum(wr * r)
    hess = jac.T @ (weights[:, None] * jac)
    grad = jac.T @ wr
    diag = jnp.diag(hess) + 1e-9
    delta = -jnp.linalg.solve(hess + s.lam * jnp.diag(diag), grad)
    delta = jnp.where(jnp.all(jnp.isfinite(delta)), delta, 0.0)
    trial = _apply(s, delta, c)
    r_new = _residual(trial, c.pts, kind)
    new_cost = jnp.sum(weights * r_new * r_new)
    better = new_cost < cost
    lam = jnp.clip(jnp.where(better, s.lam * 0.3, s.lam * 10.0), 1e-6, 1e6)
    out = jax.tree_util.tree_map(lambda a, b: jnp.where(better, a, b), trial, s)
    return dataclasses.replace(out, lam=lam), jnp.where(better, r_new, r)


def _log_likelihoods(d: jax.Array, sigma2: jax.Array, c: _Cloud, cfg: EMSConfig) -> tuple[jax.Array, jax.Array]:
    """Per-point log densities of the inlier and the outlier component, from residuals d[N]: -> 2 x [N]."""
    log_in = jnp.log1p(-cfg.outlier_ratio) - 0.5 * d * d / sigma2 - 1.5 * jnp.log(2 * jnp.pi * sigma2)
    return log_in, jnp.broadcast_to(c.log_outlier, d.shape)


def _neg_log_likelihood(d: jax.Array, sigma2: jax.Array, c: _Cloud, cfg: EMSConfig) -> jax.Array:
    log_in, log_out = _log_likelihoods(d, sigma2, c, cfg)
    nll = -jnp.sum(c.w * jnp.logaddexp(log_in, log_out))
    return jnp.where(jnp.isfinite(nll), nll, jnp.inf)


def _posterior(d: jax.Array, sigma2: jax.Array, c: _Cloud, cfg: EMSConfig) -> jax.Array:
    """E-step: inlier posteriors p[N] (0 on padding) from residuals d[N]."""
    log_in, log_out = _log_likelihoods(d, sigma2, c, cfg)
    return c.w * jax.nn.sigmoid(log_in - log_out)


def _em_iteration(s: _State, d: jax.Array, c: _Cloud, cfg: EMSConfig) -> tuple[_State, jax.Array]:
    """E-step, M-step, sigma^2 update; d[N] are the residuals at s, and are returned for the new state."""
    p = _posterior(d, s.sigma2, c, cfg)
    for _ in range(cfg.lm_steps):
        s, d = _lm_step(s, d, c, p, cfg.residual)
    sigma2 = jnp.sum(p * d * d) / (3.0 * jnp.sum(p) + 1e-12)
    sigma2 = jnp.clip(sigma2, cfg.min_sigma**2, 4.0 * cfg.init_sigma**2)
    return dataclasses.replace(s, sigma2=jnp.where(jnp.isfinite(sigma2), sigma2, s.sigma2)), d


def _run_em(s: _State, c: _Cloud, cfg: EMSConfig, n: int) -> tuple[_State, jax.Array]:
    """n EM iterations from s; returns the final state and its residuals d[N]."""
    d = _residual(s, c.pts, cfg.residual)
    return jax.lax.fori_loop(0, n, lambda _, sd: _em_iteration(*sd, c, cfg), (s, d))


def _similar_candidates(s: _State) -> _State:
    """The S-step's similar superquadrics, stacked on a new leading axis of 4.

    [current, z<->x (turn about y), z<->y (turn about x), 45 deg dual]. When the z axis is swapped, the
    profiles of the two exponents swap too.
    """
    r, a = s.rot, s.log_a
    swap_e = s.eps[::-1]
    zx = dataclasses.replace(
        s, eps=swap_e, log_a=a[jnp.array([2, 1, 0])], rot=jnp.stack([r[:, 2], r[:, 1], -r[:, 0]], -1)
    )
    zy = dataclasses.replace(
        s, eps=swap_e, log_a=a[jnp.array([0, 2, 1])], rot=jnp.stack([r[:, 0], r[:, 2], -r[:, 1]], -1)
    )
    f = jnp.log(duality_factor(s.eps[1]))
    du = dataclasses.replace(
        s,
        eps=jnp.clip(jnp.stack([s.eps[0], 2.0 - s.eps[1]]), EPS_MIN, EPS_MAX),
        log_a=a + jnp.stack([f, f, 0.0]),
        rot=r @ rot_z(jnp.pi / 4),
    )
    return jax.tree_util.tree_map(lambda *x: jnp.stack(x), s, zx, zy, du)


def _s_step(s: _State, c: _Cloud, cfg: EMSConfig) -> tuple[_State, jax.Array]:
    """Run each similar candidate a few EM iterations; keep the most likely. Returns (state, NLL)."""
    cands = _similar_candidates(s)

    def run(cand: _State) -> tuple[_State, jax.Array]:
        # A swapped candidate starts far from the points: widen sigma so its posteriors are not all zero.
        d = _residual(cand, c.pts, cfg.residual)
        spread = jnp.sum(c.w * d * d) / (3.0 * jnp.sum(c.w))
        cand = dataclasses.replace(cand, sigma2=jnp.maximum(cand.sigma2, spread), lam=jnp.asarray(1e-2))
        cand, d = _run_em(cand, c, cfg, cfg.switch_iterations)
        return cand, _neg_log_likelihood(d, cand.sigma2, c, cfg)

    cands, nll = jax.vmap(run)(cands)
    best = jnp.argmin(nll)
    return jax.tree_util.tree_map(lambda x: x[best], cands), nll[best]


def _subset(c: _Cloud, k: int) -> _Cloud:
    """The same cloud restricted to k of its real points, evenly strided through their order.

    Each LM step costs O(N); a hundred or a few hundred points already pin down 11 parameters, so the
    EM iterations run on subsets and only the final posteriors use every point. Striding (no sort, no
    randomness) keeps results deterministic and identical inside and outside a batch; a cloud with
    fewer than k real points contributes each once and pads with zero weight.
    """
    n_total = c.pts.shape[0]
    if k <= 0 or k >= n_total:
        return c
    rank = jnp.cumsum(c.w)  # rank of each real point, 1-based
    n = rank[-1]
    j = jnp.arange(k, dtype=jnp.float32)
    target = jnp.where(n >= k, jnp.floor(j * n / k), jnp.minimum(j, n - 1)) + 1.0
    idx = jnp.clip(jnp.searchsorted(rank, target), 0, n_total - 1)
    w = c.w[idx] * ((n >= k) | (j < n))
    return dataclasses.replace(c, pts=c.pts[idx], w=w)


def _fibonacci_sphere(n: int) -> jax.Array:
    """n well-spread unit vectors; the stand-in cloud for inputs that cannot be fitted."""
    i = jnp.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    phi = jnp.pi * (1.0 + 5.0**0.5) * i
    rxy = jnp.sqrt(1.0 - z * z)
    return jnp.stack([rxy * jnp.cos(phi), rxy * jnp.sin(phi), z], -1)


def _fit_one(points: jax.Array, mask: jax.Array, cfg: EMSConfig) -> FitResult:
    """Fit one padded cloud: points[N, 3], mask[N] -> unbatched FitResult."""
    status = pointcloud.cloud_status(points, mask, xp=jnp)
    ok = status == pointcloud.OK
    mask = jnp.where(ok, mask, True)
    w = mask.astype(jnp.float32)
    n = jnp.sum(w)
    pts = jnp.where(ok, jnp.where(mask[:, None], points, 0.0), _fibonacci_sphere(points.shape[0]))

    centroid = jnp.sum(pts * w[:, None], 0) / n
    centred = (pts - centroid) * w[:, None]
    cov = centred.T @ centred / n
    norm = jnp.sqrt(jnp.trace(cov))
    pts = centred / norm
    _, vecs = jnp.linalg.eigh(cov / norm**2)  # ascending variances
    big = jnp.finfo(jnp.float32).max
    local = pts @ vecs
    lo = jnp.min(jnp.where(mask[:, None], local, big), 0)
    hi = jnp.max(jnp.where(mask[:, None], local, -big), 0)
    extent = jnp.maximum(hi - lo, 0.05 * jnp.max(hi - lo))
    radius = jnp.max(jnp.linalg.norm(pts, axis=-1) * w)
    cloud = _Cloud(
        pts=pts,
        w=w,
        log_outlier=jnp.log(cfg.outlier_ratio) - jnp.sum(jnp.log(extent)),
        log_a_max=jnp.log(cfg.max_scale * radius),
        t_max=cfg.max_scale * radius,
    )
    coarse = _subset(cloud, cfg.search_points)

    def search(rot0: jax.Array) -> tuple[_State, jax.Array]:
        # Semi-axes from the RMS spread along each axis (a box face of half-side a has RMS a / sqrt(3)).
        a0 = jnp.sqrt(3.0 * jnp.sum(w[:, None] * (pts @ rot0) ** 2, 0) / n)
        state = _State(
            eps=jnp.ones(2),
            log_a=jnp.log(jnp.clip(a0, 0.05, None)),
            rot=rot0,
            t=jnp.zeros(3),
            sigma2=jnp.asarray(cfg.init_sigma**2),
            lam=jnp.asarray(1e-2),
        )
        state, _ = _run_em(state, coarse, cfg, cfg.warmup_iterations)
        return _s_step(state, coarse, cfg)

    # Starts: the z axis along the longest, the middle and the shortest principal direction.
    orders = jnp.array([[1, 0, 2], [0, 2, 1], [2, 1, 0]])[: cfg.n_starts]
    starts = jax.vmap(lambda o: proper(vecs[:, o]))(orders)
    if cfg.upright_start:
        # Objects on a table are mostly upright: a gravity-aligned start escapes the arbitrary
        # principal frame of near-isotropic clouds (a cube), where every PCA start can stall.
        _, hvecs = jnp.linalg.eigh(cov[:2, :2])
        x = jnp.concatenate([hvecs[:, 1], jnp.zeros(1)])
        upright = jnp.stack([x, jnp.cross(jnp.array([0.0, 0.0, 1.0]), x), jnp.array([0.0, 0.0, 1.0])], -1)
        starts = jnp.concatenate([starts, upright[None]])
    states, nll = jax.vmap(search)(starts)
    state = jax.tree_util.tree_map(lambda x: x[jnp.argmin(nll)], states)
    state, _ = _run_em(state, _subset(cloud, cfg.fit_points), cfg, cfg.final_iterations)

    p = _posterior(_residual(state, cloud.pts, cfg.residual), state.sigma2, cloud, cfg)
    sq = canonicalize(
        prefer_square(Superquadric(jnp.exp(state.log_a) * norm, state.eps, state.rot, centroid + norm * state.t))
    )
    finite = jnp.all(jnp.array([jnp.all(jnp.isfinite(x)) for x in jax.tree_util.tree_leaves(sq)]))
    status = jnp.where(ok & ~finite, pointcloud.FIT_FAILED, status).astype(jnp.int32)
    good = status == pointcloud.OK
    return FitResult(
        scale=jnp.where(good, sq.scale, 0.0),
        epsilon=jnp.where(good, sq.epsilon, 1.0),
        rotation=jnp.where(good, sq.rotation, jnp.eye(3)),
        translation=jnp.where(good, sq.translation, 0.0),
        inlier_ratio=jnp.where(good, jnp.sum(p) / n, 0.0),
        sigma=jnp.where(good, jnp.sqrt(state.sigma2) * norm, 0.0),
        status=status,
        valid=good,
    )


@functools.partial(jax.jit, static_argnames="config")
def _fit_batch(points: jax.Array, mask: jax.Array, config: EMSConfig) -> FitResult:
    return jax.vmap(lambda p, m: _fit_one(p, m, config))(points, mask)


def fit_superquadrics(points, mask=None, config: EMSConfig = EMSConfig()) -> FitResult:
    """Fit one superquadric to each of B padded clouds, in one jit-compiled call.

    points: [B, N, 3] (metres), mask: [B, N] bool marking real points (default: all). Clouds that cannot
    be fitted (too few points, NaN/inf, identical, collinear or coplanar points) come back with
    valid=False and a status code (`sgjax.pointcloud.describe_status`); the others are fitted normally.
    Use `sgjax.pointcloud.pad_clouds` to batch clouds of different sizes; calls with the same (B, N)
    reuse one compilation. Works under an outer jit/vmap too.
    """
    points = jnp.asarray(points, jnp.float32)
    if points.ndim != 3 or points.shape[-1] != 3:
        raise pointcloud.CloudError(f"points must have shape (B, N, 3), got {points.shape}")
    if points.shape[0] == 0 or points.shape[1] == 0:
        raise pointcloud.CloudError(f"points must hold at least one cloud and one point, got {points.shape}")
    mask = jnp.ones(points.shape[:2], bool) if mask is None else jnp.asarray(mask, bool)
    if mask.shape != points.shape[:2]:
        raise pointcloud.CloudError(f"mask must have shape {points.shape[:2]}, got {mask.shape}")
    return _fit_batch(points, mask, config)


def fit_superquadric(
    points, config: EMSConfig = EMSConfig(), max_points: int = 1024, seed: int = 0
) -> FitResult:
    """Fit one cloud points[N, 3] (metres); raises CloudError naming the problem for bad input.

    Clouds larger than `max_points` are first downsampled uniformly at random (deterministic in `seed`):
    EMS needs only a few hundred points, and a 10^6-point cloud would otherwise cost seconds per
    iteration. Returns an unbatched FitResult.
    """
    cloud = pointcloud.as_cloud(points)
    batch, mask = pointcloud.pad_clouds([cloud], max_points=max_points, seed=seed)
    result = fit_superquadrics(batch, mask, config)[0]
    if not bool(result.valid):
        raise pointcloud.CloudError(pointcloud.describe_status(int(result.status)))
    return result
