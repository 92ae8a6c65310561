"""Superquadric geometry (paper eq. 1): implicit function, radial distance, volume, meshes, frames.

A superquadric is five shape numbers {a_x, a_y, a_z, eps1, eps2} and a pose T_sq = (R_sq, t_sq).
`rotation` holds the superquadric axes as columns in the world frame, so a world point p has local
coordinates (p - t) @ R.  Everything here is batched over leading axes and works under jit/vmap,
except `to_mesh` and `sample_surface`, which build trimesh objects on the host.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
from jax.scipy.special import gammaln

from sgjax.geometry.rotations import points_to_frame, proper, rot_z

# Shape exponents are clamped to this range: eps in (0, 2] is convex (paper Sec. II-A), and eps >= 0.1
# keeps powers like |x|^(2/eps) finite in float32.
EPS_MIN = 0.1
EPS_MAX = 2.0
# Guards log|x| at x = 0 (points exactly on a symmetry plane or at the centre).
_TINY = 1e-12


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Superquadric:
    """A posed superquadric; every field may carry the same leading batch axes [...].

    scale: [..., 3] semi-axes (a_x, a_y, a_z) in metres.
    epsilon: [..., 2] shape exponents (eps1, eps2).
    rotation: [..., 3, 3] superquadric axes as columns, in the world frame.
    translation: [..., 3] centre in the world frame.
    """

    scale: jax.Array
    epsilon: jax.Array
    rotation: jax.Array
    translation: jax.Array

    @staticmethod
    def create(scale, epsilon, rotation=None, translation=None) -> "Superquadric":
        """Build from array-likes; rotation defaults to identity, translation to zero."""
        scale = jnp.asarray(scale, jnp.float32)
        batch = scale.shape[:-1]
        rotation = jnp.broadcast_to(jnp.eye(3), (*batch, 3, 3)) if rotation is None else rotation
        translation = jnp.zeros((*batch, 3)) if translation is None else translation
        return Superquadric(
            scale,
            jnp.asarray(epsilon, jnp.float32),
            jnp.asarray(rotation, jnp.float32),
            jnp.asarray(translation, jnp.float32),
        )

    def __getitem__(self, index) -> "Superquadric":
        return jax.tree_util.tree_map(lambda x: x[index], self)

    def to_matrix(self) -> jax.Array:
        """Homogeneous pose T_sq: [..., 4, 4]."""
        return pose_matrix(self.rotation, self.translation)


def pose_matrix(rotation: jax.Array, translation: jax.Array) -> jax.Array:
    """Stack rotation[..., 3, 3] and translation[..., 3] into homogeneous [..., 4, 4]."""
    batch = rotation.shape[:-2]
    top = jnp.concatenate([rotation, translation[..., :, None]], axis=-1)
    bottom = jnp.broadcast_to(jnp.array([0.0, 0.0, 0.0, 1.0], rotation.dtype), (*batch, 1, 4))
    return jnp.concatenate([top, bottom], axis=-2)


def to_local(points: jax.Array, sq: Superquadric) -> jax.Array:
    """World points[..., N, 3] -> superquadric-frame coordinates [..., N, 3]."""
    return points_to_frame(points, sq.rotation, sq.translation)


def log_implicit_local(local: jax.Array, scale: jax.Array, epsilon: jax.Array) -> jax.Array:
    """log F of eq. 1 for local points[..., N, 3], computed in log space so that no power overflows.

    scale: [..., 3], epsilon: [..., 2]. Returns [..., N]; F < 1 inside, 1 on the surface, > 1 outside.
    """
    e1 = epsilon[..., 0, None]
    e2 = epsilon[..., 1, None]
    log_r = 0.5 * jnp.log(local * local + _TINY) - jnp.log(scale)[..., None, :]
    log_xy = (e2 / e1) * jnp.logaddexp(2.0 / e2 * log_r[..., 0], 2.0 / e2 * log_r[..., 1])
    return jnp.logaddexp(log_xy, 2.0 / e1 * log_r[..., 2])


def implicit_function(points: jax.Array, sq: Superquadric) -> jax.Array:
    """Inside-outside function F (eq. 1 left-hand side) at world points[..., N, 3] -> [..., N]."""
    return jnp.exp(log_implicit_local(to_local(points, sq), sq.scale, sq.epsilon))


def signed_radial_distance_local(local: jax.Array, scale: jax.Array, epsilon: jax.Array) -> jax.Array:
    """Signed radial distance |x| (1 - F^(-eps1/2)) of local points[..., N, 3] -> [..., N].

    The distance along the ray from the centre to the point, between the point and the surface
    (the EMS residual); negative inside. Its square is smooth, which the least-squares step needs.
    """
    log_f = log_implicit_local(local, scale, epsilon)
    norm = jnp.sqrt(jnp.sum(local * local, axis=-1) + _TINY)
    return norm * (1.0 - jnp.exp(-0.5 * epsilon[..., 0, None] * log_f))


def tangent_radial_distance_local(local: jax.Array, scale: jax.Array, epsilon: jax.Array) -> jax.Array:
    """Signed radial distance projected on the surface normal: local points[..., N, 3] -> [..., N].

    Along a ray from the centre the gradient of F keeps its direction (F is homogeneous in the scaled
    coordinates), so the radial distance times the cosine between the ray and the normal there is the
    distance to the tangent plane at the ray's surface point, a first-order Euclidean distance. With
    x . grad(log F) = 2/eps1 this is (1 - F^(-eps1/2)) / |grad(log F)| * 2/eps1, all in log space.
    Unlike the plain radial distance it does not shrink for oblique surfaces, which in single-view
    clouds would otherwise favour superquadrics that bulge into the unseen side.
    """
    e1 = epsilon[..., 0, None]
    e2 = epsilon[..., 1, None]
    log_abs = 0.5 * jnp.log(local * local + _TINY)
    log_r = log_abs - jnp.log(scale)[..., None, :]
    u, v = 2.0 / e2 * log_r[..., 0], 2.0 / e2 * log_r[..., 1]
    log_uv = jnp.logaddexp(u, v)
    log_xy = (e2 / e1) * log_uv
    w = 2.0 / e1 * log_r[..., 2]
    log_f = jnp.logaddexp(log_xy, w)
    # d log F / d coordinate, up to the common factor 2/eps1, as logs of magnitudes
    g_x = log_xy - log_f + u - log_uv - log_abs[..., 0]
    g_y = log_xy - log_f + v - log_uv - log_abs[..., 1]
    g_z = w - log_f - log_abs[..., 2]
    log_g = 0.5 * jnp.logaddexp(jnp.logaddexp(2 * g_x, 2 * g_y), 2 * g_z)
    return (1.0 - jnp.exp(-0.5 * e1 * log_f)) * jnp.exp(-log_g)


def radial_distance(points: jax.Array, sq: Superquadric) -> jax.Array:
    """Unsigned radial distance of world points[..., N, 3] to the surface -> [..., N] (metres)."""
    return jnp.abs(signed_radial_distance_local(to_local(points, sq), sq.scale, sq.epsilon))


def volume(sq: Superquadric) -> jax.Array:
    """Closed-form volume 2 a_x a_y a_z e1 e2 B(e1/2 + 1, e1) B(e2/2, e2/2) -> [...] (m^3)."""

    def log_beta(x, y):
        return gammaln(x) + gammaln(y) - gammaln(x + y)

    e1, e2 = sq.epsilon[..., 0], sq.epsilon[..., 1]
    log_b = log_beta(0.5 * e1 + 1.0, e1) + log_beta(0.5 * e2, 0.5 * e2)
    return 2.0 * jnp.prod(sq.scale, axis=-1) * e1 * e2 * jnp.exp(log_b)


# ---------------------------------------------------------------------------------------------
# Frames: canonical form and the paper's equivalent parameterisation.


def _swap_xy(sq: Superquadric) -> Superquadric:
    """The same surface with x and y exchanged (a 90 deg turn about z; always a symmetry)."""
    r = sq.rotation
    rot = jnp.stack([r[..., :, 1], -r[..., :, 0], r[..., :, 2]], axis=-1)
    scale = sq.scale[..., jnp.array([1, 0, 2])]
    return Superquadric(scale, sq.epsilon, rot, sq.translation)


def _select(cond: jax.Array, a: Superquadric, b: Superquadric) -> Superquadric:
    """Per-batch-element choice between two superquadrics: cond[...] bool."""

    def pick(x, y):
        c = cond.reshape(cond.shape + (1,) * (x.ndim - cond.ndim))
        return jnp.where(c, x, y)

    return jax.tree_util.tree_map(pick, a, b)


def canonicalize(sq: Superquadric, eps_tol: float = 1e-3) -> Superquadric:
    """The canonical frame among the frames that describe the same surface.

    Symmetries used: the x/y exchange (always), any axis permutation when |eps1 - eps2| < eps_tol
    (then eq. 1 treats all three axes alike), and flipping the signs of two axes. Canonical means
    a_x >= a_y (and a_x >= a_y >= a_z when eps1 ~ eps2), the z axis pointing up (z-component >= 0),
    and the largest component of the x axis positive. Shapes: as `Superquadric`.
    """
    sq = _select(sq.scale[..., 1] > sq.scale[..., 0], _swap_xy(sq), sq)

    order = jnp.argsort(-sq.scale, axis=-1)
    sorted_scale = jnp.take_along_axis(sq.scale, order, axis=-1)
    sorted_rot = proper(jnp.take_along_axis(sq.rotation, order[..., None, :], axis=-1))
    sym = jnp.abs(sq.epsilon[..., 0] - sq.epsilon[..., 1]) < eps_tol
    sq = _select(sym, Superquadric(sorted_scale, sq.epsilon, sorted_rot, sq.translation), sq)

    r = sq.rotation
    flip_xz = jnp.where(r[..., 2, 2] < 0, -1.0, 1.0)
    r = r * jnp.stack([flip_xz, jnp.ones_like(flip_xz), flip_xz], -1)[..., None, :]
    x_axis = r[..., :, 0]
    lead = jnp.take_along_axis(x_axis, jnp.argmax(jnp.abs(x_axis), -1)[..., None], -1)[..., 0]
    flip_xy = jnp.where(lead < 0, -1.0, 1.0)
    r = r * jnp.stack([flip_xy, flip_xy, jnp.ones_like(flip_xy)], -1)[..., None, :]
    return Superquadric(sq.scale, sq.epsilon, r, sq.translation)


def duality_factor(eps2: jax.Array, xp=jnp) -> jax.Array:
    """In-plane scale factor of the 45 deg dual: sqrt(2) for a square (eps2=0), 1/sqrt(2) for a diamond (eps2=2).

    A square of half-side a, turned by 45 deg, is a diamond (eps2 = 2) with vertices at a*sqrt(2); the
    factor is interpolated linearly in eps2 towards 1 at eps2 = 1 (a circle is its own dual).
    xp: jnp, or np for float32 arrays on the host (the same values bit for bit, op by op).
    """
    s2 = xp.sqrt(xp.float32(2.0))
    lower = s2 - (s2 - 1.0) * xp.minimum(eps2, 1.0)
    upper = 1.0 / (s2 - (s2 - 1.0) * xp.minimum(2.0 - eps2, 1.0))
    return xp.where(eps2 <= 1.0, lower, upper)


def dual(sq: Superquadric) -> Superquadric:
    """The 45 deg dual parameterisation: rotate about z by 45 deg, eps2 -> 2 - eps2, scale a_x, a_y."""
    f = duality_factor(sq.epsilon[..., 1])
    scale = sq.scale * jnp.stack([f, f, jnp.ones_like(f)], -1)
    eps = jnp.stack([sq.epsilon[..., 0], 2.0 - sq.epsilon[..., 1]], -1)
    rot = sq.rotation @ rot_z(jnp.full(sq.scale.shape[:-1], jnp.pi / 4))
    return Superquadric(scale, jnp.clip(eps, EPS_MIN, EPS_MAX), rot, sq.translation)


def equivalent_parameterisations(
    sq: Superquadric, eps_tol: float = 0.3, axis_tol: float = 0.1
) -> tuple[Superquadric, jax.Array]:
    """The paper's non-uniqueness rule (Sec. IV-B, "Fast matching").

    When eps2 is within `eps_tol` of 0 or 2 and |a_x - a_y| / max(a_x, a_y) < `axis_tol`, the surface
    also admits the dual parameterisation (`dual`). Returns (both, applies): `both` has a new leading
    axis of size 2 holding [original, equivalent] (the equivalent equals the original where the rule
    does not apply), `applies` is bool[...].
    """
    e2 = sq.epsilon[..., 1]
    near = (e2 < eps_tol) | (e2 > 2.0 - eps_tol)
    ax, ay = sq.scale[..., 0], sq.scale[..., 1]
    similar = jnp.abs(ax - ay) / jnp.maximum(ax, ay) < axis_tol
    applies = near & similar
    other = _select(applies, dual(sq), sq)
    both = jax.tree_util.tree_map(lambda a, b: jnp.stack([a, b]), sq, other)
    return both, applies


# ---------------------------------------------------------------------------------------------
# Host-side meshes and surface samples.


def _spow(x: np.ndarray, e: float) -> np.ndarray:
    return np.sign(x) * np.abs(x) ** e


def _quarter_angles(eps: float, n: int) -> np.ndarray:
    """Angles in [0, pi/2] dense both in angle and in the resulting coordinates.

    Uniform angles alone leave the flat faces of boxy shapes (small eps) almost empty; adding the
    angles at which cos^eps and sin^eps are uniform fills them.
    """
    v = np.linspace(0.0, 1.0, n)
    angles = np.concatenate(
        [np.linspace(0.0, np.pi / 2, n), np.arccos(v ** (1.0 / eps)), np.arcsin(v ** (1.0 / eps))]
    )
    angles = np.unique(np.round(np.clip(angles, 0.0, np.pi / 2), 9))
    return angles


def _local_triangles(scale: np.ndarray, e1: float, e2: float, resolution: int) -> tuple[np.ndarray, np.ndarray]:
    """Parametric grid of the surface in its own frame: vertices[V, 3], faces[F, 3] (outward winding).

    Rings of constant eta between the poles, plus one vertex per pole; some faces near the poles and
    flat faces are degenerate (zero area), which area-weighted sampling ignores and trimesh merges.
    """
    q_eta = _quarter_angles(e1, resolution)
    eta = np.concatenate([-q_eta[::-1], q_eta[1:]])[1:-1]  # interior rings; poles added below
    q_om = _quarter_angles(e2, resolution)
    omega = np.concatenate([q_om, np.pi - q_om[::-1][1:], np.pi + q_om[1:], 2 * np.pi - q_om[::-1][1:-1]])
    ce, se = _spow(np.cos(eta), e1), _spow(np.sin(eta), e1)
    co, so = _spow(np.cos(omega), e2), _spow(np.sin(omega), e2)
    n_ring, n_om = len(eta), len(omega)
    ring = np.stack(
        [
            scale[0] * ce[:, None] * co[None, :],
            scale[1] * ce[:, None] * so[None, :],
            scale[2] * np.repeat(se[:, None], n_om, 1),
        ],
        -1,
    ).reshape(-1, 3)
    verts = np.concatenate([ring, [[0, 0, -scale[2]]], [[0, 0, scale[2]]]])
    south, north = n_ring * n_om, n_ring * n_om + 1
    i, j = np.meshgrid(np.arange(n_ring - 1), np.arange(n_om), indexing="ij")
    a, b = i * n_om + j, i * n_om + (j + 1) % n_om
    c, d = (i + 1) * n_om + (j + 1) % n_om, (i + 1) * n_om + j
    j = np.arange(n_om)
    top = (n_ring - 1) * n_om
    faces = np.concatenate(
        [
            np.stack([a, b, c], -1).reshape(-1, 3),
            np.stack([a, c, d], -1).reshape(-1, 3),
            np.stack([np.full(n_om, south), (j + 1) % n_om, j], -1),
            np.stack([np.full(n_om, north), top + j, top + (j + 1) % n_om], -1),
        ]
    )
    return verts, faces


def _unbatched(sq: Superquadric) -> tuple[np.ndarray, float, float, np.ndarray]:
    scale = np.asarray(sq.scale, np.float64)
    if scale.shape != (3,):
        raise ValueError(f"expected one superquadric, got scale of shape {scale.shape}")
    e1, e2 = (float(e) for e in np.asarray(sq.epsilon))
    return scale, e1, e2, np.asarray(sq.to_matrix(), np.float64)


def to_mesh(sq: Superquadric, resolution: int = 16) -> trimesh.Trimesh:
    """Watertight triangle mesh of one (unbatched) superquadric in the world frame.

    `resolution` is the number of samples per quarter angle range before the extra coordinate-uniform
    angles are merged in; the mesh has O(16 * resolution^2) vertices.
    """
    import trimesh  # here: planning never builds a mesh, and trimesh's import costs a planning process ~0.3 s

    scale, e1, e2, transform = _unbatched(sq)
    verts, faces = _local_triangles(scale, e1, e2, resolution)
    mesh = trimesh.Trimesh(verts, faces, process=True)
    mesh.fix_normals()
    mesh.apply_transform(transform)
    return mesh


def sample_surface(
    sq: Superquadric, count: int, seed: int | np.random.Generator = 0, resolution: int = 16
) -> tuple[np.ndarray, np.ndarray]:
    """Points uniform in surface area (not in angle) and their outward normals, world frame.

    One (unbatched) superquadric -> (points[count, 3], normals[count, 3]).
    """
    scale, e1, e2, transform = _unbatched(sq)
    rng = np.random.default_rng(seed)
    verts, faces = _local_triangles(scale, e1, e2, resolution)
    tri = verts[faces]
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    area = 0.5 * np.linalg.norm(cross, axis=-1)
    face = rng.choice(len(faces), size=count, p=area / area.sum())
    u, v = rng.random((2, count))
    flip = u + v > 1.0  # fold the unit square onto the triangle
    u, v = np.where(flip, 1.0 - u, u), np.where(flip, 1.0 - v, v)
    t = tri[face]
    local = t[:, 0] + u[:, None] * (t[:, 1] - t[:, 0]) + v[:, None] * (t[:, 2] - t[:, 0])
    normal = cross[face] / np.maximum(2.0 * area[face], 1e-30)[:, None]
    # The surface is convex around its centre, so the outward normal has a positive dot with the position.
    normal *= np.where(np.sum(normal * local, -1) < 0, -1.0, 1.0)[:, None]
    rot, trans = transform[:3, :3], transform[:3, 3]
    return local @ rot.T + trans, normal @ rot.T


def relative_scale_error(fitted: Superquadric, truth: Superquadric) -> float:
    """Mean relative semi-axis error of one fit against the truth, after matching their frames.

    Fitted axes are matched to true axes by the largest |cos| between them (the fit may use any of the
    equivalent frames), and the truth's dual parameterisation is tried too when the paper's rule
    applies; the smaller error is returned.
    """
    from scipy.optimize import linear_sum_assignment

    a_fit = np.asarray(fitted.scale, np.float64)
    r_fit = np.asarray(fitted.rotation, np.float64)
    both, _ = equivalent_parameterisations(truth)
    errors = []
    for k in range(2):
        a_true = np.asarray(both.scale[k], np.float64)
        cos = np.abs(np.asarray(both.rotation[k], np.float64).T @ r_fit)  # [true axis, fitted axis]
        rows, cols = linear_sum_assignment(-cos)
        errors.append(float(np.mean(np.abs(a_fit[cols] - a_true[rows]) / a_true[rows])))
    return min(errors)


def prefer_square(sq: Superquadric, eps_tol: float = 0.3, axis_tol: float = 0.1) -> Superquadric:
    """Where the paper's rule finds a dual (`equivalent_parameterisations`), use the one with eps2 <= 1.

    EMS may describe a square prism as a diamond turned by 45 deg (eps2 ~ 2); choosing one of the two
    consistently for queries and database entries makes their coefficients comparable directly.
    """
    both, applies = equivalent_parameterisations(sq, eps_tol, axis_tol)
    other = jax.tree_util.tree_map(lambda x: x[1], both)
    return _select(applies & (sq.epsilon[..., 1] > 1.0), other, sq)
