"""One object alone on the table: seeded placements, the benchmark camera's view, and grasp trials on it.

For checks of how a method fares on one kind of shape (e.g. tapered objects against cylinders:
tests/test_tapered.py, tests/test_flat.py), without the clutter of the decluttering
benchmark. Objects are assets with their axis of revolution (if any) along z.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy.spatial.transform import Rotation

from envs import camera as camera_lib
from envs import scene as scene_lib
from envs import trial as trial_lib

# standing: the asset's z axis up; narrow-end-down: upside down (a frustum on its small face);
# lying: the z axis horizontal (the object rests on its side).
KINDS = ("standing", "narrow-end-down", "lying")
SHAPE_CLASSES = ("cylinder", "frustum", "cup", "lens", "pebble", "puck", "tile")


def shape_class(name: str) -> str:
    """"tapered/frustum_r30_r18" -> "frustum": the first of SHAPE_CLASSES in the name's last part, else
    that part."""
    base = name.split("/")[-1]
    return next((cls for cls in SHAPE_CLASSES if cls in base), base)


def placements(extents, kind: str, n: int, rng: np.random.Generator, spread: float = 0.06) -> np.ndarray:
    """n poses [n, 7] (position, quaternion wxyz) for an object of bounding-box `extents` (x, y, z; m)
    placed `kind` (KINDS) at a random yaw and table position (within `spread` of the table centre), 2 mm
    above the table top (z = 0), to be settled by `envs.scene.arrange_scene`."""
    if kind not in KINDS:
        raise ValueError(f"kind must be one of {KINDS}, got {kind!r}")
    ex, ey, ez = extents
    out = np.zeros((n, 7))
    for i in range(n):
        yaw = rng.uniform(0, 2 * np.pi)
        xy = rng.uniform(-spread, spread, 2)
        if kind == "standing":
            rot, height = Rotation.from_euler("z", yaw), 0.5 * ez
        elif kind == "narrow-end-down":
            rot, height = Rotation.from_euler("zx", [yaw, np.pi]), 0.5 * ez
        else:
            rot, height = Rotation.from_euler("zy", [yaw, 0.5 * np.pi]), 0.5 * max(ex, ey)
        out[i] = [*xy, height + 0.002, *np.roll(rot.as_quat(), 1)]
    return out


@dataclasses.dataclass
class Alone:
    """A settled single-object scene and one view of it: scene (object 0), obs (`envs.camera.Observation`),
    viewpoint [3] (the camera position)."""

    scene: scene_lib.Scene
    obs: camera_lib.Observation
    viewpoint: np.ndarray


def alone(asset, pose, seed: int, camera: camera_lib.CameraConfig = camera_lib.CameraConfig()) -> Alone | None:
    """`asset` placed at pose [7] and settled, seen by `camera` (noise seeded by `seed`); None when the
    object left the workspace while settling (e.g. rolled off)."""
    scene = scene_lib.arrange_scene([asset], np.asarray(pose, np.float64)[None])
    if not scene.present[0]:
        return None
    return Alone(scene, camera_lib.observe(scene, camera, seed=seed), np.asarray(camera.position, np.float64))


def success(setup: Alone, poses, widths) -> np.ndarray:
    """The benchmark's grasp trial (approach, close, lift, reorient, 1 N disturbance) of each grasp
    poses [K, 4, 4], widths [K] on the object -> bool [K] success."""
    if len(poses) == 0:
        return np.zeros(0, bool)
    return np.asarray(trial_lib.run_trials(setup.scene, 0, np.asarray(poses), np.asarray(widths)).label, bool)


def best_scored(plan, k: int, skip: int | None = None) -> tuple[list, list]:
    """The k best-scored of a `sgjax.planner.Plan`'s scored candidates by E-RNet's eval score (valid ones
    first), leaving out row `skip` of its scores -> (poses [4, 4] list, widths list), best first."""
    s = plan.scores
    order = [j for j in np.argsort(-np.where(s["valid"], s["eval_prob"], -1.0), kind="stable") if j != skip][:k]
    picked = [plan.candidates[s["object"][j]] for j in order]
    rows = [s["object_candidate"][j] for j in order]
    return [c.poses[r] for c, r in zip(picked, rows)], [c.widths[r] for c, r in zip(picked, rows)]


def spread_rows(n: int, k: int) -> np.ndarray:
    """Up to k row indices spread evenly over 0..n-1 (first and last included), unique, ascending."""
    if n <= 0 or k <= 0:
        return np.zeros(0, np.int64)
    return np.unique(np.linspace(0, n - 1, min(k, n)).round().astype(np.int64))
