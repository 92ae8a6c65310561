"""Host-side cloud helpers against brute-force references."""

from __future__ import annotations

import numpy as np
import pytest

from sgjax.geometry import pointcloud


def _voxel_reference(points: np.ndarray, voxel: float) -> np.ndarray:
    """Per occupied voxel, in (x, y, z) voxel order: the point nearest its centre (the first of equals)."""
    best: dict[tuple, tuple[float, int]] = {}
    for i, p in enumerate(points):
        cell = tuple(np.floor(p / voxel).astype(int))
        d = float(np.linalg.norm(p / voxel - np.floor(p / voxel) - 0.5))
        if cell not in best or d < best[cell][0]:
            best[cell] = (d, i)
    return np.array([best[c][1] for c in sorted(best)])


@pytest.mark.parametrize("voxel", [0.002, 0.01])
def test_voxel_downsample_keeps_the_point_nearest_each_voxel_centre(voxel):
    rng = np.random.default_rng(0)
    points = rng.uniform(-0.05, 0.05, (3000, 3))
    points[:50] = points[50:100]  # exact duplicates: the first one is kept
    labels = np.arange(len(points))
    got, got_labels = pointcloud.voxel_downsample(points, voxel, labels)
    expected = _voxel_reference(points, voxel)
    np.testing.assert_array_equal(got_labels, expected)
    np.testing.assert_array_equal(got, points[expected])
    # A far-away point makes the grid too wide for one packed key: the other path agrees.
    wide = np.concatenate([points, [[1e15, 0.0, 0.0]]])
    np.testing.assert_array_equal(pointcloud.voxel_downsample(wide, voxel)[0][:-1], points[expected])
    with pytest.raises(ValueError, match="voxel"):
        pointcloud.voxel_downsample(points, 0.0)
