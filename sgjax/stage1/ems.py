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

Single-view clouds: given the camera position (`viewpoint`), the fit must also not put surface where
the camera would have seen it but saw nothing (see the Visibility section). That surface counts
against the candidates when starts and S-step candidates are compared, and the final iterations pull
it onto the points. Without a viewpoint (full-surface samples, like the primitive database's) the fit
is plain EMS, bit for bit.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np

from sgjax.geometry import pointcloud
from sgjax.geometry.rotations import proper, rot_z, so3_exp
from sgjax.geometry.superquadric import (
    EPS_MAX,
    EPS_MIN,
    Superquadric,
    canonicalize,
    duality_factor,
    log_implicit_local,
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
    # Single-view clouds (used only when a viewpoint is given; see the Visibility section below).
    # visibility_weight = visibility_fit = 0 switches the term off: plain EMS even with a viewpoint.
    visibility_weight: float = 2.0  # nats per point, times the fraction of the visible fitted area left unseen
    visibility_fit: float = 1.0  # final M-steps: weight of that surface's distances to the points (0: off)
    visibility_samples: int = 64  # surface samples of the visibility term


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

    def __getitem__(self, index) -> FitResult:
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
    cam: jax.Array | None = None  # [3] the viewpoint in normalised coordinates; None: no visibility term
    spacing: jax.Array | None = None  # [] mean distance of a point to its nearest neighbour


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


# ---------------------------------------------------------------------------------------------
# Visibility (single-view clouds with a known viewpoint).
#
# A superquadric with eps in (0, 2] is convex, so the camera sees exactly the part of its surface
# whose outward normal faces the viewpoint. Where the fitted surface faces the camera, the cloud must
# have points; fitted surface there, far from every observed point, is surface the camera would have
# seen but did not (the fit reaching into free space beside or in front of the object). The
# likelihood alone cannot see it, since it only asks that observed points lie on the surface, not
# that the surface lies on observed points; single-view fits then extend into the unseen back or
# sideways. The term samples the surface at fixed directions, weights the samples by the
# area they stand for and by how squarely they face the camera (grazing surface is hardly seen), and
#   - adds visibility_weight nats per point times the unseen fraction of the visible area to the
#     score that selects among the starts and the S-step candidates (`_score`);
#   - adds the samples' distances to the nearest point, beyond the point spacing, to the M-step's
#     least squares in the final iterations (weight visibility_fit; in every iteration it would cost
#     ~3x the fit time for no measured gain).
# Only the object's own points are known here, so surface hidden by other objects counts as unseen
# too: fits of occluded objects lean towards their visible part (under- rather than over-extension).


def _sphere_directions(n: int) -> np.ndarray:
    """n well-spread unit vectors (a Fibonacci lattice), as a NumPy constant: -> [n, 3]."""
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    phi = np.pi * (1.0 + 5.0**0.5) * i
    rxy = np.sqrt(1.0 - z * z)
    return np.stack([rxy * np.cos(phi), rxy * np.sin(phi), z], -1).astype(np.float32)


def _surface_points(eps: jax.Array, log_a: jax.Array, dirs: jax.Array) -> jax.Array:
    """Local surface points [K, 3]: the scaled directions a * dirs[K, 3], projected radially.

    F is homogeneous, F(s x) = s^(2/eps1) F(x), so s = F(x)^(-eps1/2) puts s x on the surface; an
    ellipsoid gets exactly its parametric samples, and boxy shapes get their faces covered too.
    """
    a = jnp.exp(log_a)
    d = dirs * a
    log_f = log_implicit_local(d, a, eps)
    return d * jnp.exp(-0.5 * eps[0] * log_f)[:, None]


def _visible_area(s: _State, c: _Cloud, dirs: jax.Array) -> jax.Array:
    """Visible area of each surface sample [K], as a fraction of the whole visible area (no gradient):
    the area element times a facing-the-camera weight (grazing surface is hardly seen)."""
    s = jax.lax.stop_gradient(s)
    a = jnp.exp(s.log_a)
    local = _surface_points(s.eps, s.log_a, dirs)
    grad = jax.vmap(jax.grad(lambda x: log_implicit_local(x[None], a, s.eps)[0]))(local)
    normal = grad / (jnp.linalg.norm(grad, axis=-1, keepdims=True) + 1e-12)
    # Area element of the map dirs -> surface: |x|^2 dOmega / cos(x, n), where the linear map dirs ->
    # a * dirs changes the solid angle by prod(a) / |a * dirs|^3 (dOmega of the lattice is constant).
    radius = jnp.linalg.norm(local, axis=-1)
    cos_radial = jnp.sum(normal * local, -1) / (radius + 1e-12)
    scaled = jnp.linalg.norm(dirs * a, axis=-1)
    area = radius**2 * jnp.prod(a) / scaled**3 / jnp.maximum(cos_radial, 0.2)
    to_cam = c.cam - (local @ s.rot.T + s.t)
    cos_view = jnp.sum((normal @ s.rot.T) * to_cam, -1) / (jnp.linalg.norm(to_cam, axis=-1) + 1e-12)
    visible = area * jnp.clip((cos_view - 0.1) / 0.3, 0.0, 1.0)
    return visible / (jnp.sum(visible) + 1e-12)


def _sample_world(s: _State, dirs: jax.Array) -> jax.Array:
    return _surface_points(s.eps, s.log_a, dirs) @ s.rot.T + s.t


def _sq_distances(x: jax.Array, c: _Cloud) -> jax.Array:
    """Squared distances [K, N] from x[K, 3] to the cloud's points, padding pushed far away.

    Expanded as |x|^2 - 2 x.p + |p|^2: one matrix product, several times faster on CPU than the
    broadcast difference."""
    d2 = jnp.sum(x * x, -1)[:, None] - 2.0 * x @ c.pts.T + jnp.sum(c.pts * c.pts, -1)[None]
    return jnp.maximum(d2, 0.0) + jnp.where(c.w > 0, 0.0, 1e6)


def _nearest(world: jax.Array, c: _Cloud) -> jax.Array:
    """The observed point nearest to each of world[K, 3]: -> [K, 3] (no gradient).

    A one-hot product instead of argmin + gather (much faster under XLA on CPU); ties are averaged."""
    d2 = _sq_distances(world, c)
    hot = (d2 <= jnp.min(d2, 1, keepdims=True)).astype(d2.dtype)
    return jax.lax.stop_gradient((hot @ c.pts) / jnp.sum(hot, 1, keepdims=True))


def _excess(world: jax.Array, nearest: jax.Array, c: _Cloud) -> jax.Array:
    """Distance [K] of each surface sample to its nearest observed point, beyond the point spacing
    (a tolerance for noise and for sampling: on the seen surface, samples lie that close to a point)."""
    dist = jnp.sqrt(jnp.sum((world - nearest) ** 2, -1) + 1e-12)
    return jax.nn.relu(dist - c.spacing)


def _visibility_excess(s: _State, c: _Cloud, dirs: jax.Array) -> jax.Array:
    world = _sample_world(s, dirs)
    return _excess(world, _nearest(world, c), c)


def _visibility_jacobian(s: _State, c: _Cloud, dirs: jax.Array) -> tuple[jax.Array, jax.Array]:
    """`_visibility_excess` [K] and its Jacobian [K, 11] w.r.t. the LM increment (eps, log a, w, t),
    the nearest points held fixed."""
    nearest = _nearest(_sample_world(s, dirs), c)

    def excess(delta):
        moved = dataclasses.replace(
            s, eps=s.eps + delta[0:2], log_a=s.log_a + delta[2:5], rot=s.rot @ so3_exp(delta[5:8]), t=s.t + delta[8:11]
        )
        return _excess(_sample_world(moved, dirs), nearest, c)

    zero = jnp.zeros(11)
    return excess(zero), jax.jacfwd(excess)(zero)


def _unseen_fraction(s: _State, c: _Cloud, dirs: jax.Array) -> jax.Array:
    """Fraction of the fitted surface's visible area that the camera should have seen but did not
    (farther than a few point spacings from every point, smoothly): -> []."""
    excess = _visibility_excess(s, c, dirs)
    return jnp.sum(_visible_area(s, c, dirs) * (1.0 - jnp.exp(-((excess / (2.0 * c.spacing)) ** 2))))


def _mean_spacing(c: _Cloud) -> jax.Array:
    """Mean distance of a real point to its nearest real neighbour (at least 1e-3; the cloud is
    normalised to RMS radius 1, and duplicated points must not make it 0): -> []."""
    d2 = _sq_distances(c.pts, c) + 1e6 * jnp.eye(c.pts.shape[0])
    mean = jnp.sum(c.w * jnp.sqrt(jnp.min(d2, 1))) / jnp.maximum(jnp.sum(c.w), 1.0)
    return jnp.maximum(mean, 1e-3)


def _lm_step(
    s: _State, r: jax.Array, c: _Cloud, weights: jax.Array, kind: str, vis: tuple | None = None
) -> tuple[_State, jax.Array]:
    """One Levenberg-Marquardt step on sum_i weights_i r_i^2, kept only if the cost falls.

    r[N] are the residuals at s; returns the new state and its residuals. vis = (weights[K],
    directions[K, 3]) adds sum_k weights_k excess_k^2 of the visibility samples (`_visibility_excess`).
    """
    jac = _jacobian(s, c.pts, kind)
    wr = weights * r
    cost = jnp.sum(wr * r)
    hess = jac.T @ (weights[:, None] * jac)
    grad = jac.T @ wr
    if vis is not None:
        v, dirs = vis
        e, jac_v = _visibility_jacobian(s, c, dirs)
        cost = cost + jnp.sum(v * e * e)
        hess = hess + jac_v.T @ (v[:, None] * jac_v)
        grad = grad + jac_v.T @ (v * e)
    diag = jnp.diag(hess) + 1e-9
    delta = -jnp.linalg.solve(hess + s.lam * jnp.diag(diag), grad)
    delta = jnp.where(jnp.all(jnp.isfinite(delta)), delta, 0.0)
    trial = _apply(s, delta, c)
    r_new = _residual(trial, c.pts, kind)
    new_cost = jnp.sum(weights * r_new * r_new)
    if vis is not None:
        e_new = _visibility_excess(trial, c, dirs)
        new_cost = new_cost + jnp.sum(v * e_new * e_new)
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


def _score(s: _State, d: jax.Array, c: _Cloud, cfg: EMSConfig) -> jax.Array:
    """What the search minimises: the NLL, plus the unseen-surface penalty when a viewpoint is known."""
    nll = _neg_log_likelihood(d, s.sigma2, c, cfg)
    if c.cam is None or cfg.visibility_weight <= 0:
        return nll
    dirs = jnp.asarray(_sphere_directions(cfg.visibility_samples))
    return nll + cfg.visibility_weight * jnp.sum(c.w) * _unseen_fraction(s, c, dirs)


def _posterior(d: jax.Array, sigma2: jax.Array, c: _Cloud, cfg: EMSConfig) -> jax.Array:
    """E-step: inlier posteriors p[N] (0 on padding) from residuals d[N]."""
    log_in, log_out = _log_likelihoods(d, sigma2, c, cfg)
    return c.w * jax.nn.sigmoid(log_in - log_out)


def _em_iteration(
    s: _State, d: jax.Array, c: _Cloud, cfg: EMSConfig, visibility: bool = False
) -> tuple[_State, jax.Array]:
    """E-step, M-step, sigma^2 update; d[N] are the residuals at s, and are returned for the new state.

    visibility: the M-step also pulls the fitted surface the camera should have seen onto the points."""
    p = _posterior(d, s.sigma2, c, cfg)
    vis = None
    if visibility and c.cam is not None and cfg.visibility_fit > 0:
        # The visible samples weigh, in all, visibility_fit times the points' inlier weight.
        dirs = jnp.asarray(_sphere_directions(cfg.visibility_samples))
        vis = (cfg.visibility_fit * jnp.sum(p) * _visible_area(s, c, dirs), dirs)
    for _ in range(cfg.lm_steps):
        s, d = _lm_step(s, d, c, p, cfg.residual, vis)
    sigma2 = jnp.sum(p * d * d) / (3.0 * jnp.sum(p) + 1e-12)
    sigma2 = jnp.clip(sigma2, cfg.min_sigma**2, 4.0 * cfg.init_sigma**2)
    return dataclasses.replace(s, sigma2=jnp.where(jnp.isfinite(sigma2), sigma2, s.sigma2)), d


def _run_em(s: _State, c: _Cloud, cfg: EMSConfig, n: int, visibility: bool = False) -> tuple[_State, jax.Array]:
    """n EM iterations from s; returns the final state and its residuals d[N]."""
    d = _residual(s, c.pts, cfg.residual)
    return jax.lax.fori_loop(0, n, lambda _, sd: _em_iteration(*sd, c, cfg, visibility), (s, d))


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
    """Run each similar candidate a few EM iterations; keep the best. Returns (state, `_score`)."""
    cands = _similar_candidates(s)

    def run(cand: _State) -> tuple[_State, jax.Array]:
        # A swapped candidate starts far from the points: widen sigma so its posteriors are not all zero.
        d = _residual(cand, c.pts, cfg.residual)
        spread = jnp.sum(c.w * d * d) / (3.0 * jnp.sum(c.w))
        cand = dataclasses.replace(cand, sigma2=jnp.maximum(cand.sigma2, spread), lam=jnp.asarray(1e-2))
        cand, d = _run_em(cand, c, cfg, cfg.switch_iterations)
        return cand, _score(cand, d, c, cfg)

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


def _search_cloud(c: _Cloud, k: int) -> _Cloud:
    """`_subset`, with the point spacing the visibility term needs (when it is on)."""
    c = _subset(c, k)
    return c if c.cam is None else dataclasses.replace(c, spacing=_mean_spacing(c))


def _fibonacci_sphere(n: int) -> jax.Array:
    """n well-spread unit vectors; the stand-in cloud for inputs that cannot be fitted."""
    i = jnp.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    phi = jnp.pi * (1.0 + 5.0**0.5) * i
    rxy = jnp.sqrt(1.0 - z * z)
    return jnp.stack([rxy * jnp.cos(phi), rxy * jnp.sin(phi), z], -1)


def _fit_one(points: jax.Array, mask: jax.Array, cfg: EMSConfig, viewpoint: jax.Array | None = None) -> FitResult:
    """Fit one padded cloud: points[N, 3], mask[N] -> unbatched FitResult.

    viewpoint[3]: the camera position in the points' frame, for single-view clouds (see the Visibility
    section); None fits without it (full-surface samples, or an unknown camera), exactly as plain EMS.
    """
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
    if viewpoint is not None and (cfg.visibility_weight > 0 or cfg.visibility_fit > 0):
        cloud = dataclasses.replace(cloud, cam=(jnp.asarray(viewpoint, jnp.float32) - centroid) / norm)
    coarse = _search_cloud(cloud, cfg.search_points)

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
    # With a viewpoint, the final iterations also draw the surface the camera should have seen onto the points.
    state, _ = _run_em(state, _search_cloud(cloud, cfg.fit_points), cfg, cfg.final_iterations, visibility=True)

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
def _fit_batch(points: jax.Array, mask: jax.Array, config: EMSConfig, viewpoints: jax.Array | None = None) -> FitResult:
    if viewpoints is None:
        return jax.vmap(lambda p, m: _fit_one(p, m, config))(points, mask)
    return jax.vmap(lambda p, m, v: _fit_one(p, m, config, v))(points, mask, viewpoints)


def fit_superquadrics(points, mask=None, config: EMSConfig = EMSConfig(), viewpoints=None) -> FitResult:
    """Fit one superquadric to each of B padded clouds, in one jit-compiled call.

    points: [B, N, 3] (metres), mask: [B, N] bool marking real points (default: all). Clouds that cannot
    be fitted (too few points, NaN/inf, identical, collinear or coplanar points) come back with
    valid=False and a status code (`sgjax.geometry.pointcloud.describe_status`); the others are fitted normally.
    Use `sgjax.geometry.pointcloud.pad_clouds` to batch clouds of different sizes; calls with the same (B, N)
    reuse one compilation. Works under an outer jit/vmap too.

    viewpoints: None, [3] or [B, 3], the camera position of single-view clouds in the points' frame.
    With it the fit keeps to the surface the camera saw (see the Visibility section of this module);
    without it (full-surface samples, or an unknown camera) the result is exactly that of plain EMS.
    """
    points = jnp.asarray(points, jnp.float32)
    if points.ndim != 3 or points.shape[-1] != 3:
        raise pointcloud.CloudError(f"points must have shape (B, N, 3), got {points.shape}")
    if points.shape[0] == 0 or points.shape[1] == 0:
        raise pointcloud.CloudError(f"points must hold at least one cloud and one point, got {points.shape}")
    mask = jnp.ones(points.shape[:2], bool) if mask is None else jnp.asarray(mask, bool)
    if mask.shape != points.shape[:2]:
        raise pointcloud.CloudError(f"mask must have shape {points.shape[:2]}, got {mask.shape}")
    if viewpoints is not None:
        b = points.shape[0]
        viewpoints = jnp.asarray(viewpoints, jnp.float32)
        if viewpoints.shape not in ((3,), (b, 3)):
            raise pointcloud.CloudError(f"viewpoints must have shape (3,) or ({b}, 3), got {viewpoints.shape}")
        viewpoints = jnp.broadcast_to(viewpoints, (b, 3))
    return _fit_batch(points, mask, config, viewpoints)


def fit_superquadric(
    points, config: EMSConfig = EMSConfig(), max_points: int = 1024, seed: int = 0, viewpoint=None
) -> FitResult:
    """Fit one cloud points[N, 3] (metres); raises CloudError naming the problem for bad input.

    Clouds larger than `max_points` are first downsampled uniformly at random (deterministic in `seed`):
    EMS needs only a few hundred points, and a 10^6-point cloud would otherwise cost seconds per
    iteration. viewpoint: None or [3], the camera position for a single-view cloud (see
    `fit_superquadrics`). Returns an unbatched FitResult.
    """
    cloud = pointcloud.as_cloud(points)
    batch, mask = pointcloud.pad_clouds([cloud], max_points=max_points, seed=seed)
    result = fit_superquadrics(batch, mask, config, viewpoint)[0]
    if not bool(result.valid):
        raise pointcloud.CloudError(pointcloud.describe_status(int(result.status)))
    return result
