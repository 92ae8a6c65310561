"""Small rotation helpers (plain functions over arrays, JAX)."""

from __future__ import annotations

import jax
import jax.numpy as jnp


def hat(omega: jax.Array) -> jax.Array:
    """Skew-symmetric matrix of a vector: omega[..., 3] -> [..., 3, 3]."""
    x, y, z = omega[..., 0], omega[..., 1], omega[..., 2]
    zero = jnp.zeros_like(x)
    return jnp.stack(
        [
            jnp.stack([zero, -z, y], -1),
            jnp.stack([z, zero, -x], -1),
            jnp.stack([-y, x, zero], -1),
        ],
        -2,
    )


def so3_exp(omega: jax.Array) -> jax.Array:
    """Rotation matrix of an axis-angle vector (Rodrigues), safe at zero: omega[..., 3] -> [..., 3, 3]."""
    theta2 = jnp.sum(omega * omega, axis=-1)[..., None, None]
    small = theta2 < 1e-8
    safe2 = jnp.where(small, 1.0, theta2)
    theta = jnp.sqrt(safe2)
    # Taylor expansions near zero keep the function and its derivatives finite.
    a = jnp.where(small, 1.0 - theta2 / 6.0, jnp.sin(theta) / theta)
    b = jnp.where(small, 0.5 - theta2 / 24.0, (1.0 - jnp.cos(theta)) / safe2)
    k = hat(omega)
    eye = jnp.eye(3, dtype=omega.dtype)
    return eye + a * k + b * (k @ k)


def rot_z(angle: jax.Array | float) -> jax.Array:
    """Rotation about z by `angle` radians: [...] -> [..., 3, 3]."""
    angle = jnp.asarray(angle)
    c, s = jnp.cos(angle), jnp.sin(angle)
    zero, one = jnp.zeros_like(c), jnp.ones_like(c)
    return jnp.stack(
        [jnp.stack([c, -s, zero], -1), jnp.stack([s, c, zero], -1), jnp.stack([zero, zero, one], -1)],
        -2,
    )


def proper(rotation: jax.Array) -> jax.Array:
    """Flip the last column where needed so that det = +1: [..., 3, 3] -> [..., 3, 3]."""
    sign = jnp.sign(jnp.linalg.det(rotation))
    sign = jnp.where(sign == 0, 1.0, sign)
    return rotation.at[..., :, 2].multiply(sign[..., None])


def random_rotation(key: jax.Array, shape: tuple[int, ...] = ()) -> jax.Array:
    """Uniformly random rotations (from random unit quaternions): -> [*shape, 3, 3]."""
    q = jax.random.normal(key, (*shape, 4))
    q = q / jnp.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return jnp.stack(
        [
            jnp.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            jnp.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            jnp.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


# Points between frames. Written as three broadcast multiply-adds rather than an einsum: XLA on CPU
# lowers a batched 3x3 product per point to a slow dot, and cannot fuse it with what follows (a
# region test, a reduction over points), so [M, N, 3] intermediates get materialised; the elementwise
# form fuses (measured: 1024 poses x 4096 points with a region test, 122 ms -> 4.5 ms).


def points_to_frame(points: jax.Array, rotation: jax.Array, translation: jax.Array) -> jax.Array:
    """World points [..., N, 3] in frames (rotation [..., 3, 3], translation [..., 3]) -> [..., N, 3],
    p_local = R^T (p - t). Batch axes broadcast (one cloud [N, 3] against M frames gives [M, N, 3])."""
    d = points - translation[..., None, :]
    return d[..., 0:1] * rotation[..., None, 0, :] + d[..., 1:2] * rotation[..., None, 1, :] + d[..., 2:3] * rotation[..., None, 2, :]


def points_from_frame(points: jax.Array, rotation: jax.Array, translation: jax.Array) -> jax.Array:
    """Frame points [..., N, 3] -> world [..., N, 3], p = R p_local + t (the inverse of `points_to_frame`)."""
    return (
        points[..., 0:1] * rotation[..., None, :, 0]
        + points[..., 1:2] * rotation[..., None, :, 1]
        + points[..., 2:3] * rotation[..., None, :, 2]
        + translation[..., None, :]
    )
