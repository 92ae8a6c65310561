"""Point-cloud input: loading, checking, downsampling and padding into fixed-shape batches.

Every check that decides whether a cloud can be fitted lives in `cloud_status`, written once over an
array module so that the host (NumPy, clear exceptions) and the device (JAX, per-cloud status inside a
batch) agree exactly.
"""

from __future__ import annotations

import os
from typing import Sequence

import numpy as np

# Status codes shared by the host checks and the batched fit.
OK = 0
TOO_FEW_POINTS = 1
NON_FINITE = 2
IDENTICAL_POINTS = 3
COLLINEAR = 4
COPLANAR = 5
FIT_FAILED = 6

MIN_POINTS = 11  # fewer than the 11 unknowns of a posed superquadric cannot determine it

STATUS_MESSAGES = {
    OK: "ok",
    TOO_FEW_POINTS: f"too few points (a superquadric needs at least {MIN_POINTS})",
    NON_FINITE: "the cloud contains NaN or inf coordinates",
    IDENTICAL_POINTS: "all points are identical",
    COLLINEAR: "the points are collinear",
    COPLANAR: "the points are coplanar (no extent along one direction)",
    FIT_FAILED: "the fit did not converge to finite parameters",
}

# Degeneracy thresholds: spread below 1 micrometre is one point; a principal variance ratio below
# 1e-6 (thickness below 1e-3 of the length; float32 eigenvalues resolve ~1e-7) is a line or a plane,
# far below any real sensor's noise.
_IDENTICAL_STD = 1e-6
_FLAT_RATIO = 1e-6


class CloudError(ValueError):
    """A point cloud that cannot be used, with a message naming the problem."""


def describe_status(code: int) -> str:
    """Human-readable meaning of a status code."""
    return STATUS_MESSAGES.get(int(code), f"unknown status {int(code)}")


def cloud_status(points, mask, xp=np):
    """Status code of one cloud: points[N, 3], mask[N] bool -> int (scalar array under JAX).

    `xp` is `numpy` or `jax.numpy`; the logic is the same for both.
    """
    finite = xp.all(xp.isfinite(points), axis=-1)
    any_bad = xp.any(mask & ~finite)
    use = mask & finite
    n = xp.sum(use)
    w = use.astype(points.dtype)
    safe = xp.where(use[:, None], points, 0.0)
    centroid = xp.sum(safe * w[:, None], axis=0) / xp.maximum(n, 1)
    centred = (safe - centroid) * w[:, None]
    cov = centred.T @ centred / xp.maximum(n, 1)
    lam = xp.linalg.eigvalsh(cov)  # ascending
    lam_max = xp.maximum(lam[2], 1e-30)
    code = xp.where(lam[0] / lam_max < _FLAT_RATIO, COPLANAR, OK)
    code = xp.where(lam[1] / lam_max < _FLAT_RATIO, COLLINEAR, code)
    code = xp.where(lam[2] < _IDENTICAL_STD**2, IDENTICAL_POINTS, code)
    code = xp.where(n < MIN_POINTS, TOO_FEW_POINTS, code)
    code = xp.where(any_bad, NON_FINITE, code)
    return code


def as_cloud(points, name: str = "cloud") -> np.ndarray:
    """Validate an array-like as one cloud: -> float64 [N, 3]; raises CloudError naming the problem."""
    arr = as_points(points, name)
    if arr.shape[0] == 0:
        raise CloudError(f"{name}: the cloud is empty")
    code = int(cloud_status(arr, np.ones(len(arr), bool)))
    if code != OK:
        raise CloudError(f"{name}: {describe_status(code)} ({len(arr)} points)")
    return arr


