"""Ray casting on MJX (`mjx.ray`, JAX implementation): `envs.raycast`'s "mjx" backend."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import mjx

from envs import scene as scene_lib


@functools.lru_cache(maxsize=4)
def _camera_model(assets: tuple, config: scene_lib.SceneConfig, gripper) -> tuple[mujoco.MjModel, mjx.Model]:
    """The sensorless scene with one unused material: mjx.ray reads mat_rgba, which fails on a model
    without materials (geoms without a material are still judged by their own rgba)."""
    spec = scene_lib.build_sensorless_spec(assets, config, gripper)
    spec.add_material(name="mjx_ray_workaround")
    model = spec.compile()
    return model, mjx.put_model(model, impl="jax")


@functools.partial(jax.jit, static_argnames=("groups", "chunk"))
def _cast(mx, dx, origin, directions, groups: tuple, chunk: int):
    """mjx.ray for directions [R, 3] (R a multiple of chunk) from origin [3] -> (dist [R], geom id [R]).
    Chunks bound the [rays, mesh triangles] intermediate."""
    one = lambda v: mjx.ray(mx, dx, origin, v, groups, True, -1)
    dist, geom = jax.lax.map(jax.vmap(one), directions.reshape(-1, chunk, 3))
    return dist.reshape(-1), geom.reshape(-1)


def cast_rays_mjx(scene: scene_lib.Scene, data: mujoco.MjData, origin: np.ndarray, directions: np.ndarray,
                  groups: np.ndarray, max_depth: float, chunk: int = 256) -> tuple[np.ndarray, np.ndarray]:
    """The depth camera's rays on MJX (JAX impl), as `mujoco.mj_multiRay` casts them on the C engine:
    origin [3], directions [R, 3] unit, groups [mjNGROUP] 0/1 -> (geom id [R] int32, -1 for none;
    distance [R], -1 for none). `data` holds the state to render (of scene.model)."""
    model, mx = _camera_model(scene.assets, scene.config, scene.gripper)
    state = np.empty(mujoco.mj_stateSize(scene.model, scene_lib.STATE_SPEC))
    mujoco.mj_getState(scene.model, data, state, scene_lib.STATE_SPEC)
    camera_data = mujoco.MjData(model)
    mujoco.mj_setState(model, camera_data, state, scene_lib.STATE_SPEC)
    mujoco.mj_kinematics(model, camera_data)
    dx = mjx.put_data(model, camera_data, impl="jax")
    n = len(directions)
    padded = np.zeros((-(-n // chunk) * chunk, 3), np.float32)
    padded[:n] = directions
    padded[n:] = directions[0]
    dist, geom = _cast(mx, dx, jnp.asarray(origin, jnp.float32), jnp.asarray(padded),
                       tuple(int(g) for g in groups), chunk)
    dist, geom = np.asarray(dist, np.float64)[:n], np.asarray(geom, np.int32)[:n]
    miss = (geom < 0) | (dist > max_depth)
    return np.where(miss, -1, geom).astype(np.int32), np.where(miss, -1.0, dist)
