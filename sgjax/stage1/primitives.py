"""Standard primitives and their template grasps (paper Sec. IV-B, "Primitive database").

Four families, each described by `dims` (metres) in a frame centred at its bounding-box centre with
z up:
  * cuboid:              (x, y, z) full edge lengths;
  * cylinder:            (2r, 2r, h);
  * elliptical_cylinder: (2r_x, 2r_y, h);
  * frustum:             (2r_bottom, 2r_top, h)  (bottom at z = -h/2).

Template grasps are gripper poses (gripper frame of `sgjax.geometry.gripper`) placed by family-specific rules
that cover the main feasible grasp directions: across opposite faces of a cuboid from each face, across
the diameter from the side at several heights and angles, across the height from the side, and across
the diameter from the top or bottom. Each template's width is found as in the paper: close the gripper
from open until the smallest distance between either inner finger face and the surface reaches
delta (`GripperSpec.contact_threshold`); a template whose width would exceed the maximum opening, whose
fingers close on nothing, or whose palm touches the surface is dropped. Everything here is host-side
NumPy: it runs once, when the database is built.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from sgjax.geometry.gripper import GripperSpec, finger_stops

FAMILIES = ("cuboid", "cylinder", "frustum", "elliptical_cylinder")
_SECTIONS = 64  # polygon sides of round primitives: < 0.2 mm from the true circle at r = 0.1 m


@dataclasses.dataclass(frozen=True)
class Primitive:
    """One database shape: `family` in FAMILIES and its `dims` (see the module docstring)."""

    family: str
    dims: tuple[float, float, float]

    def __post_init__(self):
        if self.family not in FAMILIES:
            raise ValueError(f"unknown primitive family {self.family!r}; expected one of {FAMILIES}")
        object.__setattr__(self, "dims", tuple(float(d) for d in self.dims))
        if len(self.dims) != 3 or not all(d > 0 for d in self.dims):
            raise ValueError(f"primitive dims must be 3 positive lengths, got {self.dims}")

    @property
    def extents(self) -> np.ndarray:
        """Bounding-box edge lengths [3]."""
        a, b, h = self.dims
        if self.family == "frustum":
            return np.array([max(a, b), max(a, b), h])
        return np.array([a, b, h])


@dataclasses.dataclass(frozen=True)
class TemplateConfig:
    """How densely templates are placed (metres, counts)."""

    lateral_step: float = 0.015  # spacing of grasp positions along the fingers' width axis
    max_positions: int = 8  # at most this many positions per grasp line (spacing grows beyond)
    depth_fractions: tuple[float, ...] = (0.3, 0.6, 0.9)  # fingertip insertion, fraction of min(L, object depth)
    palm_clearance: float = 0.002  # gap kept between the palm-side face and the surface
    side_angles: int = 12  # radial approach directions around round primitives
    top_angles: int = 6  # closing directions of top/bottom grasps on round primitives (over 180 deg)
    top_offset_fraction: float = 0.3  # top/bottom grasps: chord offsets up to this fraction of the radius
    max_templates: int = 400
    surface_samples: int = 6000


def primitive_mesh(p: Primitive) -> trimesh.Trimesh:
    """Watertight mesh of a primitive in its own frame (bounding-box centre at the origin, z up)."""
    import trimesh  # here: only building a database makes meshes, and a planning process need not import it

    a, b, h = p.dims
    if p.family == "cuboid":
        return trimesh.creation.box(extents=(a, b, h))
    mesh = trimesh.creation.cylinder(radius=0.5, height=h, sections=_SECTIONS)
    v = mesh.vertices.copy()
    if p.family in ("cylinder", "elliptical_cylinder"):
        v[:, 0] *= a
        v[:, 1] *= b
    else:  # frustum: radius interpolates linearly from the bottom (z = -h/2) to the top
        t = (v[:, 2] + 0.5 * h) / h
        diameter = a + (b - a) * t
        v[:, :2] *= diameter[:, None]
    return trimesh.Trimesh(v, mesh.faces, process=True)


def surface_points(p: Primitive, count: int, seed: int = 0) -> np.ndarray:
    """Points uniform in area on the primitive's surface: -> [count, 3] (deterministic in seed)."""
    import trimesh

    points, _ = trimesh.sample.sample_surface(primitive_mesh(p), count, seed=seed)
    return np.asarray(points, np.float64)


def grasp_frame(approach: np.ndarray, closing: np.ndarray, origin: np.ndarray) -> np.ndarray:
    """Gripper poses from unit approach (z) and closing (x) axes and origins: [..., 3] x3 -> [..., 4, 4]."""
    z = approach / np.linalg.norm(approach, axis=-1, keepdims=True)
    x = closing - np.sum(closing * z, -1, keepdims=True) * z
    x = x / np.linalg.norm(x, axis=-1, keepdims=True)
    y = np.cross(z, x)
    pose = np.zeros(np.broadcast_shapes(z.shape, origin.shape)[:-1] + (4, 4))
    pose[..., :3, 0], pose[..., :3, 1], pose[..., :3, 2], pose[..., :3, 3] = x, y, z, origin
    pose[..., 3, 3] = 1.0
    return pose


