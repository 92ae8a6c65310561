"""Superquadric similarity matching and grasp transfer (paper Sec. IV-B, "Fast matching").

Two steps, exactly as the paper:
  1. d_shape = w_r d_ratio + w_eps d_eps over the whole database; keep the top K1;
  2. s = d_shape + lambda_s d_scale + lambda_a d_abs over those; keep the top K2.
Where the paper's non-uniqueness rule applies, the equivalent parameterisation of the query and of each
candidate take part too, and each pair (query param, candidate param) keeps its best; the chosen pair
fixes the frames used for the transfer T = T_sq^q (T_sq^c)^-1.

Everything is JAX, jit-compiled and batched over queries [Q]; the database enters as a `MatchDB`
pytree of device arrays (`MatchDB.from_db`), so one compilation serves every call with the same Q.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import ClassVar

import jax
import jax.numpy as jnp
import numpy as np

from sgjax.geometry.rotations import rot_z
from sgjax.geometry.superquadric import (EPS_MAX, EPS_MIN, Superquadric, duality_factor, equivalent_parameterisations,
                                         pose_matrix)


@dataclasses.dataclass(frozen=True)
class MatchConfig:
    """The paper's constants (Sec. IV-B) and the non-uniqueness rule's tolerances."""

    w_r: float = 1.0
    w_eps: float = 1.2
    lambda_s: float = 1.6
    lambda_a: float = 2.0
    K1: int = 50
    K2: int = 5
    eps_tol: float = 0.3  # eps2 within this of 0 or 2 ...
    axis_tol: float = 0.1  # ... and |a_x - a_y| / max below this: the dual parameterisation exists
    # Options measured and not adopted (docs/experiments.md): saved configs holding their old defaults still load.
    RETIRED_FIELDS: ClassVar[dict] = {"relabel_axes": False, "relabel_extra": 0}

    def __post_init__(self):
        if self.K1 < 1 or self.K2 < 1:
            raise ValueError(f"K1 and K2 must be >= 1, got {self.K1} and {self.K2}")


@jax.tree_util.register_dataclass
@dataclasses.dataclass
class MatchDB:
    """Database coefficients for matching, with the equivalent parameterisation precomputed.

    scale [P, 2, 3], epsilon [P, 2, 2], param_valid [P, 2] (index 1: the dual, valid where the rule
    applies); grasps [P, G, 4, 4] in each primitive's superquadric frame, widths [P, G], mask [P, G].
    """

    scale: jax.Array
    epsilon: jax.Array
    param_valid: jax.Array
    grasps: jax.Array
    widths: jax.Array
    mask: jax.Array

    @classmethod
    def from_db(cls, db, cfg: MatchConfig = MatchConfig()) -> MatchDB:
        """From a `sgjax.stage1.database.PrimitiveDB`."""
        poses, widths, mask = db.padded_grasps()
        scale, eps, valid = db_parameterisations(db.sq_scale, db.sq_epsilon, cfg)
        return cls(*(jnp.asarray(a) for a in (scale, eps, valid, poses, widths, mask)))


@jax.tree_util.register_dataclass
@dataclasses.dataclass
class MatchResult:
    """Top-K2 matches per query: index, score s, d_shape [Q, K2] and the parameterisations used
    (query_param, db_param [Q, K2]: 0 original, 1 equivalent)."""

    index: jax.Array
    score: jax.Array
    d_shape: jax.Array
    query_param: jax.Array
    db_param: jax.Array


def parameterisations(scale: jax.Array, epsilon: jax.Array, cfg: MatchConfig = MatchConfig()):
    """Original and equivalent coefficients: scale [..., 3], epsilon [..., 2] ->
    (scale [..., 2, 3], epsilon [..., 2, 2], valid [..., 2])."""
    eye = jnp.broadcast_to(jnp.eye(3), scale.shape[:-1] + (3, 3))
    sq = Superquadric(scale, epsilon, eye, jnp.zeros_like(scale))
    both, applies = equivalent_parameterisations(sq, cfg.eps_tol, cfg.axis_tol)
    valid = jnp.stack([jnp.ones_like(applies), applies], -1)
    return jnp.moveaxis(both.scale, 0, -2), jnp.moveaxis(both.epsilon, 0, -2), valid


def db_parameterisations(scale: np.ndarray, epsilon: np.ndarray, cfg: MatchConfig = MatchConfig()):
    """`parameterisations` on the host, for the database: the same float32 values bit for bit (tested),
    without eager JAX, which compiles its ~60 small operations anew in every process (~2 s of each new
    planner). scale [P, 3], epsilon [P, 2] -> NumPy (scale [P, 2, 3], epsilon [P, 2, 2], valid [P, 2])."""
    scale, epsilon = np.asarray(scale, np.float32), np.asarray(epsilon, np.float32)
    e2 = epsilon[..., 1]
    # As `equivalent_parameterisations` and `dual` (Python floats are weak, as in JAX).
    near = (e2 < cfg.eps_tol) | (e2 > 2.0 - cfg.eps_tol)
    ax, ay = scale[..., 0], scale[..., 1]
    applies = near & (np.abs(ax - ay) / np.maximum(ax, ay) < cfg.axis_tol)
    f = duality_factor(e2, np)
    dual_scale = scale * np.stack([f, f, np.ones_like(f)], -1)
    dual_eps = np.clip(np.stack([epsilon[..., 0], 2.0 - e2], -1), EPS_MIN, EPS_MAX)
    other_scale = np.where(applies[..., None], dual_scale, scale)
    other_eps = np.where(applies[..., None], dual_eps, epsilon)
    valid = np.stack([np.ones_like(applies), applies], -1)
    return np.stack([scale, other_scale], -2), np.stack([epsilon, other_eps], -2), valid


def geometric_mean(scale: jax.Array) -> jax.Array:
    """m = (a_x a_y a_z)^(1/3): [..., 3] -> [...]."""
    return jnp.exp(jnp.mean(jnp.log(scale), -1))


def d_shape(scale_q, eps_q, scale_c, eps_c, cfg: MatchConfig) -> jax.Array:
    """w_r ||log r_q - log r_c|| + w_eps ||eps_q - eps_c||, r = a / m (broadcasting over leading axes)."""
    log_r_q = jnp.log(scale_q) - jnp.log(geometric_mean(scale_q))[..., None]
    log_r_c = jnp.log(scale_c) - jnp.log(geometric_mean(scale_c))[..., None]
    d_ratio = jnp.linalg.norm(log_r_q - log_r_c, axis=-1)
    d_eps = jnp.linalg.norm(eps_q - eps_c, axis=-1)
    return cfg.w_r * d_ratio + cfg.w_eps * d_eps


def match_score(scale_q, eps_q, scale_c, eps_c, cfg: MatchConfig) -> jax.Array:
    """s = d_shape + lambda_s |log(m_q / m_c)| + lambda_a mean_k |a_k^q - a_k^c| / max(a_k^q, a_k^c)."""
    d_scale = jnp.abs(jnp.log(geometric_mean(scale_q) / geometric_mean(scale_c)))
    d_abs = jnp.mean(jnp.abs(scale_q - scale_c) / jnp.maximum(scale_q, scale_c), -1)
    return d_shape(scale_q, eps_q, scale_c, eps_c, cfg) + cfg.lambda_s * d_scale + cfg.lambda_a * d_abs


def _best_pair(dist: jax.Array, q_valid: jax.Array, c_valid: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Best over (query param, candidate param) pairs: dist [..., 2, 2] -> (min, q index, c index)."""
    ok = q_valid[..., :, None] & c_valid[..., None, :]
    flat = jnp.where(ok, dist, jnp.inf).reshape(dist.shape[:-2] + (4,))
    k = jnp.argmin(flat, -1)
    return jnp.min(flat, -1), k // 2, k % 2


