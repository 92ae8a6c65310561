"""GPD-style grasp candidates (no learning): antipodal candidates sampled on the scene cloud, evaluated
geometrically. Shared by the `gpd` method (eval/gpd.py) and the PointNetGPD / gpd+s2 baselines
(eval/baselines.py), which score them with a network instead.

In the spirit of GPD's candidate generator (ten Pas et al., IJRR 2017) and the antipodal sampler of
PointNetGPD, ranked by a geometric antipodal score instead of a learned classifier:

Stage 1 (candidates):
  1. the observed object points (labels >= 0) are voxel-downsampled to at most `max_points` (fixed
     shape, padded with a mask); the table height is the median z of the table points (labels < 0);
  2. unit normals by kNN PCA (`sgjax.stage1.filters.estimate_normals`), oriented towards the camera;
  3. `num_samples` points are drawn (seeded); at each the closing axis x is the surface normal and the
     approach z is turned about x over `num_angles` angles, starting from the most downward direction
     perpendicular to x (approaches further than `max_approach_angle_deg` from straight down are
     dropped: GPD's approach-direction filter);
  4. the sampled point is put inside the +x finger of the open gripper (`lateral_steps` placements
     along x, contact_threshold inside the finger first) and the hand is pushed as deep as it goes: of
     `depth_steps` depths, the deepest one with a placement at which no cloud point lies in a finger or
     the palm -- swept back along the approach by `approach_clearance`, the path of the executor's
     pre-grasp motion -- and the gripper stays `table_clearance` above the table plane.
Stage 2 (evaluation):
  5. when both contact faces are seen (points within `contact_slab` of each finger whose normals point
     outwards along the closing axis, within `observed_angle_deg`), the hand is centred on the points
     between its fingers and its width set to their extent along x plus 2 * contact_threshold (capped
     at max_opening); when only one face is seen, the object's far side is hidden, so the hand stays
     open at max_opening with the seen face contact_threshold inside its finger, moved back just enough
     to keep every seen point between the fingers (a width read off one visible face would put the
     other finger inside the object); when neither is, the open hand is centred on the seen points.
     Collisions are checked again; a hand that now collides falls back to stage 1's open placement;
  6. candidates with fewer than `min_points` points between the fingers are dropped; the rest are ranked
     by the antipodal score: per finger, the best alignment max(0, +-n . x) between the outward normal
     n of a point within `contact_slab` of that finger and the finger's closing direction; the score is
     the mean over the two fingers (an unseen contact face contributes 0, so grasps across two seen
     faces rank first).

All array work is two jitted JAX functions of fixed shapes (one compile per GPDConfig); the host only
voxelizes the cloud (the method picks the best candidate).
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np

from sgjax.stage1.filters import estimate_normals
from sgjax.geometry.gripper import GripperSpec, local_regions, lowest_height
from sgjax.geometry.rotations import points_to_frame
from sgjax.geometry.superquadric import pose_matrix

DOWN = np.array([0.0, 0.0, -1.0], np.float32)


@dataclasses.dataclass(frozen=True)
class GPDConfig:
    """Sampling, search and ranking settings (metres, degrees); hashable, so a static jit argument."""

    voxel_size: float = 0.006
    max_points: int = 4096  # 10 objects at 6 mm voxels give ~2000-3000 points, 20 objects ~4000
    num_samples: int = 128
    num_angles: int = 7
    max_approach_angle_deg: float = 60.0
    depth_steps: int = 6
    lateral_steps: int = 4  # placements of the sampled point along the closing axis (1-4)
    min_depth: float = 0.01  # the sampled point's smallest distance in front of the palm face
    tip_margin: float = 0.005  # ... and its smallest distance behind the fingertips
    min_points: int = 10
    contact_slab: float = 0.005
    observed_angle_deg: float = 60.0  # a contact face counts as seen if its normal is this close to +-x
    normal_neighbours: int = 16
    approach_clearance: float = 0.05  # TrialConfig.pregrasp_distance: the approach path is checked too
    table_clearance: float = 0.003
    spec: GripperSpec = dataclasses.field(default_factory=GripperSpec)
    # num_samples serve up to this many objects in view; a scene with more gets a multiple of it
    # (`scaled_to_scene`): a fixed budget left dense scenes short of candidates (docs/experiments.md,
    # 2026-12-05). 0: a fixed budget.
    objects_per_budget: int = 10

    def __post_init__(self):
        for name in ("voxel_size", "max_points", "num_samples", "num_angles", "depth_steps", "normal_neighbours"):
            if not getattr(self, name) > 0:
                raise ValueError(f"GPDConfig.{name} must be positive, got {getattr(self, name)}")
        if self.objects_per_budget < 0:
            raise ValueError(f"GPDConfig.objects_per_budget must be >= 0 (0: a fixed budget), got {self.objects_per_budget}")
        if not 1 <= self.lateral_steps <= 4:
            raise ValueError(f"GPDConfig.lateral_steps must be in [1, 4], got {self.lateral_steps}")
        if not 0 <= self.max_approach_angle_deg <= 90:
            raise ValueError(f"max_approach_angle_deg must be in [0, 90], got {self.max_approach_angle_deg}")
        if not 0 <= self.min_depth < self.spec.finger_length - self.tip_margin:
            raise ValueError("need 0 <= min_depth < finger_length - tip_margin")


# ---------------------------------------------------------------------------------------------------
# Host side: the cloud.


def first_per_voxel(points: np.ndarray, voxel: float) -> np.ndarray:
    """Indices of one point per occupied voxel (the first in input order), sorted: [N, 3] -> [V].

    Not `pointcloud.voxel_downsample` (the point nearest each voxel's centre): GPD's sampler and the
    oracle index other per-point arrays with these, and changing which point a voxel keeps would
    change the baselines' candidates."""
    if len(points) == 0:
        return np.zeros(0, np.int64)
    keys = np.floor(np.asarray(points, np.float64) / voxel).astype(np.int64)
    _, first = np.unique(keys, axis=0, return_index=True)
    return np.sort(first)


def budget_factor(labels: np.ndarray, config: GPDConfig) -> int:
    """How many times `num_samples` a scene gets: ceil(objects in view / objects_per_budget), at least 1
    (labels [P]: an object is in view with at least `min_points` points). Whole multiples keep the number
    of compiled shapes small (one per factor)."""
    if config.objects_per_budget == 0:
        return 1
    ids, counts = np.unique(np.asarray(labels).reshape(-1), return_counts=True)
    in_view = int(np.sum((ids >= 0) & (counts >= config.min_points)))
    return max(1, -(-in_view // config.objects_per_budget))


def scaled_to_scene(config: GPDConfig, labels: np.ndarray) -> tuple[GPDConfig, int]:
    """(config with num_samples times `budget_factor`, the factor) for the scene of labels [P]."""
    factor = budget_factor(labels, config)
    return (config if factor == 1 else dataclasses.replace(config, num_samples=config.num_samples * factor)), factor


def prepare_cloud(
    points: np.ndarray, labels: np.ndarray, config: GPDConfig, seed: int = 0
) -> tuple[np.ndarray, np.ndarray, float, int]:
    """Object points voxel-downsampled and padded: (points [max_points, 3] f32, mask [max_points],
    table_z, number of object points before padding). Table points (labels < 0) only give table_z
    (median z; -inf when no table point is seen, i.e. no table check)."""
    out, mask, table_z, n, _ = prepare_labelled_cloud(points, labels, config, seed)
    return out, mask, table_z, n


def prepare_labelled_cloud(
    points: np.ndarray, labels: np.ndarray, config: GPDConfig, seed: int = 0
) -> tuple[np.ndarray, np.ndarray, float, int, np.ndarray]:
    """`prepare_cloud` plus the object label of each kept point: (..., labels [max_points] int32, -1
    for padding), so that candidates can be drawn on one object (`candidates(sample_mask=...)`)."""
    points = np.asarray(points, np.float32).reshape(-1, 3)
    labels = np.asarray(labels).reshape(-1)
    if len(labels) != len(points):
        raise ValueError(f"got {len(points)} points but {len(labels)} labels")
    finite = np.isfinite(points).all(axis=1)
    table = finite & (labels < 0)
    table_z = float(np.median(points[table, 2])) if table.any() else -np.inf
    keep = finite & (labels >= 0)
    obj, obj_labels = points[keep], labels[keep]
    first = first_per_voxel(obj, config.voxel_size)
    obj, obj_labels = obj[first], obj_labels[first]
    if len(obj) > config.max_points:
        pick = np.sort(np.random.default_rng(seed).choice(len(obj), config.max_points, replace=False))
        obj, obj_labels = obj[pick], obj_labels[pick]
    out = np.zeros((config.max_points, 3), np.float32)
    out[: len(obj)] = obj
    out_labels = np.full(config.max_points, -1, np.int32)
    out_labels[: len(obj)] = obj_labels
    return out, np.arange(config.max_points) < len(obj), table_z, len(obj), out_labels


# ---------------------------------------------------------------------------------------------------
# Device side.


def swept_hits(local: jax.Array, width: jax.Array, spec: GripperSpec, sweep: float) -> jax.Array:
    """Gripper-frame points [..., N, 3] inside a finger or the palm of an open hand of `width` [...],
    swept back by `sweep` along -z (the approach path) -> bool [..., N]."""
    return local_regions(local, width, spec, 0.0, sweep)[1]


def _table_plane(table_z: jax.Array) -> jax.Array:
    """The table z = table_z as a plane (n, d) [4]; table_z = -inf (no table seen) puts it infinitely low."""
    return jnp.concatenate([jnp.asarray([0.0, 0.0, 1.0]), -jnp.reshape(table_z, (1,))]).astype(jnp.float32)


def lateral_offsets(config: GPDConfig) -> np.ndarray:
    """Where stage 1 tries to put the sampled point along the closing axis (m from the hand's centre
    plane, +x side): first contact_threshold inside the +x finger, then nearer the finger, then
    towards the centre (GPD's hand search over finger placements)."""
    half = 0.5 * config.spec.max_opening
    delta = config.spec.contact_threshold
    return np.asarray([half - delta, half - 0.004, 0.5 * (half - delta), 0.0][: config.lateral_steps], np.float32)


@functools.partial(jax.jit, static_argnames="config")
def candidates(points, mask, viewpoint, table_z, key, config: GPDConfig, sample_mask=None) -> dict:
    """Stage 1: collision-free antipodal candidates on a padded cloud.

    points [N, 3], mask [N], viewpoint [3], table_z [], key -> {"poses" [K, A, 4, 4], "valid" [K, A],
    "normals" [N, 3], "sample" [K]}; K = num_samples, A = num_angles.
    sample_mask [N] or None: the points to draw the K samples from (e.g. one object's, for candidates on
    that object); every point of `mask` is still an obstacle. None: all of `mask`.
    """
    spec, n = config.spec, points.shape[0]
    table = _table_plane(table_z)
    normals = estimate_normals(points, mask, viewpoint, config.normal_neighbours)
    weight = (mask if sample_mask is None else mask & sample_mask).astype(jnp.float32)
    sample = jax.random.choice(key, n, (config.num_samples,), replace=True, p=weight / jnp.maximum(weight.sum(), 1.0))
    p, x = points[sample], normals[sample]  # [K, 3]
    down = jnp.asarray(DOWN)
    a0 = down - (x @ down)[:, None] * x
    norm = jnp.linalg.norm(a0, axis=-1, keepdims=True)
    other = jnp.cross(x, jnp.asarray([1.0, 0.0, 0.0]))  # x (anti)parallel to down: any perpendicular
    other = jnp.where(jnp.linalg.norm(other, axis=-1, keepdims=True) < 1e-3, jnp.cross(x, jnp.asarray([0.0, 1.0, 0.0])), other)
    a0 = jnp.where(norm > 1e-3, a0 / jnp.maximum(norm, 1e-9), other / jnp.linalg.norm(other, axis=-1, keepdims=True))
    b0 = jnp.cross(x, a0)
    limit = np.deg2rad(config.max_approach_angle_deg)
    theta = jnp.asarray(np.linspace(-limit, limit, config.num_angles), jnp.float32)
    z = jnp.cos(theta)[None, :, None] * a0[:, None] + jnp.sin(theta)[None, :, None] * b0[:, None]  # [K, A, 3]
    xk = jnp.broadcast_to(x[:, None], z.shape)
    y = jnp.cross(z, xk)
    rotation = jnp.stack([xk, y, z], axis=-1)  # columns x, y, z: [K, A, 3, 3]
    approach_ok = jnp.einsum("kaj,j->ka", z, down) >= np.cos(limit) - 1e-6

    # Gripper-frame points with the origin at p (depth 0, offset 0): local = R^T (q - p).
    local0 = points_to_frame(points, rotation, jnp.broadcast_to(p[:, None], rotation.shape[:-1]))
    open_width = jnp.full(z.shape[:2], spec.max_opening, jnp.float32)
    depths = np.linspace(config.min_depth, spec.finger_length - config.tip_margin, config.depth_steps)
    offsets = lateral_offsets(config)
    free = []  # [D * L] in search order: deepest first, then the offsets in order
    for s in depths:  # the sample s metres in front of the palm face
        for u in offsets:  # ... and u along +x from the hand's centre plane
            hits = swept_hits(local0 + jnp.asarray([u, 0.0, s], jnp.float32), open_width, spec, config.approach_clearance)
            cloud_free = ~jnp.any(hits & mask, -1)
            origin = p[:, None] - u * xk - s * z
            table_free = lowest_height(pose_matrix(rotation, origin), open_width, spec, table) >= config.table_clearance
            free.append(cloud_free & table_free)
    free = jnp.stack(free, -1)  # [K, A, D * L]
    first = jnp.argmax(free, -1)
    depth = jnp.asarray(np.repeat(depths, len(offsets)), jnp.float32)[first]
    offset = jnp.asarray(np.tile(offsets, len(depths)), jnp.float32)[first]
    origin = p[:, None] - offset[..., None] * xk - depth[..., None] * z
    poses = jnp.zeros((*z.shape[:2], 4, 4), jnp.float32).at[..., :3, :3].set(rotation)
    poses = poses.at[..., :3, 3].set(origin).at[..., 3, 3].set(1.0)
    valid = jnp.any(free, -1) & approach_ok & (weight[sample] > 0)[:, None]
    return {"poses": poses, "valid": valid, "normals": normals, "sample": sample, "approach_ok": approach_ok}


@functools.partial(jax.jit, static_argnames="config")
def evaluate(poses, valid, points, mask, normals, table_z, config: GPDConfig) -> dict:
    """Stage 2: centre, size, re-check and score candidates poses [M, 4, 4], valid [M].

    -> {"poses" [M, 4, 4], "widths" [M], "scores" [M], "valid" [M], "points_between" [M]}.
    """
    spec = config.spec
    table = _table_plane(table_z)
    rotation, origin = poses[:, :3, :3], poses[:, :3, 3]
    local = points_to_frame(points, rotation, origin)
    x, y, z = local[..., 0], local[..., 1], local[..., 2]
    in_y = jnp.abs(y) <= 0.5 * spec.finger_width
    in_z = (z >= 0.0) & (z <= spec.finger_length)
    between = mask & in_y & in_z & (jnp.abs(x) <= 0.5 * spec.max_opening)
    big = 1e3
    lo = jnp.min(jnp.where(between, x, big), -1)
    hi = jnp.max(jnp.where(between, x, -big), -1)
    any_between = jnp.any(between, -1)
    # Normals face the camera, i.e. outwards on a visible surface: a finger's contact face is observed
    # when points near that finger have normals pointing away from the hand's centre along x.
    signed = jnp.einsum("nj,mj->mn", normals, rotation[:, :, 0])  # [M, N]
    observed_cos = np.cos(np.deg2rad(config.observed_angle_deg))
    slab = config.contact_slab
    right = jnp.any(between & (x >= hi[:, None] - slab) & (signed >= observed_cos), -1)
    left = jnp.any(between & (x <= lo[:, None] + slab) & (signed <= -observed_cos), -1)
    both = right & left
    # One face seen: keep it contact_threshold inside its finger, as far as the seen points allow.
    inner = 0.5 * spec.max_opening - spec.contact_threshold
    low, high = hi - 0.5 * spec.max_opening + 0.002, lo + 0.5 * spec.max_opening - 0.002
    one_sided = jnp.clip(jnp.where(right, hi - inner, lo + inner), low, high)
    shift = jnp.where(both | ~(right | left), 0.5 * (lo + hi), one_sided)
    shift = jnp.where(any_between, shift, 0.0)
    width = jnp.where(both, jnp.clip(hi - lo + 2.0 * spec.contact_threshold, 0.0, spec.max_opening), spec.max_opening)

    def assess(shift, width):
        """(ok [M], score [M], points between [M]) of the hands moved by shift [M] along x, of width [M]."""
        xs = x - shift[:, None]
        moved = origin + shift[:, None] * rotation[:, :, 0]
        inside = mask & in_y & in_z & (jnp.abs(xs) <= 0.5 * width[:, None])
        count = jnp.sum(inside, -1)
        hits = jnp.any(swept_hits(local.at[..., 0].set(xs), width, spec, config.approach_clearance) & mask, -1)
        table_ok = lowest_height(pose_matrix(rotation, moved), width, spec, table) >= config.table_clearance
        sides = []
        for side in (-1.0, 1.0):
            extreme = jnp.max(jnp.where(inside, side * xs, -big), -1, keepdims=True)
            contact = inside & (side * xs >= extreme - slab)
            sides.append(jnp.max(jnp.where(contact, jnp.clip(side * signed, 0.0, 1.0), 0.0), -1))
        ok = valid & any_between & ~hits & table_ok & (count >= config.min_points)
        return ok, 0.5 * (sides[0] + sides[1]), count

    # The placement above, else stage 1's own (collision-free with the open hand).
    ok, score, count = assess(shift, width)
    zero, full = jnp.zeros_like(shift), jnp.full_like(width, spec.max_opening)
    ok0, score0, count0 = assess(zero, full)
    use0 = ~ok & ok0
    shift, width = jnp.where(use0, zero, shift), jnp.where(use0, full, width)
    ok, score, count = ok | ok0, jnp.where(use0, score0, score), jnp.where(use0, count0, count)
    out = poses.at[:, :3, 3].set(origin + shift[:, None] * rotation[:, :, 0])
    return {"poses": out, "widths": width, "scores": jnp.where(ok, score, -1.0), "valid": ok, "points_between": count}


@functools.partial(jax.jit, static_argnames="config")
def hand_collisions(poses, widths, points, obstacle_mask, table_z, config: GPDConfig) -> jax.Array:
    """The generator's own collision test on given hands (e.g. refined ones, before they are executed):
    poses [K, 4, 4], widths [K], points [N, 3] with obstacle_mask [N] (the points that count: the cloud
    of `prepare_labelled_cloud`, e.g. without the grasped object's) and table_z [] -> bool [K]: the
    fingers or palm, swept back over `approach_clearance`, meet an obstacle point, or the hand comes
    within `table_clearance` of the table."""
    local = points_to_frame(points, poses[:, :3, :3], poses[:, :3, 3])
    hits = jnp.any(swept_hits(local, widths, config.spec, config.approach_clearance) & obstacle_mask, -1)
    return hits | (lowest_height(poses, widths, config.spec, _table_plane(table_z)) < config.table_clearance)
