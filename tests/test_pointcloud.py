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


def test_same_cloud_passes_a_still_object_and_fails_a_moved_or_uncovered_one():
    rng = np.random.default_rng(0)
    cloud = rng.uniform(-0.03, 0.03, (1500, 3))
    again = cloud + rng.normal(0, 0.0003, cloud.shape)  # a new view of a still object: sensor noise
    assert pointcloud.same_cloud(cloud, cloud.copy(), 0.0)
    assert pointcloud.same_cloud(cloud, again, 0.002) and not pointcloud.same_cloud(cloud, again, 0.0)
    assert not pointcloud.same_cloud(cloud, cloud + [0.004, 0, 0], 0.002)  # nudged 4 mm
    assert pointcloud.same_cloud(cloud, cloud + [0.001, 0, 0], 0.002)
    assert not pointcloud.same_cloud(cloud, cloud[:1300], 0.002)  # partly hidden now (13 % fewer points)
    # As many points, the same centroid, but 200 of them somewhere else (a part hidden, another revealed).
    other = np.r_[cloud[:1300], cloud[:100] + [0.05, 0, 0], cloud[:100] - [0.05, 0, 0]]
    assert np.linalg.norm(other.mean(0) - cloud.mean(0)) < 0.002 and not pointcloud.same_cloud(cloud, other, 0.002)
    assert not pointcloud.same_cloud(cloud, np.zeros((0, 3)), 0.002)
