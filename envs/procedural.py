"""Procedurally generated graspable objects: extra shape variety beyond the YCB meshes.

Three kinds, cycled by index, every one seeded by (seed, index) so a set is reproducible object by object:
  * "superquadric": one superquadric (boxes, cylinders, ellipsoids and everything between); convex.
  * "blend": a smooth union of 2-3 superquadrics through a common point (L, T, X shapes, knobs);
    usually non-convex.
  * "extrusion": a prism over a random star-shaped profile (lobes, dents); usually non-convex.
Sizes are drawn, then shrunk where needed, so every object fits an 8 cm gripper across its smallest
extent and where it lies on a table (`envs.meshprep.rest_width` <= MAX_WIDTH) and is at most 20 cm long; meshes are watertight, in metres, centred near the origin (preparation moves the origin to
the centre of mass).
"""

from __future__ import annotations

import numpy as np
import trimesh

from envs.meshprep import rest_width
from sgjax.geometry.superquadric import Superquadric, to_mesh

KINDS = ("superquadric", "blend", "extrusion")
PROCEDURAL_VERSION = 2  # bump when generation changes, so cached meshes are regenerated

MAX_WIDTH = 0.054  # m, smallest extent and rest width: + 2 delta (Stage-1 width rule) fits the 8 cm opening
MAX_LENGTH = 0.20  # m, largest extent
_BLEND_SHARPNESS = 10.0  # p of the smooth union r = (sum r_i^p)^(1/p): larger = sharper creases