# Seen from each template's frame, `_footprint` returns which points lie in the slab the fingers sweep.
def _local(points: np.ndarray, poses: np.ndarray) -> np.ndarray:
    """World points [S, 3] in each gripper frame: poses [T, 4, 4] -> [T, S, 3]."""
    rotation = poses[:, :3, :3]
    return points @ rotation - (poses[:, None, :3, 3] @ rotation)  # batched matmul: einsum is 20x slower


def closing_widths(points: np.ndarray, poses: np.ndarray, spec: GripperSpec) -> np.ndarray:
    """The paper's width rule for each pose: close until an inner finger face is delta from the surface.

    points: [S, 3] dense surface samples; poses: [T, 4, 4] gripper poses (centred on the object along
    x). Both fingers close symmetrically from fully open; a face sweeping along x stops when its
    Euclidean distance to some surface point reaches delta. Returns widths [T]; NaN where no surface
    comes within delta of a finger (a grasp of air) or where the stop lies beyond the maximum opening.
    """
    width = 2.0 * np.maximum(*finger_stops(_local(points, poses), spec, xp=np))
    ok = np.isfinite(width) & (width <= spec.max_opening) & (width > 0)
    return np.where(ok, width, np.nan)


def palm_hits(points: np.ndarray, poses: np.ndarray, spec: GripperSpec, margin: float = 0.0) -> np.ndarray:
    """Whether any surface point lies in the palm box of each pose: points [S, 3], poses [T, 4, 4] -> [T]."""
    local = _local(points, poses)
    px, py, pz = spec.palm_size
    inside = (
        (np.abs(local[..., 0]) <= 0.5 * px + margin)
        & (np.abs(local[..., 1]) <= 0.5 * py + margin)
        & (local[..., 2] <= margin)
        & (local[..., 2] >= -pz - margin)
    )
    return inside.any(-1)


def _centred_offsets(extent: float, spec: GripperSpec, cfg: TemplateConfig) -> np.ndarray:
    """Positions along the fingers' width axis covering `extent` with the finger inside it."""
    usable = max(extent - spec.finger_width, 0.0)
    n = min(int(np.floor(usable / cfg.lateral_step)) + 1, cfg.max_positions)
    return np.linspace(-0.5, 0.5, n) * min(usable, (n - 1) * cfg.lateral_step) if n > 1 else np.zeros(1)