def as_points(points, name: str = "points") -> np.ndarray:
    """Validate an array-like as a set of points: -> float64 [N, 3] (N may be 0); raises CloudError for a
    non-numeric array, a wrong shape or NaN/inf. No shape test (a flat table is a fine obstacle cloud)."""
    try:
        arr = np.asarray(points, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise CloudError(f"{name}: not a numeric array ({exc})") from None
    if arr.ndim != 2 or arr.shape[-1] != 3:
        raise CloudError(f"{name}: expected an array of shape (N, 3), got {arr.shape}")
    bad = ~np.all(np.isfinite(arr), axis=1)
    if bad.any():
        raise CloudError(f"{name}: {int(bad.sum())} of {len(arr)} points hold NaN or inf coordinates")
    return arr


def load_cloud(path: str | os.PathLike) -> np.ndarray:
    """Read a cloud from .npy (N x 3, metres), .ply or .pcd -> float64 [N, 3]; raises CloudError."""
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise CloudError(f"{path}: no such file")
    ext = os.path.splitext(path)[1].lower()
    try:
        if ext == ".npy":
            arr = np.load(path, allow_pickle=False)
        elif ext == ".ply":
            import trimesh

            geom = trimesh.load(path, process=False)
            if not hasattr(geom, "vertices"):
                raise CloudError(f"{path}: the PLY file holds no vertices")
            arr = np.asarray(geom.vertices)
        elif ext == ".pcd":
            arr = _read_pcd(path)
        else:
            raise CloudError(f"{path}: unsupported extension {ext!r} (use .npy, .ply or .pcd)")
    except CloudError:
        raise
    except Exception as exc:  # any parser failure is an unreadable file, not a crash
        raise CloudError(f"{path}: cannot read the file ({type(exc).__name__}: {exc})") from None
    return as_cloud(arr, name=path)


def _read_pcd(path: str) -> np.ndarray:
    with open(path, "rb") as fh:
        if not fh.read(256).lstrip().startswith((b"#", b"VERSION", b"FIELDS")):
            raise CloudError(f"{path}: not a PCD file (bad header)")
    try:
        import open3d as o3d
    except ImportError as exc:  # e.g. a missing system library such as libusb-1.0
        raise CloudError(
            f"{path}: reading .pcd needs open3d, which failed to import ({exc}); on Linux open3d needs the "
            "system library libusb-1.0 (apt-get install libusb-1.0-0). .npy and .ply clouds need neither."
        ) from None
    cloud = o3d.io.read_point_cloud(path, format="pcd")
    return np.asarray(cloud.points)


def downsample(points: np.ndarray, max_points: int, seed: int = 0) -> np.ndarray:
    """At most `max_points` points chosen uniformly at random without replacement (deterministic in seed).

    [N, 3] -> [min(N, max_points), 3]. Random subsets keep the density of a single-view cloud, which
    the EMS likelihood assumes; a 10^6-point cloud costs one O(N) pass.
    """
    if len(points) <= max_points:
        return points
    idx = np.random.default_rng(seed).choice(len(points), size=max_points, replace=False)
    return points[np.sort(idx)]


def padded_size(n: int, multiple: int = 128) -> int:
    """Round a point count up so that nearby sizes share one compiled fit."""
    return max(multiple, -(-n // multiple) * multiple)


def pad_clouds(
    clouds: Sequence[np.ndarray], max_points: int = 1024, seed: int = 0, n_points: int | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Downsample each cloud to <= max_points and pad into one batch.

    Returns points[B, N, 3] float32 and mask[B, N] bool, where N is `n_points` or the largest cloud
    rounded up by `padded_size`. Cloud i is downsampled with seed `seed + i`.
    """
    if len(clouds) == 0:
        raise CloudError("no clouds given")
    sampled = [downsample(np.asarray(c, np.float64), max_points, seed + i) for i, c in enumerate(clouds)]
    size = n_points or padded_size(max(len(c) for c in sampled))
    points = np.zeros((len(sampled), size, 3), np.float32)
    mask = np.zeros((len(sampled), size), bool)
    for i, c in enumerate(sampled):
        if len(c) > size:
            raise CloudError(f"cloud {i} has {len(c)} points, more than the padded size {size}")
        points[i, : len(c)] = c
        mask[i, : len(c)] = True
    return points, mask


def voxel_downsample(
    points: np.ndarray, voxel: float, labels: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray | None]:
    """One point per occupied voxel of side `voxel` (the point nearest the voxel centre), in voxel order.

    points [N, 3], labels [N] or None -> (points [V, 3], labels [V] or None). Keeping a real point (not a
    centroid) leaves it on the surface and keeps its label; the result's density no longer depends on
    the camera's distance, so crops seen in training and at run time look alike. Deterministic.
    """
    points = np.asarray(points)
    if voxel <= 0:
        raise ValueError(f"voxel must be positive, got {voxel}")
    if len(points) == 0:
        return points.reshape(0, 3), None if labels is None else np.asarray(labels)[:0]
    scaled = points / voxel
    cell = np.floor(scaled).astype(np.int64)
    offset = np.linalg.norm(scaled - cell - 0.5, axis=1)
    cell -= cell.min(0)
    span = cell.max(0) + 1
    if np.prod(span.astype(np.float64)) < 2.0**62:
        # One int64 key in the voxels' (x, y, z) order. A stable sort on it alone is ~10x faster than a
        # lexsort with the offset (a camera's cloud is nearly in key order already); the nearest point
        # of each voxel (the first of equals) is then picked per run.
        key = (cell[:, 0] * span[1] + cell[:, 1]) * span[2] + cell[:, 2]
        order = np.argsort(key, kind="stable")
        sorted_key, sorted_offset = key[order], offset[order]
        start = np.ones(len(order), bool)
        start[1:] = sorted_key[1:] != sorted_key[:-1]
        starts = np.flatnonzero(start)
        nearest = np.minimum.reduceat(sorted_offset, starts)
        group = np.cumsum(start) - 1
        at_min = np.flatnonzero(sorted_offset == nearest[group])
        first = np.ones(len(at_min), bool)
        first[1:] = group[at_min[1:]] != group[at_min[:-1]]
        keep = order[at_min[first]]
    else:  # a cloud too wide for one key
        order = np.lexsort((offset, cell[:, 2], cell[:, 1], cell[:, 0]))  # by voxel, nearest-to-centre first
        sorted_cells = cell[order]
        first = np.ones(len(order), bool)
        first[1:] = np.any(sorted_cells[1:] != sorted_cells[:-1], axis=1)
        keep = order[first]
    return points[keep], None if labels is None else np.asarray(labels)[keep]


def scene_cloud(
    points: np.ndarray,
    max_points: int,
    voxel: float = 0.003,
    labels: np.ndarray | None = None,
    bounds: tuple[np.ndarray, np.ndarray] | None = None,
    seed: int = 0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """The fixed-size scene cloud Stage 2 sees, the same in labelling and planning.

    points [N, 3] (non-finite rows dropped), optional labels [N] and axis-aligned bounds (lo [3],
    hi [3]) -> (points [max_points, 3] float32, mask [max_points] bool, labels [max_points] int32 or
    None; padding label -1). Voxel-downsampled (voxel 0: not), then at most max_points drawn uniformly
    (seeded).
    """
    points = np.asarray(points, np.float64)
    if points.ndim != 2 or points.shape[-1] != 3:
        raise CloudError(f"scene cloud must have shape [N, 3], got {points.shape}")
    if labels is not None and np.shape(labels) != points.shape[:1]:
        raise ValueError(f"labels must have shape {points.shape[:1]}, got {np.shape(labels)}")
    keep = np.all(np.isfinite(points), axis=1)
    if bounds is not None:
        lo, hi = (np.asarray(b, np.float64) for b in bounds)
        keep &= np.all((points >= lo) & (points <= hi), axis=1)
    kept_labels = None if labels is None else np.asarray(labels)[keep]
    points = points[keep]
    if voxel > 0:  # 0: no voxel grid
        points, kept_labels = voxel_downsample(points, voxel, kept_labels)
    if len(points) > max_points:
        idx = np.sort(np.random.default_rng(seed).choice(len(points), size=max_points, replace=False))
        points = points[idx]
        kept_labels = None if kept_labels is None else kept_labels[idx]
    out = np.zeros((max_points, 3), np.float32)
    out[: len(points)] = points
    mask = np.arange(max_points) < len(points)
    if kept_labels is None:
        return out, mask, None
    out_labels = np.full(max_points, -1, np.int32)
    out_labels[: len(points)] = kept_labels
    return out, mask, out_labels


def table_plane(points: np.ndarray, labels: np.ndarray, up=(0.0, 0.0, 1.0)) -> tuple[float, float, float, float] | None:
    """The table as a plane (a, b, c, d) (free space a x + b y + c z + d > 0, `PlannerConfig.support_plane`'s
    convention) of normal n = up / |up| through the table points' (labels < 0) median height h along n:
    (n, -h); None without table points. up [3]: the frame's up direction, world z by default (the
    simulator's frames; then the plane is (0, 0, 1, -z) with z the median of the table points' z, computed
    as before `up` existed); in the camera frame of a depth image, the table's normal towards the camera.
    ValueError for an up that is zero, not finite or not 3 numbers."""
    n = np.asarray(up, np.float64)
    length = float(np.linalg.norm(n)) if n.shape == (3,) else float("nan")
    if not (np.isfinite(length) and length > 0):
        raise ValueError(f"table_plane: up must be a finite non-zero 3-vector, got {up!r}")
    table = np.asarray(labels) < 0
    if not table.any():
        return None
    n = n / length
    if n[0] == 0.0 and n[1] == 0.0 and n[2] == 1.0:  # z up: the height is z itself (bit for bit as always)
        z = float(np.median(np.asarray(points)[table, 2]))
        return (0.0, 0.0, 1.0, -z)
    h = float(np.median(np.asarray(points, np.float64)[table] @ n))
    return (float(n[0]), float(n[1]), float(n[2]), -h)


def same_cloud(a: np.ndarray, b: np.ndarray, tolerance: float) -> bool:
    """Whether clouds a [N, 3] and b [M, 3] show the same surface within `tolerance` (metres): point
    counts within 5 % of each other, centroids within tolerance, and 95 % of each cloud's points within
    tolerance of the other's (so a new view of a still object passes and a nudged one, or one partly
    hidden or revealed, does not). tolerance <= 0: only equal arrays pass."""
    from scipy.spatial import cKDTree

    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    if a.shape == b.shape and np.array_equal(a, b):
        return True
    if tolerance <= 0.0:
        return False
    if not len(a) or not len(b) or abs(len(a) - len(b)) > 0.05 * max(len(a), len(b)):
        return False
    if np.linalg.norm(a.mean(0) - b.mean(0)) > tolerance:
        return False
    for x, y in ((a, b), (b, a)):
        near = cKDTree(y).query(x, distance_upper_bound=tolerance)[0] <= tolerance
        if near.mean() < 0.95:
            return False
    return True
