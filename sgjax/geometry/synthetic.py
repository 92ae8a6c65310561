"""Synthetic superquadrics and their single-view clouds (for examples, tests and benchmarks).

A superquadric with eps in (0, 2] is convex, so a surface point is seen by a camera exactly when its
outward normal faces the camera: back-face culling is an exact visibility test here.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from sgjax.geometry.superquadric import Superquadric, sample_surface


def random_superquadric(
    rng: np.random.Generator,
    scale_range: tuple[float, float] = (0.015, 0.1),
    eps_range: tuple[float, float] = (0.1, 2.0),
    max_aspect: float = 4.0,
) -> Superquadric:
    """A randomly shaped and posed superquadric of graspable size (semi-axes in `scale_range`, metres).

    Aspect ratios between semi-axes are limited to `max_aspect`.
    """
    while True:
        scale = rng.uniform(*scale_range, size=3)
        if scale.max() / scale.min() <= max_aspect:
            break
    eps = rng.uniform(*eps_range, size=2)
    rot = Rotation.random(random_state=rng).as_matrix()
    trans = rng.uniform(-0.2, 0.2, size=3)
    return Superquadric.create(scale, eps, rot, trans)


def view_direction(rng: np.random.Generator, elevation_deg: tuple[float, float] = (20.0, 70.0)) -> np.ndarray:
    """A unit vector from the object towards a camera above the table (z up): -> [3]."""
    az = rng.uniform(0.0, 2 * np.pi)
    el = np.deg2rad(rng.uniform(*elevation_deg))
    return np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])


def single_view_cloud(
    sq: Superquadric,
    n_points: int = 800,
    view: np.ndarray | None = None,
    noise_std: float = 0.001,
    outlier_ratio: float = 0.0,
    seed: int | np.random.Generator = 0,
    camera_distance: float = 0.6,
) -> np.ndarray:
    """What one depth camera sees of a superquadric: -> points[n_points, 3] (metres, world frame).

    `view` points from the object towards the camera (default: a random direction above the object).
    The visible surface is sampled uniformly in area, perturbed by isotropic Gaussian noise of
    `noise_std`, and a fraction `outlier_ratio` of the points are replaced by outliers uniform in the
    visible points' bounding box enlarged by 25 % on each side.
    """
    rng = np.random.default_rng(seed)
    view = view_direction(rng) if view is None else np.asarray(view, np.float64) / np.linalg.norm(view)
    camera = np.asarray(sq.translation, np.float64) + camera_distance * view
    n_in = int(round(n_points * (1.0 - outlier_ratio)))
    visible = np.zeros((0, 3))
    while len(visible) < n_in:  # about half the surface faces the camera
        pts, normals = sample_surface(sq, 3 * n_points, seed=rng)
        visible = np.concatenate([visible, pts[np.sum(normals * (camera - pts), -1) > 0]])
    visible = visible[:n_in] + rng.normal(0.0, noise_std, size=(n_in, 3))
    lo, hi = visible.min(0), visible.max(0)
    pad = 0.25 * (hi - lo)
    outliers = rng.uniform(lo - pad, hi + pad, size=(n_points - n_in, 3))
    cloud = np.concatenate([visible, outliers])
    return cloud[rng.permutation(len(cloud))]


def full_cloud(sq: Superquadric, n_points: int = 800, noise_std: float = 0.001, seed: int = 0) -> np.ndarray:
    """The whole surface, uniform in area, with Gaussian noise: -> points[n_points, 3]."""
    rng = np.random.default_rng(seed)
    pts, _ = sample_surface(sq, n_points, seed=rng)
    return pts + rng.normal(0.0, noise_std, size=pts.shape)