def _directions(p: Primitive, spec: GripperSpec, cfg: TemplateConfig) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Family templates as (approach [3], closing [3], lateral offsets along y [k]) triples.

    Each triple is a grasp line through the primitive's centre; offsets shift it along the gripper y.
    """
    ext = p.extents
    eye = np.eye(3)
    lines = []
    if p.family == "cuboid":
        for a in range(3):
            for sign in (1.0, -1.0):
                for c in range(3):
                    if c == a:
                        continue
                    b = 3 - a - c
                    offsets = _centred_offsets(ext[b], spec, cfg)
                    lines.append((-sign * eye[a], eye[c], offsets))
        return lines
    # Round families: from the side at several heights, across the height, and from top/bottom.
    for k in range(cfg.side_angles):
        phi = 2 * np.pi * k / cfg.side_angles
        radial = np.array([np.cos(phi), np.sin(phi), 0.0])
        tangent = np.array([-np.sin(phi), np.cos(phi), 0.0])
        lines.append((-radial, tangent, _centred_offsets(ext[2], spec, cfg)))
        lines.append((-radial, eye[2], np.zeros(1)))
    for sign in (1.0, -1.0):
        for k in range(cfg.top_angles):
            psi = np.pi * k / cfg.top_angles
            closing = np.array([np.cos(psi), np.sin(psi), 0.0])
            chord = cfg.top_offset_fraction * 0.5 * min(ext[0], ext[1])
            offsets = np.unique(np.round(np.array([-chord, 0.0, chord]), 6))
            lines.append((-sign * eye[2], closing, offsets))
    return lines


def _place(points: np.ndarray, lines: np.ndarray, spec: GripperSpec, cfg: TemplateConfig) -> np.ndarray:
    """Poses along grasp lines: depth variants, centred on the surface between the fingers.

    lines: [K, 4, 4] gripper frames whose z axis is a grasp line (origin anywhere on it) ->
    poses [K', 4, 4] (lines that meet no surface between the fingers are dropped).
    """
    local = _local(points, lines)
    reach = 0.5 * max(spec.max_opening + 2 * spec.finger_thickness, spec.palm_size[0])
    half_y = 0.5 * max(spec.finger_width, spec.palm_size[1])
    x, y, z = local[..., 0], local[..., 1], local[..., 2]
    under = (np.abs(x) <= reach) & (np.abs(y) <= half_y)
    fingers = (np.abs(x) <= 0.5 * spec.max_opening) & (np.abs(y) <= 0.5 * spec.finger_width)
    hit = fingers.any(-1)
    near = np.where(under, z, np.inf).min(-1)  # the first surface the palm would meet
    depth = np.where(fingers, z, -np.inf).max(-1) - near
    x_mid = 0.5 * (np.where(fingers, x, np.inf).min(-1) + np.where(fingers, x, -np.inf).max(-1))
    lines, near, depth, x_mid = lines[hit], near[hit], depth[hit], x_mid[hit]
    poses = []
    for frac in cfg.depth_fractions:
        insertion = frac * np.minimum(spec.finger_length - cfg.palm_clearance, depth)
        origin_z = near + insertion - spec.finger_length
        q = lines.copy()
        q[:, :3, 3] += origin_z[:, None] * lines[:, :3, 2] + x_mid[:, None] * lines[:, :3, 0]
        poses.append(q)
    return np.concatenate(poses)


def canonical_grasp(poses: np.ndarray) -> np.ndarray:
    """A parallel-jaw grasp equals itself turned 180 deg about approach; pick one of the two: [..., 4, 4].

    The closing axis is flipped (with y) so that it has a positive dot with a fixed generic direction.
    """
    generic = np.array([0.8117, 0.4719, 0.3441])
    flip = np.where(poses[..., :3, 0] @ generic < 0, -1.0, 1.0)
    out = poses.copy()
    out[..., :3, 0] *= flip[..., None]
    out[..., :3, 1] *= flip[..., None]
    return out


def unique_grasps(poses: np.ndarray, widths: np.ndarray, tol: float = 1e-3) -> tuple[np.ndarray, np.ndarray]:
    """Drop duplicate grasps: the same pose up to the 180 deg jaw symmetry, origins within `tol` metres
    and axes within `tol` radians. Keeps first occurrences, in order: [T, 4, 4], [T] -> [T', 4, 4], [T']."""
    if len(poses) == 0:
        return poses, widths
    canon = canonical_grasp(poses)
    key = np.concatenate([canon[:, :3, 3], canon[:, :3, 0], canon[:, :3, 2]], axis=1)
    close = np.all(np.abs(key[:, None] - key[None]) <= tol, axis=-1)
    # Greedy: keep a grasp unless it is a copy of an already kept one. Every dropped grasp then lies
    # within tol of a kept one, which keeps `symmetrize` closed under repeated application.
    alive = np.ones(len(key), bool)
    kept = []
    for i in range(len(key)):
        if alive[i]:
            kept.append(i)
            alive &= ~close[i]
    return canon[kept], widths[kept]


# The four proper frame flips of a superquadric (it is symmetric under each): identity and the
# half-turns about x, y and z.
FRAME_SYMMETRIES = np.stack([np.diag(d) for d in ([1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1])]).astype(float)


def symmetrize(poses: np.ndarray, widths: np.ndarray, tol: float = 1e-3) -> tuple[np.ndarray, np.ndarray]:
    """Close a grasp set (given in a superquadric's frame) under FRAME_SYMMETRIES, widths carried along.

    A superquadric fitted in a flipped frame is the same surface, so its transferred grasps must be the
    same set in the world: that holds exactly when the template set is closed under the flips.
    poses [T, 4, 4], widths [T] -> ([T', 4, 4], [T']).
    """
    sym = np.zeros((len(FRAME_SYMMETRIES), 4, 4))
    sym[:, :3, :3] = FRAME_SYMMETRIES
    sym[:, 3, 3] = 1.0
    all_poses = np.einsum("gij,tjk->gtik", sym, poses).reshape(-1, 4, 4)
    return unique_grasps(all_poses, np.tile(widths, len(sym)), tol)


def template_grasps(
    p: Primitive, spec: GripperSpec = GripperSpec(), cfg: TemplateConfig = TemplateConfig(), seed: int = 0
) -> tuple[np.ndarray, np.ndarray]:
    """Template grasps of one primitive in its own frame: -> (poses [T, 4, 4], widths [T]).

    Poses come from `_directions` and `_place`; widths from `closing_widths`; templates over the
    maximum opening, in the air, or with the palm on the surface are dropped, duplicates removed.
    """
    points = surface_points(p, cfg.surface_samples, seed=seed)
    lines = []
    for approach, closing, offsets in _directions(p, spec, cfg):
        frame = grasp_frame(approach, closing, np.zeros(3))
        for offset in offsets:
            line = frame.copy()
            line[:3, 3] = offset * frame[:3, 1]
            lines.append(line)
    poses = _place(points, np.stack(lines), spec, cfg)
    widths = closing_widths(points, poses, spec)
    keep = np.isfinite(widths) & ~palm_hits(points, poses, spec)
    return unique_grasps(poses[keep], widths[keep])
