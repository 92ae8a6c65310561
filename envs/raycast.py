"""Ray casting against a scene: the depth camera's one job that needs an engine.

`cast_rays` casts rays from one origin on the C engine (`backend="cpu"`, `mujoco.mj_multiRay`, here)
or on MJX (`backend="mjx"`, `mjx.ray`, JAX implementation, `envs.raycast_mjx`; the same hits). Ray
casting has its own modules, apart from the trial backends, so that the camera never reaches into a
simulation backend.
"""

from __future__ import annotations

import copy
import functools
import os
from concurrent.futures import ThreadPoolExecutor

import mujoco
import numpy as np

from envs import scene as scene_lib

BACKENDS = ("cpu", "mjx")


# mj_multiRay runs on one core and releases the GIL: the rays are cast in RAY_THREADS parts at once
# (one MjData copy each, since it allocates on its data's stack). Each ray's hit is computed alone, so
# the result is the same as in one call; ~1.4x on a busy 2-core machine for the 640 x 480 camera.
RAY_THREADS = max(1, min(4, os.cpu_count() or 1))
_MIN_RAYS_PER_THREAD = 20000


@functools.lru_cache(maxsize=1)
def _pool(threads: int) -> ThreadPoolExecutor:
    return ThreadPoolExecutor(threads, thread_name_prefix="sgjax-rays")


def _cast_rays_cpu(model, data, origin, directions, groups, max_depth: float) -> tuple[np.ndarray, np.ndarray]:
    n = len(directions)
    geomid = np.empty(n, np.int32)
    dist = np.empty(n, np.float64)
    directions = np.ascontiguousarray(directions, np.float64)
    parts = max(1, min(RAY_THREADS, n // _MIN_RAYS_PER_THREAD))
    bounds = np.linspace(0, n, parts + 1).astype(int)

    def cast(i: int, part_data) -> None:
        a, b = bounds[i], bounds[i + 1]
        mujoco.mj_multiRay(model, part_data, origin, directions[a:b].ravel(), groups, True, -1, geomid[a:b], dist[a:b],
                           None, b - a, max_depth)

    if parts == 1:
        cast(0, data)
    else:
        list(_pool(parts).map(cast, range(parts), [data] + [copy.copy(data) for _ in range(parts - 1)]))
    return geomid, dist


def cast_rays(scene: scene_lib.Scene, data: mujoco.MjData, origin: np.ndarray, directions: np.ndarray,
              groups: np.ndarray, max_depth: float, backend: str = "cpu") -> tuple[np.ndarray, np.ndarray]:
    """Rays from origin [3] along unit directions [R, 3] against the geoms of `groups` [mjNGROUP] 0/1 in
    the state `data` (of scene.model) -> (geom id [R] int32, -1 for none; distance [R], -1 for none)."""
    if backend == "cpu":
        return _cast_rays_cpu(scene.model, data, origin, directions, groups, max_depth)
    if backend == "mjx":
        from envs.raycast_mjx import cast_rays_mjx  # imports MJX only when asked for

        return cast_rays_mjx(scene, data, origin, directions, groups, max_depth)
    raise ValueError(f"camera backend must be 'cpu' or 'mjx', got {backend!r}")
