"""Stage-2 crops: the scene points inside each candidate's gripper regions, in its gripper frame.

Both Stage-2 networks see a crop of the scene cloud around each grasp candidate:

  crop_regions          E-RNet (paper Sec. IV-C): the enlarged region, the union of the closing regions
                        of the initial pose and the refined poses (deepen 0.008 m, rotate -15/0/+15 deg).
  crop_closing_regions  PointNetGPD (the baseline): the closing region of the initial pose,
                        |x| <= w/2, |y| <= finger_width/2, 0 <= z <= finger_length.

One crop routine (`_crop`) serves both; only the region test differs. A crop is one fused pass over
M candidates x N scene points with the membership bits packed 32 to a word (no [M, N, 3]
intermediate); it keeps the first `n_points` region points in scene order, so shuffle the scene first
for a uniform sample (`ernet.score` and `pointnetgpd.score` do). Non-finite scene points count as
absent. The region tests take coordinate planes x, y, z so that XLA fuses them into that pass; their boxes
and the point test are `sgjax.geometry.gripper`'s (`closing_box`, `in_box`), as for every region test.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from sgjax.geometry import gripper
from sgjax.geometry.gripper import GripperSpec
from sgjax.geometry.rotations import points_to_frame
from sgjax.stage2.pointnet2 import first_set_bits, interleave, pack_interleaved

# The hand's swept volume in E-RNet's "swept" input: the executor's pre-grasp approach runs the last
# HAND_SWEEP metres straight in (envs TrialConfig.pregrasp_distance), and the boxes are grown by
# HAND_MARGIN so that a neighbour just outside a finger is seen too.
HAND_SWEEP = 0.05
HAND_MARGIN = 0.005

# ---------------------------------------------------------------------------------------------
# Region tests in the gripper frame.


@functools.cache
def _region_frames(spec: GripperSpec) -> np.ndarray:
    """The enlarged region's poses relative to the initial pose: [1 + K, 4, 4] (index 0: identity).

    refined = pose @ T_v, so T_v = enlarged_region_poses(identity)."""
    with jax.ensure_compile_time_eval():
        return np.asarray(gripper.enlarged_region_poses(jnp.eye(4), spec), np.float64)


def _in_closing_box(x, y, z, width, spec: GripperSpec, frame: np.ndarray | None = None):
    """Whether gripper-frame points (planes x, y, z [M, N]) lie in the closing region of the pose
    `frame` (relative to the gripper frame; None: the initial pose) for widths [M]."""
    if frame is not None:
        r, t = frame[:3, :3], frame[:3, 3]
        d = [c - float(o) if o != 0 else c for c, o in zip((x, y, z), t)]
        x, y, z = (_dot_constant(r[:, i], d) for i in range(3))
    return gripper.in_box(x, y, z, gripper.closing_box(spec, jnp.asarray(width, jnp.float32)[:, None]))


def _dot_constant(coefficients: np.ndarray, planes: list) -> jax.Array:
    """sum_j c_j * planes[j] for trace-time constants c, skipping zeros and unit factors (the refined
    frames are a z shift and a z rotation, so most terms vanish; this runs M x N times per call)."""
    terms = [p if c == 1.0 else (-p if c == -1.0 else float(c) * p) for c, p in zip(coefficients, planes) if c != 0.0]
    out = terms[0] if terms else jnp.zeros_like(planes[0])
    for term in terms[1:]:
        out = out + term
    return out


def in_closing_region_local(points: jax.Array, width: jax.Array, spec: GripperSpec) -> jax.Array:
    """Gripper-frame points[M, N, 3], width[M] -> bool[M, N]: inside the initial closing region.

    Equals `gripper.points_in_closing_region(to_world(points, pose), pose, width, spec)`."""
    x, y, z = points[..., 0], points[..., 1], points[..., 2]
    return _in_closing_box(x, y, z, jnp.asarray(width, points.dtype), spec)


def in_enlarged_region_local(points: jax.Array, width: jax.Array, spec: GripperSpec) -> jax.Array:
    """Gripper-frame points[M, N, 3], width[M] -> bool[M, N]: inside the enlarged region.

    Equals `gripper.points_in_enlarged_region` evaluated in the world frame."""
    x, y, z = points[..., 0], points[..., 1], points[..., 2]
    return _in_enlarged(x, y, z, jnp.asarray(width, points.dtype), spec)


def in_swept_hand_local(points: jax.Array, width: jax.Array, spec: GripperSpec, sweep: float, margin: float) -> jax.Array:
    """Gripper-frame points[M, N, 3], width[M] -> bool[M, N]: inside a finger or the palm of the hand
    open to `width`, grown by `margin` and swept back by `sweep` along -z (the approach's last metres):
    where a collision on the way in or at the grasp would happen (`gripper.hand_boxes`)."""
    x, y, z = points[..., 0], points[..., 1], points[..., 2]
    return _in_swept_hand(x, y, z, jnp.asarray(width, points.dtype)[..., None], spec, sweep, margin)


def _in_swept_hand(x, y, z, width, spec: GripperSpec, sweep: float, margin: float):
    right, left, palm = gripper.hand_boxes(spec, width, margin, sweep)
    return gripper.in_box(x, y, z, right) | gripper.in_box(x, y, z, left) | gripper.in_box(x, y, z, palm)


def _in_enlarged(x, y, z, width, spec: GripperSpec):
    inside = _in_closing_box(x, y, z, width, spec)
    for frame in _region_frames(spec)[1:]:
        inside = inside | _in_closing_box(x, y, z, width, spec, frame)
    return inside


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Region:
    """Scene points in each candidate's enlarged region, in that candidate's gripper frame.

    points: [M, P, 3] (padding rows are 0); mask: bool[M, P]; count: int32[M], points found in the
    region before truncation to P (count > P means a uniform random P of them were kept)."""

    points: jax.Array
    mask: jax.Array
    count: jax.Array


def check_candidates(poses, widths) -> tuple[jax.Array, jax.Array]:
    poses = jnp.asarray(poses)
    if poses.ndim != 3 or poses.shape[-2:] != (4, 4):
        raise ValueError(f"poses must have shape [M, 4, 4], got {poses.shape}")
    widths = jnp.asarray(widths, poses.dtype if jnp.issubdtype(poses.dtype, jnp.floating) else jnp.float32)
    if widths.shape != poses.shape[:1]:
        raise ValueError(f"widths must have shape [M] = {poses.shape[:1]} (one per pose), got {widths.shape}")
    return poses.astype(jnp.float32), widths.astype(jnp.float32)



def _in_closing_planes(x, y, z, width, spec: GripperSpec):
    """Gripper-frame coordinate planes (any equal shapes) inside the closing region of `width` (scalar)."""
    return gripper.in_box(x, y, z, gripper.closing_box(spec, jnp.asarray(width, jnp.float32)))


# ---------------------------------------------------------------------------------------------
# The crops.


def _crop(
    scene: jax.Array,
    poses: jax.Array,
    widths: jax.Array,
    n_points: int,
    scene_mask: jax.Array | None,
    inside: Callable[[list, jax.Array], jax.Array],
) -> Region:
    """The points of scene[N, 3] for which `inside(local planes [x, y, z] each [32, W], width [])`
    holds, per candidate (poses[M, 4, 4], widths[M]), in its gripper frame -> Region with P = n_points."""
    scene = jnp.asarray(scene, jnp.float32)
    if scene.ndim != 2 or scene.shape[-1] != 3:
        raise ValueError(f"scene must have shape [N, 3], got {scene.shape}")
    poses, widths = check_candidates(poses, widths)
    valid = jnp.all(jnp.isfinite(scene), -1)
    if scene_mask is not None:
        scene_mask = jnp.asarray(scene_mask)
        if scene_mask.shape != scene.shape[:1]:
            raise ValueError(f"scene_mask must have shape {scene.shape[:1]}, got {scene_mask.shape}")
        valid = valid & scene_mask.astype(bool)
    rotation, translation = poses[:, :3, :3], poses[:, :3, 3]
    # Absent points become NaN: every comparison with NaN is False, so they are never inside.
    planes = interleave(jnp.where(valid[None, :], scene.T, jnp.nan), jnp.nan)  # [3, 32, W]

    def region_words(candidate):
        r, t, w = candidate  # [3, 3], [3], []
        d = [planes[i] - t[i] for i in range(3)]
        local = [r[0, i] * d[0] + r[1, i] * d[1] + r[2, i] * d[2] for i in range(3)]  # p_g = R^T (p_w - t)
        return pack_interleaved(inside(local, w))

    # lax.map over chunks of candidates: its inputs are materialised, so XLA cannot fuse whatever
    # computed the poses (a caller's guard, a reduction) into the M x N loop and redo it per point.
    words = jax.lax.map(region_words, (rotation, translation, widths), batch_size=min(64, len(widths)))
    index, count = first_set_bits(words, scene.shape[0], n_points)
    mask = jnp.arange(n_points) < count[:, None]
    picked = jnp.where(valid[:, None], scene, 0.0)[jnp.minimum(index, scene.shape[0] - 1)]  # [M, P, 3]
    points = points_to_frame(picked, rotation, translation)
    return Region(jnp.where(mask[..., None], points, 0.0), mask, count)


def crop_regions(
    scene: jax.Array,
    poses: jax.Array,
    widths: jax.Array,
    spec: GripperSpec,
    n_points: int,
    scene_mask: jax.Array | None = None,
) -> Region:
    """Crop each candidate's enlarged region (E-RNet's input) from a world-frame scene cloud, in its
    gripper frame.

    scene[N, 3] (world), poses[M, 4, 4] (gripper -> world), widths[M], scene_mask[N] (None: all)
    -> Region with P = n_points.
    """
    return _crop(scene, poses, widths, n_points, scene_mask,
                 lambda local, w: _in_enlarged(*(c[None] for c in local), w[None], spec)[0])


def crop_swept_regions(
    scene: jax.Array,
    poses: jax.Array,
    widths: jax.Array,
    spec: GripperSpec,
    n_points: int,
    scene_mask: jax.Array | None = None,
    *,
    sweep: float = HAND_SWEEP,
    margin: float = HAND_MARGIN,
) -> Region:
    """Crop each candidate's enlarged region together with its hand's swept volume (`in_swept_hand_local`)
    from a world-frame scene cloud, in its gripper frame: E-RNet's input when it also judges collisions.

    scene[N, 3] (world), poses[M, 4, 4], widths[M], scene_mask[N] (None: all) -> Region with P = n_points.
    """
    def inside(local, w):
        x, y, z = (c[None] for c in local)
        return (_in_enlarged(x, y, z, w[None], spec) | _in_swept_hand(x, y, z, w[None], spec, sweep, margin))[0]

    return _crop(scene, poses, widths, n_points, scene_mask, inside)


def crop_closing_regions(
    scene: jax.Array,
    poses: jax.Array,
    widths: jax.Array,
    spec: GripperSpec,
    n_points: int,
    scene_mask: jax.Array | None = None,
) -> Region:
    """Crop each candidate's closing region (PointNetGPD's input) from a world-frame scene cloud, in its
    gripper frame.

    scene[N, 3] (world), poses[M, 4, 4] (gripper -> world), widths[M], scene_mask[N] (None: all)
    -> Region with P = n_points.
    """
    return _crop(scene, poses, widths, n_points, scene_mask, lambda local, w: _in_closing_planes(*local, w, spec))
