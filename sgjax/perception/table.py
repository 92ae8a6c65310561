"""The table: a robust plane fit to a real cloud, its normal towards the camera."""

from __future__ import annotations

import dataclasses

import numpy as np


@dataclasses.dataclass(frozen=True)
class TablePlane:
    """plane (a, b, c, d) with (a, b, c) a unit normal towards the camera: free space a x + b y + c z + d > 0
    (`sgjax.planner.PlannerConfig.support_plane`'s convention); inliers bool [N]: the points within the fit's
    distance of it; rms: their distance's root mean square (metres); heights: the fitted points' signed
    distances above the plane [N] (`height` of them; not finite where a point was not), or None."""

    plane: tuple[float, float, float, float]
    inliers: np.ndarray
    rms: float
    heights: np.ndarray | None = dataclasses.field(default=None, repr=False, compare=False)

    @property
    def normal(self) -> np.ndarray:
        return np.asarray(self.plane[:3])

    def height(self, points: np.ndarray) -> np.ndarray:
        """Signed distance of points [N, 3] above the plane (towards the camera) -> [N]."""
        return np.asarray(points, np.float64) @ self.normal + self.plane[3]


def fit_table(points: np.ndarray, viewpoint=(0.0, 0.0, 0.0), distance: float = 0.005, iterations: int = 500,
              seed: int = 0, max_tilt_deg: float | None = None, up=None, sample: int = 4000) -> TablePlane:
    """RANSAC: the plane through three random points that has the most points within `distance` metres
    (at most `iterations` tries, seeded; fewer when the best plane so far is large), refined by least squares on those inliers (twice), its normal turned
    towards `viewpoint` (the camera's position in the points' frame; the origin in the camera frame).
    The largest plane in view is taken to be the table: crop the cloud to the workspace first when a
    wall or floor could outsize it. max_tilt_deg with up [3]: only planes whose normal lies within that
    angle of `up` (e.g. world z with extrinsics) count. The tries are scored on a seeded subsample of
    `sample` points (a VGA frame holds 300k), the least squares on the inliers among 20k of them, the
    returned inliers and rms use them all.
    points [N, 3], N >= 3 -> TablePlane."""
    pts = np.asarray(points, np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"points must be [N, 3], got shape {pts.shape}")
    if not np.isfinite(pts.sum()):  # a NaN or an inf makes the sum one (as would an overflow: then nothing goes)
        pts = pts[np.all(np.isfinite(pts), axis=1)]
    if len(pts) < 3:
        raise ValueError(f"a table plane needs at least 3 finite points, got {len(pts)}")
    if not distance > 0 or iterations < 1 or sample < 3:
        raise ValueError(f"distance must be > 0 metres, iterations >= 1 and sample >= 3, got {distance}, {iterations} "
                         f"and {sample}")
    view = np.asarray(viewpoint, np.float64)
    if up is not None:
        up = np.asarray(up, np.float64) / np.linalg.norm(up)
    min_cos = None if max_tilt_deg is None or up is None else np.cos(np.deg2rad(max_tilt_deg))
    rng = np.random.default_rng(seed)
    scored = pts if len(pts) <= sample else pts[rng.integers(0, len(pts), sample)]  # (with replacement: O(sample))
    triples = rng.integers(0, len(scored), size=(iterations, 3))
    a, b, c = scored[triples[:, 0]], scored[triples[:, 1]], scored[triples[:, 2]]
    normals = np.cross(b - a, c - a)
    norms = np.linalg.norm(normals, axis=1)
    ok = norms > 1e-12
    normals[ok] /= norms[ok, None]
    if min_cos is not None:
        ok &= np.abs(normals @ up) >= min_cos
    if not ok.any():
        raise ValueError("no plane found: the points are collinear, or no plane lies within max_tilt_deg of up")
    offsets = -np.sum(normals * a, axis=1)
    best, best_count = -1, -1
    # Candidates in chunks, so that memory stays bounded for large clouds; stop once the tries so far
    # would have drawn three inliers of the best plane with probability 0.9999 (adaptive RANSAC,
    # Hartley & Zisserman Sec. 4.7: a table filling most of the frame needs a few dozen tries).
    for start in range(0, iterations, 64):
        share = best_count / len(scored)
        if best_count > 0 and start >= np.log(1e-4) / np.log(max(1.0 - share ** 3, 1e-12)):
            break
        rows = np.flatnonzero(ok[start:start + 64]) + start
        if not len(rows):
            continue
        counts = np.sum(np.abs(scored @ normals[rows].T + offsets[rows]) <= distance, axis=0)
        i = int(np.argmax(counts))
        if counts[i] > best_count:
            best, best_count = int(rows[i]), int(counts[i])
    normal, offset = normals[best], offsets[best]
    refit = pts if len(pts) <= 20000 else pts[rng.integers(0, len(pts), 20000)]
    for _ in range(2):  # least squares on the inliers: the plane through their centroid, smallest spread
        inliers = np.abs(refit @ normal + offset) <= distance
        if inliers.sum() < 3:
            break
        # The smallest principal axis of the inliers, from their 3x3 second moments (two BLAS products:
        # an SVD of the [n, 3] inliers, or their mean over axis 0, costs several times as much).
        chosen = refit[inliers]
        centroid = np.ones(len(chosen)) @ chosen / len(chosen)
        _, axes = np.linalg.eigh(chosen.T @ chosen / len(chosen) - np.outer(centroid, centroid))
        normal = axes[:, 0] * (1.0 if axes[:, 0] @ normal >= 0 else -1.0)
        offset = -float(normal @ centroid)
    if normal @ view + offset < 0:  # free space (the camera's side) positive
        normal, offset = -normal, -offset
    full = np.asarray(points, np.float64)
    residual = full @ normal + offset
    inliers = np.abs(residual) <= distance  # (False where the residual is NaN)
    rms = float(np.sqrt(np.mean(residual[inliers] ** 2))) if inliers.any() else float("nan")
    return TablePlane((*map(float, normal), float(offset)), inliers, rms, residual)