def _rot_z(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _rot_y(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def _superquadric(rng: np.random.Generator) -> trimesh.Trimesh:
    # Semi-axes: the smallest gives a 3-7 cm width, the longest at most 18 cm.
    a1 = rng.uniform(0.015, 0.035)
    scale = (a1, rng.uniform(a1, 0.045), rng.uniform(0.02, 0.09))
    eps = rng.uniform(0.2, 1.5, size=2)
    return to_mesh(Superquadric.create(scale, eps), resolution=10)


def _sq_log_inside(local: np.ndarray, scale: np.ndarray, eps: np.ndarray) -> np.ndarray:
    """log of the superquadric inside-outside function at local points (N, 3): < 0 inside."""
    q = np.abs(local) / scale + 1e-12
    xy = q[:, 0] ** (2 / eps[1]) + q[:, 1] ** (2 / eps[1])
    return np.log(xy ** (eps[1] / eps[0]) + q[:, 2] ** (2 / eps[0]))


def _ray_exit(directions: np.ndarray, scale, eps, rotation, centre, far: float = 0.5) -> np.ndarray:
    """Distance (N,) from the origin along unit `directions` (N, 3) to the surface of a convex
    superquadric that contains the origin (bisection: the ray leaves a convex body exactly once)."""
    lo, hi = np.zeros(len(directions)), np.full(len(directions), far)
    for _ in range(40):
        mid = (lo + hi) / 2
        inside = _sq_log_inside((directions * mid[:, None] - centre) @ rotation, scale, eps) < 0
        lo, hi = np.where(inside, mid, lo), np.where(inside, hi, mid)
    return (lo + hi) / 2


def _blend(rng: np.random.Generator) -> trimesh.Trimesh:
    # Star-shaped about the origin: each part is convex and contains it, so the union's surface is one
    # radius per direction; mapping a sphere mesh through it gives a watertight mesh with no booleans.
    # Parts lie roughly in the xy plane (long axis horizontal, small tilt), giving flat L/T/X/V shapes
    # that a gripper can take across their thickness.
    sphere = trimesh.creation.icosphere(subdivisions=4)
    directions = sphere.vertices
    radii = []
    for _ in range(rng.integers(2, 4)):
        scale = np.array([rng.uniform(0.012, 0.025), rng.uniform(0.012, 0.025), rng.uniform(0.03, 0.08)])
        eps = rng.uniform(0.1, 1.0, size=2)
        tilt = np.pi / 2 + rng.uniform(-0.25, 0.25)
        rotation = _rot_z(rng.uniform(0, 2 * np.pi)) @ _rot_y(tilt) @ _rot_z(rng.uniform(0, 2 * np.pi))
        # Shift the part along its long axis by up to 60 % of that semi-axis: the origin stays inside.
        centre = rotation @ np.array([0.0, 0.0, rng.uniform(-0.6, 0.6) * scale[2]])
        radii.append(_ray_exit(directions, scale, eps, rotation, centre))
    r = np.sum(np.stack(radii) ** _BLEND_SHARPNESS, axis=0) ** (1 / _BLEND_SHARPNESS)
    return trimesh.Trimesh(directions * r[:, None], sphere.faces, process=True)


def _extrusion(rng: np.random.Generator, sides: int = 64) -> trimesh.Trimesh:
    # A lobed profile r(theta) = 1 + sum_k a_k cos(k theta + phi_k): star-shaped, often with dents.
    theta = np.linspace(0, 2 * np.pi, sides, endpoint=False)
    k = np.arange(2, 6)
    amplitude = rng.uniform(0.0, 0.06, size=len(k))
    amplitude[rng.integers(len(k))] = rng.uniform(0.15, 0.35)  # one dominant lobe count: dents
    phase = rng.uniform(0, 2 * np.pi, size=len(k))
    r = 1 + np.sum(amplitude[:, None] * np.cos(k[:, None] * theta + phase[:, None]), axis=0)
    r = np.maximum(r, 0.3)  # keep the profile star-shaped with no pinch to a point
    profile = np.stack([r * np.cos(theta), r * np.sin(theta)], 1)
    profile *= rng.uniform(0.015, 0.035) / np.abs(profile[:, 1]).max()  # half-width across y: 1.5-3.5 cm
    profile[:, 0] *= rng.uniform(1.0, 2.5)  # elongate along x, up to ~18 cm
    return extrude_profile(profile, rng.uniform(0.03, 0.12))


def extrude_profile(profile: np.ndarray, height: float) -> trimesh.Trimesh:
    """Watertight prism over a closed 2D `profile` (N, 2) along z, centred at z = 0.

    The profile must be star-shaped about the origin (the caps are fans from it), in either winding.
    """
    profile = np.asarray(profile, np.float64)
    sides = len(profile)
    bottom, top = np.c_[profile, np.full(sides, -height / 2)], np.c_[profile, np.full(sides, height / 2)]
    vertices = np.concatenate([bottom, top, [[0, 0, -height / 2], [0, 0, height / 2]]])
    i, j = np.arange(sides), (np.arange(sides) + 1) % sides
    faces = np.concatenate(
        [
            np.stack([i, j, sides + j], 1),
            np.stack([i, sides + j, sides + i], 1),
            np.stack([np.full(sides, 2 * sides), j, i], 1),
            np.stack([np.full(sides, 2 * sides + 1), sides + i, sides + j], 1),
        ]
    )
    mesh = trimesh.Trimesh(vertices, faces, process=True)
    mesh.fix_normals()  # outward whatever the profile's winding
    return mesh


_GENERATORS = {"superquadric": _superquadric, "blend": _blend, "extrusion": _extrusion}


def procedural_name(index: int) -> str:
    """Name of object `index`: its kind and index, e.g. "blend_004"."""
    return f"{KINDS[index % len(KINDS)]}_{index:03d}"


def procedural_object(index: int, seed: int = 0) -> tuple[str, trimesh.Trimesh]:
    """Object `index` of the procedural family `seed`: (name such as "blend_004", watertight mesh)."""
    kind = KINDS[index % len(KINDS)]
    rng = np.random.default_rng([seed, index])
    mesh = _GENERATORS[kind](rng)
    # Guarantee the size rule whatever the draw: shrink (uniformly) until it fits, lying on the table too
    # (`rest_width` scales with the mesh).
    extents = np.sort(mesh.extents)
    shrink = min(1.0, MAX_WIDTH / extents[0], MAX_WIDTH / rest_width(mesh), MAX_LENGTH / extents[2])
    mesh.apply_scale(shrink)
    return procedural_name(index), mesh


def procedural_objects(count: int = 24, seed: int = 0) -> list[tuple[str, trimesh.Trimesh]]:
    """The first `count` objects of family `seed` (the first n of a larger set are the same objects)."""
    if count < 0:
        raise ValueError(f"count must be >= 0, got {count}")
    return [procedural_object(i, seed) for i in range(count)]
