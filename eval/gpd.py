"""The GPD-style geometric baseline (no learning) as a benchmark method: the candidates of
`sgjax.samplers.gpd` (antipodal sampling on the scene cloud, then geometric evaluation), ranked by
their antipodal score instead of a learned classifier (in the spirit of GPD, ten Pas et al., IJRR 2017).
"""

from __future__ import annotations

import time

import jax
import numpy as np

from sgjax.samplers.gpd import GPDConfig, candidates, evaluate, prepare_cloud, scaled_to_scene
from eval.protocol import Decision, near_grasps


class GPDMethod:
    """The GPD-style baseline as a harness method (`eval.protocol.Method`)."""

    name = "gpd"

    def __init__(self, config: GPDConfig | None = None):
        self.config = config or GPDConfig()

    def plan(self, points: np.ndarray, labels: np.ndarray, viewpoint, seed: int = 0, avoid=None) -> Decision:
        """Best grasp for a scene cloud points [P, 3] (world) with labels [P] (object id, < 0 table),
        leaving out the same grasps as the poses in avoid [F, 4, 4] (failed ones; see eval/protocol.py)."""
        start = time.perf_counter()
        cfg, _ = scaled_to_scene(self.config, labels)  # more objects in view, more samples
        cloud, mask, table_z, n = prepare_cloud(points, labels, cfg, seed)
        if n < cfg.min_points:
            elapsed = time.perf_counter() - start
            return Decision(None, 0.0, 0.0, f"only {n} object points seen",
                            {"stage1_s": elapsed, "stage2_s": 0.0, "total_s": elapsed}, {"object_points": n})
        view = np.asarray(viewpoint, np.float32).reshape(3)
        stage1 = candidates(cloud, mask, view, np.float32(table_z), jax.random.key(seed), cfg)
        stage1 = jax.block_until_ready(stage1)
        mid = time.perf_counter()
        m = cfg.num_samples * cfg.num_angles
        out = evaluate(stage1["poses"].reshape(m, 4, 4), stage1["valid"].reshape(m), cloud, mask,
                       stage1["normals"], np.float32(table_z), cfg)
        out = jax.tree_util.tree_map(np.asarray, out)
        avoided = out["valid"] & near_grasps(out["poses"], avoid, cfg.spec)
        out["scores"] = np.where(avoided, -1.0, out["scores"])
        counts = {
            "object_points": n,
            "candidates": m,
            "collision_free": int(np.asarray(stage1["valid"]).sum()),
            "kept": int((out["valid"] & ~avoided).sum()),
            "avoided": int(avoided.sum()),
        }
        if counts["kept"]:
            best = int(np.argmax(out["scores"]))
            pose = _orthonormal(out["poses"][best])
            result = (pose, float(out["widths"][best]), float(out["scores"][best]), "")
        elif counts["avoided"]:
            result = (None, 0.0, 0.0, f"all {counts['avoided']} kept candidates are the same grasp as one that already failed")
        elif counts["collision_free"]:
            reason = (
                f"none of {counts['collision_free']} collision-free candidates kept "
                f"(< {cfg.min_points} points between the fingers or colliding once centred)"
            )
            result = (None, 0.0, 0.0, reason)
        else:
            result = (None, 0.0, 0.0, f"no collision-free candidate among {m}")
        end = time.perf_counter()
        timing = {"stage1_s": mid - start, "stage2_s": end - mid, "total_s": end - start}
        return Decision(*result, timing, counts)


def _orthonormal(pose: np.ndarray) -> np.ndarray:
    """pose [4, 4] in float64 with its rotation re-orthonormalised (float32 math leaves ~1e-7)."""
    pose = np.asarray(pose, np.float64).copy()
    u, _, vt = np.linalg.svd(pose[:3, :3])
    pose[:3, :3] = u @ vt
    pose[3] = [0.0, 0.0, 0.0, 1.0]
    return pose
