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
from sgjax.stage2.pointnet2 import first_set_bits, interleave, pack_flags, pack_interleaved

_WORD_ALIGN = 32  # subsets are whole 32-point words

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


# Candidates are cropped in chunks of CHUNK; each chunk first keeps the scene points inside the world
# box around its candidates' regions (their gripper-frame bounds, `_local_bounds`) and tests only those
# (scene order kept: the same crop). The subset has a fixed size, the smallest of SUBSET_FRACTIONS of
# the scene that holds the box's points; a chunk whose box holds more tests every point. The planner
# hands candidates object by object, so a chunk's box is one object's neighbourhood: on
# benchmarks/bench_ernet.py's scene 6-13 % of the points for chunks of 64 swept regions, at most 26 %.
CHUNK = 64
SUBSET_FRACTIONS = (0.125, 0.375)
_BOUNDS_PAD = 1e-3  # m: the box is grown so that float rounding can never leave a region point out


def _local_bounds(spec: GripperSpec, widths: jax.Array, kind: str, sweep: float = 0.0, margin: float = 0.0):
    """Gripper-frame boxes (centre [M, 3], half extents [M, 3]) holding each candidate's crop region:
    "closing" the closing region, "enlarged" its union over the refined frames, "swept" that and the
    hand's swept boxes (`gripper.hand_boxes`)."""
    w = jnp.asarray(widths, jnp.float32)
    fy, length = 0.5 * spec.finger_width, spec.finger_length
    lo = [jnp.broadcast_to(jnp.float32(v), w.shape) for v in (0.0, 0.0, 0.0)]
    hi = list(lo)
    frames = _region_frames(spec) if kind in ("enlarged", "swept") else np.eye(4)[None]
    for frame in frames:  # a closing box moved by each frame: centre R c + t, half extents |R| h
        r, t = frame[:3, :3], frame[:3, 3]
        centre = r @ np.array([0.0, 0.0, 0.5 * length]) + t
        half = [float(abs(r[i, 0])) * 0.5 * w + float(abs(r[i, 1])) * fy + float(abs(r[i, 2])) * 0.5 * length for i in range(3)]
        lo = [jnp.minimum(lo[i], float(centre[i]) - half[i]) for i in range(3)]
        hi = [jnp.maximum(hi[i], float(centre[i]) + half[i]) for i in range(3)]
    if kind == "swept":
        for box_lo, box_hi in gripper.hand_boxes(spec, w, margin, sweep):
            lo = [jnp.minimum(lo[i], box_lo[i]) for i in range(3)]
            hi = [jnp.maximum(hi[i], box_hi[i]) for i in range(3)]
    lo, hi = jnp.stack(lo, -1), jnp.stack(hi, -1)
    return 0.5 * (lo + hi), 0.5 * (hi - lo) + _BOUNDS_PAD