@functools.partial(jax.jit, static_argnames="cfg")
def match(query_scale: jax.Array, query_epsilon: jax.Array, db: MatchDB, cfg: MatchConfig = MatchConfig()) -> MatchResult:
    """Top-K2 database primitives for each query: query_scale [Q, 3], query_epsilon [Q, 2] -> MatchResult."""
    qs, qe, qv = parameterisations(query_scale, query_epsilon, cfg)  # [Q, 2, ...]
    k1 = min(cfg.K1, db.scale.shape[0])
    k2 = min(cfg.K2, k1)
    # Step 1 over the whole database: [Q, P, 2 (query), 2 (db)].
    shape_all = d_shape(qs[:, None, :, None], qe[:, None, :, None], db.scale[None, :, None], db.epsilon[None, :, None], cfg)
    best_shape, _, _ = _best_pair(shape_all, qv[:, None], db.param_valid[None])
    _, top1 = jax.lax.top_k(-best_shape, k1)  # [Q, K1]
    # Step 2 on the K1 survivors.
    cs, ce, cv = db.scale[top1], db.epsilon[top1], db.param_valid[top1]  # [Q, K1, 2, ...]
    s_all = match_score(qs[:, None, :, None], qe[:, None, :, None], cs[:, :, None], ce[:, :, None], cfg)
    s, q_param, c_param = _best_pair(s_all, qv[:, None], cv)
    neg_s, order = jax.lax.top_k(-s, k2)
    shape_k1 = jnp.take_along_axis(best_shape, top1, 1)
    take = lambda x: jnp.take_along_axis(x, order, 1)
    return MatchResult(take(top1), -neg_s, take(shape_k1), take(q_param), take(c_param))


def transfer_grasps(query: Superquadric, result: MatchResult, db: MatchDB) -> tuple[jax.Array, jax.Array, jax.Array]:
    """World grasps of the matched primitives: T = T_sq^q (T_sq^c)^-1 applied to their templates.

    query: Superquadric batched [Q] (its fitted world pose T_sq^q); result from `match`.
    Templates are stored in each candidate's superquadric frame, so T (T_sq^c g) = T_sq^q g; when an
    equivalent (45 deg dual) parameterisation was matched, its frame is the original turned about z.
    Returns (poses [Q, K2, G, 4, 4], widths [Q, K2, G], mask [Q, K2, G]).
    """
    quarter = jnp.pi / 4
    turn = rot_z(quarter * (result.query_param - result.db_param).astype(jnp.float32))  # [Q, K2, 3, 3]
    rotation = query.rotation[:, None] @ turn
    t_q = pose_matrix(rotation, jnp.broadcast_to(query.translation[:, None], rotation.shape[:-1]))
    poses = t_q[:, :, None] @ db.grasps[result.index]
    return poses, db.widths[result.index], db.mask[result.index]
