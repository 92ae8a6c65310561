"""Mesh preparation for simulation: plain functions over trimesh meshes (no files, no cache).

The steps `envs.objects` chains for every object mesh:
  load_mesh -> clean_mesh -> check_size -> simplify_mesh (visual, fast-simplification) -> convex_pieces (collision)
  -> mass_properties (mass, centre of mass) -> the caller moves everything to the centre of mass.

Collision geometry is what MuJoCo and MJX collide well: convex meshes of at most 64 vertices. A mesh
that fills >= 90 % of its convex hull collides as that hull; anything else is decomposed with CoACD into
a few convex pieces (one geom each).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
from collections.abc import Sequence

import numpy as np
import trimesh

PREP_VERSION = 4  # bump when the preparation changes: cached assets are then rebuilt
MESH_EXTENSIONS = (".obj", ".stl", ".ply")


class MeshPrepError(ValueError):
    """A mesh that cannot be prepared (unreadable, empty, wrong units, failed decomposition)."""


@dataclasses.dataclass(frozen=True)
class PrepConfig:
    """Parameters of the preparation; all of them enter the cache key.

    visual_faces: the visual mesh is decimated (quadric) to at most this many faces.
    convex_ratio: volume / hull volume at or above which the convex hull is the collision geometry.
    max_hull_vertices: cap per convex piece (MJX collides hulls; keep them small).
    coacd_*: CoACD parameters, chosen for speed (a few seconds per YCB mesh on one core): concavity
        threshold 0.08, at most 8 pieces, a coarse manifold pre-pass and a short tree search.
    seed: CoACD's random seed (determinism).
    density: kg/m^3 over the solid volume. Household objects are partly hollow or light (packaging,
        plastic, foam) yet some are dense (cans, fruit): the YCB masses over their mesh volumes span
        ~200-1100 kg/m^3 with a median near 500 (cracker box 190, banana 385, sugar box 800, soup
        can 1090), so 500 gives realistic masses (a 6 x 6 x 10 cm box: 0.18 kg).
    mass_range: clamp (kg): tiny items are not feather-light (unstable contacts), big solid volumes
        stay within a small arm's payload.
    min_extent, max_extent: a mesh whose longest extent is outside this range is rejected as
        "not in metres" (e.g. millimetre files are 1000x too large).
    """

    visual_faces: int = 3000
    convex_ratio: float = 0.9
    max_hull_vertices: int = 64
    coacd_threshold: float = 0.08
    coacd_max_hulls: int = 8
    coacd_resolution: int = 1000
    coacd_preprocess_resolution: int = 30
    coacd_mcts_iterations: int = 60
    coacd_mcts_nodes: int = 10
    seed: int = 0
    density: float = 500.0
    mass_range: tuple[float, float] = (0.03, 1.0)
    min_extent: float = 0.005
    max_extent: float = 2.0


def prep_key(path: str | os.PathLike, config: PrepConfig) -> str:
    """Content hash of a mesh file + the preparation (config, PREP_VERSION): the cache key (hex)."""
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    digest.update(os.path.splitext(os.fspath(path))[1].lower().encode())  # the loader depends on it
    digest.update(json.dumps([PREP_VERSION, dataclasses.asdict(config)], sort_keys=True).encode())
    return digest.hexdigest()[:24]


def load_mesh(path: str | os.PathLike) -> trimesh.Trimesh:
    """Read a triangle mesh (.obj/.stl/.ply; scenes are concatenated); MeshPrepError if unusable."""
    path = os.fspath(path)
    if os.path.splitext(path)[1].lower() not in MESH_EXTENSIONS:
        raise MeshPrepError(f"{path}: unsupported mesh format (expected {', '.join(MESH_EXTENSIONS)})")
    try:
        mesh = trimesh.load(path, force="mesh", process=False)
    except Exception as exc:  # trimesh raises many types on bad files
        raise MeshPrepError(f"{path}: cannot read mesh ({type(exc).__name__}: {exc})") from exc
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise MeshPrepError(f"{path}: no triangles in file")
    if not np.all(np.isfinite(mesh.vertices)):
        raise MeshPrepError(f"{path}: vertices contain NaN or inf")
    return mesh


def clean_mesh(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """A copy with duplicate vertices merged, degenerate/duplicate faces dropped, small holes filled and
    faces wound consistently outward."""
    mesh = mesh.copy()
    mesh.merge_vertices()
    mesh.update_faces(mesh.nondegenerate_faces())
    mesh.update_faces(mesh.unique_faces())
    mesh.remove_unreferenced_vertices()
    if len(mesh.faces) == 0:
        raise MeshPrepError("mesh has no non-degenerate faces")
    if not mesh.is_watertight:
        trimesh.repair.fill_holes(mesh)
    mesh.fix_normals()
    return mesh


def check_size(mesh: trimesh.Trimesh, config: PrepConfig) -> None:
    """MeshPrepError unless the longest extent is within [min_extent, max_extent] metres."""
    longest = float(np.max(mesh.extents))
    if not config.min_extent <= longest <= config.max_extent:
        raise MeshPrepError(
            f"mesh is {longest:.4g} long; meshes must be in metres with a longest extent in "
            f"[{config.min_extent}, {config.max_extent}] m"
        )


def simplify_mesh(mesh: trimesh.Trimesh, max_faces: int) -> trimesh.Trimesh:
    """Quadric decimation towards at most `max_faces` faces (the decimator may stop a little above it
    where collapses would fold faces); meshes already small come back as is, and so does a closed mesh
    whose decimation would not be closed (thin parts pinched).

    Through trimesh's wrapper of `fast-simplification`, a PyPI wheel that carries its own binary, so
    the default path needs no system library (open3d's decimation needs libusb-1.0 on Linux).
    """
    if len(mesh.faces) <= max_faces:
        return mesh
    try:
        import fast_simplification  # noqa: F401  (imported by trimesh; checked here for a clear error)
    except ImportError as exc:  # an environment problem, not the mesh's: never recorded as its failure
        raise ImportError(
            f"decimating a {len(mesh.faces)}-face mesh needs fast-simplification "
            f"(a dependency of sgjax: reinstall with `pip install -e .`): {exc}"
        ) from exc
    target = max_faces
    for _ in range(4):  # the decimator may stop a few faces above its target: aim lower until it fits
        small = mesh.simplify_quadric_decimation(face_count=target)
        if len(small.faces) <= max_faces:
            break
        target = int(target * 0.95)
    out = trimesh.Trimesh(np.asarray(small.vertices), np.asarray(small.faces), process=True)
    out.update_faces(out.nondegenerate_faces())
    out.remove_unreferenced_vertices()
    out.fix_normals()
    if mesh.is_watertight and not out.is_watertight:
        # Edge collapses pinched a thin part (a knife's blade, a fork's tines: the two faces of a sheet
        # share edges afterwards). The camera then sees a different object than the one simulated, and
        # on 3 seen-10 scenes such meshes cost a third of the grasped objects, so keep the full mesh.
        return mesh
    return out


def cap_hull_vertices(hull: trimesh.Trimesh, max_vertices: int) -> trimesh.Trimesh:
    """A convex hull with at most `max_vertices` vertices, about the same volume as `hull`.

    Qhull stops after adding `max_vertices - 4` points (MuJoCo's own `maxhullvert` does the same); the
    smaller hull is then scaled about its centroid to the original volume, so collision surfaces err by
    about a millimetre both ways instead of always shrinking (a 64-vertex sphere keeps ~88 % volume).
    """
    if len(hull.vertices) <= max_vertices:
        return hull
    from scipy.spatial import ConvexHull

    points = np.asarray(hull.vertices)
    for added in range(max_vertices - 4, 0, -4):
        keep = ConvexHull(points, qhull_options=f"Qt TA{added}").vertices
        capped = trimesh.convex.convex_hull(points[keep])
        if len(capped.vertices) <= max_vertices:
            break
    centroid = capped.center_mass
    capped.apply_translation(-centroid)
    capped.apply_scale((hull.volume / capped.volume) ** (1 / 3))
    capped.apply_translation(centroid)
    return capped


def _convex_piece(vertices: np.ndarray, max_vertices: int) -> trimesh.Trimesh | None:
    """The capped convex hull of `vertices`, or None for a flat or degenerate piece."""
    from scipy.spatial import QhullError

    try:
        hull = trimesh.convex.convex_hull(np.asarray(vertices, np.float64))
    except (QhullError, ValueError, IndexError):  # coplanar or too few points
        return None
    if len(hull.vertices) < 4 or not hull.volume > 1e-10:
        return None
    return cap_hull_vertices(hull, max_vertices)


def convex_pieces(mesh: trimesh.Trimesh, config: PrepConfig) -> tuple[list[trimesh.Trimesh], str]:
    """Convex collision pieces of `mesh` in its frame, and the method ("convex_hull" | "coacd").

    The hull ratio needs a trustworthy volume, so only watertight meshes may take the hull shortcut;
    others go through CoACD, whose manifold pre-pass copes with holes.
    """
    if mesh.is_watertight and mesh.volume > 0:
        hull = mesh.convex_hull
        if mesh.volume / hull.volume >= config.convex_ratio:
            return [cap_hull_vertices(hull, config.max_hull_vertices)], "convex_hull"
    import coacd

    coacd.set_log_level("error")
    try:
        parts = coacd.run_coacd(
            coacd.Mesh(np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int32)),
            threshold=config.coacd_threshold,
            max_convex_hull=config.coacd_max_hulls,
            preprocess_mode="auto",
            preprocess_resolution=config.coacd_preprocess_resolution,
            resolution=config.coacd_resolution,
            mcts_nodes=config.coacd_mcts_nodes,
            mcts_iterations=config.coacd_mcts_iterations,
            decimate=True,
            max_ch_vertex=config.max_hull_vertices,
            seed=config.seed,
        )
    except Exception as exc:
        raise MeshPrepError(f"convex decomposition failed ({type(exc).__name__}: {exc})") from exc
    pieces = [p for p in (_convex_piece(v, config.max_hull_vertices) for v, _ in parts) if p is not None]
    if not pieces:
        raise MeshPrepError("convex decomposition returned no solid piece")
    return pieces, "coacd"


def mass_properties(
    solids: Sequence[trimesh.Trimesh], pieces: list[trimesh.Trimesh], config: PrepConfig
) -> tuple[float, float, np.ndarray]:
    """(mass kg, volume m^3, centre of mass (3,)) of the object.

    From the first watertight mesh among `solids` (e.g. the full-resolution mesh, then its decimated
    copy, which often closes a scan's pinholes); when none is, the convex pieces stand in for the solid
    (volume-weighted centroids; they over-fill thin objects). Mass = density * volume, clamped.
    """
    solid = next((m for m in solids if m.is_watertight and m.volume > 0), None)
    if solid is not None:
        volume, com = float(solid.volume), np.asarray(solid.center_mass)
    else:
        volumes = np.array([p.volume for p in pieces])
        volume = float(volumes.sum())
        com = (volumes[:, None] * np.array([p.center_mass for p in pieces])).sum(0) / volume
    mass = float(np.clip(config.density * volume, *config.mass_range))
    return mass, volume, com


def rest_width(mesh: trimesh.Trimesh, probability: float = 0.5, directions: int = 90) -> float:
    """How wide an object lies on a table, for a gripper closing horizontally (m).

    For each stable resting pose of the convex hull (`trimesh.poses.compute_stable_poses`), the hull's
    narrowest horizontal width; returns the smallest width w such that the poses no wider than w have
    at least `probability` of the resting probability. An object whose smallest extent stands vertical
    when it rests (a tuna can, a box on its largest face) is wide here, however thin it is.
    """
    hull = mesh.convex_hull
    transforms, probs = trimesh.poses.compute_stable_poses(hull, n_samples=1, threshold=0.0)
    if len(transforms) == 0:  # degenerate hull: fall back to the bounding box
        return float(np.sort(mesh.extents)[1])
    angles = np.linspace(0.0, np.pi, directions, endpoint=False)
    axes = np.stack([np.cos(angles), np.sin(angles)], 1)  # [D, 2] horizontal closing directions
    widths = []
    for transform in transforms:
        along = trimesh.transform_points(hull.vertices, transform)[:, :2] @ axes.T  # [V, D]
        widths.append(float((along.max(0) - along.min(0)).min()))
    widths, probs = np.asarray(widths), np.asarray(probs, np.float64) / np.sum(probs)
    order = np.argsort(widths, kind="stable")
    covered = np.cumsum(probs[order])
    return float(widths[order][min(np.searchsorted(covered, probability - 1e-9), len(order) - 1)])