def _crop(
    scene: jax.Array,
    poses: jax.Array,
    widths: jax.Array,
    n_points: int,
    scene_mask: jax.Array | None,
    inside: Callable[[list, jax.Array], jax.Array],
    bounds: Callable[[jax.Array], tuple[jax.Array, jax.Array]],
) -> Region:
    """The points of scene[N, 3] for which `inside(local planes [x, y, z] each [32, W], width [])`
    holds, per candidate (poses[M, 4, 4], widths[M]), in its gripper frame -> Region with P = n_points.
    bounds(widths [M]) -> (centre, half extents) [M, 3]: gripper-frame boxes that hold `inside`."""
    scene = jnp.asarray(scene, jnp.float32)
    if scene.ndim != 2 or scene.shape[-1] != 3:
        raise ValueError(f"scene must have shape [N, 3], got {scene.shape}")
    poses, widths = check_candidates(poses, widths)
    n, m = scene.shape[0], widths.shape[0]
    valid = jnp.all(jnp.isfinite(scene), -1)
    if scene_mask is not None:
        scene_mask = jnp.asarray(scene_mask)
        if scene_mask.shape != scene.shape[:1]:
            raise ValueError(f"scene_mask must have shape {scene.shape[:1]}, got {scene_mask.shape}")
        valid = valid & scene_mask.astype(bool)
    rotation, translation = poses[:, :3, :3], poses[:, :3, 3]
    # Absent points become NaN: every comparison with NaN is False, so they are never inside.
    absent = jnp.where(valid[:, None], scene, jnp.nan)  # [N, 3]
    planes = interleave(absent.T, jnp.nan)  # [3, 32, W]

    def region_words(candidate, planes):
        r, t, w = candidate  # [3, 3], [3], []
        d = [planes[i] - t[i] for i in range(3)]
        local = [r[0, i] * d[0] + r[1, i] * d[1] + r[2, i] * d[2] for i in range(3)]  # p_g = R^T (p_w - t)
        return pack_interleaved(inside(local, w))

    # World boxes around each candidate's region: centre R c + t, half extents |R| h.
    local_centre, local_half = bounds(widths)
    centre = jnp.einsum("mij,mj->mi", rotation, local_centre) + translation
    half = jnp.einsum("mij,mj->mi", jnp.abs(rotation), local_half)
    chunk = min(CHUNK, m)
    chunks = -(-m // chunk)
    pad = chunks * chunk - m  # padding repeats the last candidate: its box adds nothing

    def chunked(x):
        x = jnp.concatenate([x, jnp.repeat(x[-1:], pad, axis=0)]) if pad else x
        return x.reshape(chunks, chunk, *x.shape[1:])

    sizes = sorted({min(n, max(_WORD_ALIGN, -(-int(n * f) // _WORD_ALIGN) * _WORD_ALIGN)) for f in SUBSET_FRACTIONS} - {n})
    words_of = jax.vmap(region_words, in_axes=((0, 0, 0), None))

    def crop_chunk(args):
        r, t, w, box_lo, box_hi = args  # [G, 3, 3], [G, 3], [G], [3], [3]

        def from_all(_):
            return first_set_bits(words_of((r, t, w), planes), n, n_points)

        if not sizes:
            return from_all(None)
        near = jnp.all((absent >= box_lo) & (absent <= box_hi), axis=-1)  # NaN rows are never near
        near_count = jnp.sum(near, dtype=jnp.int32)
        subset = jnp.nonzero(near, size=sizes[-1], fill_value=n)[0].astype(jnp.int32)  # scene order kept

        def from_subset(c):
            def crop(_):
                index = subset[:c]
                points = jnp.where((index < n)[:, None], absent[jnp.minimum(index, n - 1)], jnp.nan)
                found, count = first_set_bits(words_of((r, t, w), interleave(points.T, jnp.nan)), c, n_points)
                return jnp.where(found < c, index[jnp.minimum(found, c - 1)], n), count
            return crop

        tier = sum((near_count > c).astype(jnp.int32) for c in sizes)  # the smallest subset that holds them
        return jax.lax.switch(tier, [from_subset(c) for c in sizes] + [from_all], None)

    lo, hi = chunked(centre - half), chunked(centre + half)
    index, count = jax.lax.map(crop_chunk, (chunked(rotation), chunked(translation), chunked(widths),
                                            lo.min(axis=1), hi.max(axis=1)))
    index, count = index.reshape(-1, n_points)[:m], count.reshape(-1)[:m]
    mask = jnp.arange(n_points) < count[:, None]
    picked = jnp.where(valid[:, None], scene, 0.0)[jnp.minimum(index, n - 1)]  # [M, P, 3]
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
                 lambda local, w: _in_enlarged(*(c[None] for c in local), w[None], spec)[0],
                 lambda w: _local_bounds(spec, w, "enlarged"))


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

    return _crop(scene, poses, widths, n_points, scene_mask, inside,
                 lambda w: _local_bounds(spec, w, "swept", sweep, margin))


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
    return _crop(scene, poses, widths, n_points, scene_mask, lambda local, w: _in_closing_planes(*local, w, spec),
                 lambda w: _local_bounds(spec, w, "closing"))


CROPS = ("enlarged", "swept")  # the stored Stage-2 inputs, by name (`ERNetConfig.crop`, train.dataset)


def crop_function(crop: str) -> Callable[..., Region]:
    """The cropper of the Stage-2 input named `crop` ("enlarged": `crop_regions`, the paper's; "swept":
    `crop_swept_regions`), one choice for scoring, labelled data and checks alike; ValueError names an
    unknown one."""
    if crop not in CROPS:
        raise ValueError(f"unknown crop {crop!r}; known: {', '.join(CROPS)}")
    return crop_swept_regions if crop == "swept" else crop_regions
