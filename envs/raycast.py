"""Ray casting against a scene: the depth camera's one job that needs an engine.

`cast_rays` casts rays from one origin on the C engine (`backend="cpu"`, `mujoco.mj_multiRay`, here)
or on MJX (`backend="mjx"`, `mjx.ray`, JAX implementation, `envs.raycast_mjx`; the same hits). Ray
casting has its own modules, apart from the trial backends, so that the camera never reaches into a
simulation backend.
"""

from __future__ import annotations

import mujoco
import numpy as np

from envs import scene as scene_lib

BACKENDS = ("cpu", "mjx")


def cast_rays(scene: scene_lib.Scene, data: mujoco.MjData, origin: np.ndarray, directions: np.ndarray,
              groups: np.ndarray, max_depth: float, backend: str = "cpu") -> tuple[np.ndarray, np.ndarray]:
    """Rays from origin [3] along unit directions [R, 3] against the geoms of `groups` [mjNGROUP] 0/1 in
    the state `data` (of scene.model) -> (geom id [R] int32, -1 for none; distance [R], -1 for none)."""
    if backend == "cpu":
        n = len(directions)
        geomid = np.empty(n, np.int32)
        dist = np.empty(n, np.float64)
        mujoco.mj_multiRay(scene.model, data, origin, directions.ravel(), groups, True, -1, geomid, dist, None, n, max_depth)
        return geomid, dist
    if backend == "mjx":
        from envs.raycast_mjx import cast_rays_mjx  # imports MJX only when asked for

        return cast_rays_mjx(scene, data, origin, directions, groups, max_depth)
    raise ValueError(f"camera backend must be 'cpu' or 'mjx', got {backend!r}")
