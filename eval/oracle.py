"""`oracle-topdown`: a diagnostic method that reads the simulator's ground truth (not a paper method).

For the objects seen by the camera it builds top-down grasps closing across each object's two most
horizontal mesh axes (as `envs.simple_grasps.top_down_grasps`, but the width is capped at max_opening
instead of dropping objects that leave less than the contact clearance) and across 12 yaws, keeps
those whose open hand,
swept along the approach, holds no observed point in a finger or the palm, and returns one of them:
drawn at random by the plan's seed (default, so that a grasp that fails is not repeated every attempt:
a failed trial leaves the scene unchanged) or the narrowest grasp on the highest object
(`order="highest"`). It validates the harness: a working harness lets it clear most tiny-set scenes.
"""

from __future__ import annotations

import time

import jax.numpy as jnp
import numpy as np
from scipy.spatial.transform import Rotation

from envs import simple_grasps
from sgjax.samplers.gpd import swept_hits, first_per_voxel
from eval.protocol import Decision, near_grasps


def top_down_candidates(scene, index: int, depth: float = 0.03, table_clearance: float = 0.01,
                        min_margin: float = 0.004, yaws: int = 12) -> tuple[np.ndarray, np.ndarray]:
    """Top-down grasps of object `index`: poses [G, 4, 4], widths [G], narrowest first.

    Closing directions: the object's two most horizontal mesh axes (as `simple_grasps`) and `yaws`
    horizontal directions evenly over 180 deg. Each grasp is centred on the object's extent across and
    along its closing direction; width = extent + 2 * contact_threshold capped at max_opening;
    directions wider than max_opening - min_margin are left out. Fingertips `depth` below the object's
    top, at least `table_clearance` above the table.
    """
    spec = scene.gripper
    rotation = Rotation.from_quat(np.roll(scene.object_poses()[index, 3:], -1)).as_matrix()
    vertices = simple_grasps.object_vertices(scene, index)
    tips = max(vertices[:, 2].max() - depth, table_clearance)
    vertical = int(np.argmax(np.abs(rotation[2])))
    axes = [rotation[:, a] for a in range(3) if a != vertical]
    angles = np.arange(yaws) * np.pi / max(yaws, 1)
    axes += [np.array([np.cos(a), np.sin(a), 0.0]) for a in angles]
    poses, widths = [], []
    for x in axes:
        pose, extent = simple_grasps.top_down_pose(vertices, x, tips, spec)
        if pose is None or extent > spec.max_opening - min_margin:
            continue
        poses.append(pose)
        widths.append(min(extent + 2 * spec.contact_threshold, spec.max_opening))
    order = np.argsort(widths, kind="stable")
    return np.reshape(poses, (-1, 4, 4))[order], np.asarray(widths)[order]


class OracleTopDown:
    """Ground-truth top-down grasps, collision-checked against the observed cloud (see module doc)."""

    name = "oracle-topdown"
    uses_ground_truth = True

    def __init__(self, depth: float = 0.03, order: str = "random", voxel_size: float = 0.004,
                 approach_clearance: float = 0.05):
        if order not in ("random", "highest"):
            raise ValueError(f"order must be 'random' or 'highest', got {order!r}")
        self.depth = depth
        self.order = order
        self.voxel_size = voxel_size
        self.approach_clearance = approach_clearance
        self._scene = None

    def set_scene(self, scene) -> None:
        """The scene the next `plan` call observes (ground truth)."""
        self._scene = scene

    def plan(self, points: np.ndarray, labels: np.ndarray, viewpoint, seed: int = 0, avoid=None) -> Decision:
        if self._scene is None:
            raise RuntimeError("oracle-topdown reads the ground truth: call set_scene(scene) before plan")
        start = time.perf_counter()
        scene, spec = self._scene, self._scene.gripper
        points = np.asarray(points, np.float32).reshape(-1, 3)
        labels = np.asarray(labels).reshape(-1)
        seen = [int(i) for i in np.unique(labels[labels >= 0]) if scene.present[i]]
        seen.sort(key=lambda i: -simple_grasps.object_vertices(scene, i)[:, 2].max())  # highest first
        cloud = points[labels >= 0]
        cloud = jnp.asarray(cloud[first_per_voxel(cloud, self.voxel_size)])
        free = []  # (object, pose, width) of the collision-free grasps
        tried = 0
        for index in seen:
            poses, widths = top_down_candidates(scene, index, self.depth)
            fresh = ~near_grasps(poses, avoid, spec)  # not one that already failed
            for pose, width in zip(poses[fresh], widths[fresh]):
                tried += 1
                local = (cloud - pose[:3, 3]) @ pose[:3, :3]
                hits = swept_hits(local, jnp.asarray(width, jnp.float32), spec, self.approach_clearance)
                if not bool(jnp.any(hits)):
                    free.append((index, pose, float(width)))
            if free and self.order == "highest":
                break
        if free:
            pick = 0 if self.order == "highest" else int(np.random.default_rng(seed).integers(len(free)))
            index, pose, width = free[pick]
            elapsed = time.perf_counter() - start
            timing = {"stage1_s": elapsed, "stage2_s": 0.0, "total_s": elapsed}
            return Decision(pose, width, 1.0, "", timing, {"object": index, "tried": tried, "free": len(free)})
        elapsed = time.perf_counter() - start
        timing = {"stage1_s": elapsed, "stage2_s": 0.0, "total_s": elapsed}
        reason = f"no collision-free top-down grasp on {len(seen)} visible object(s) ({tried} tried)"
        return Decision(None, 0.0, 0.0, reason, timing, {"tried": tried})
