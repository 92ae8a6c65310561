"""Parallel-jaw gripper spec and geometry: closing region, enlarged region, collision boxes.

`GripperSpec` is the single source of truth for the gripper's dimensions, shared by Stage 1 (template
widths, coarse filtering), the E-RNet crops and the simulated gripper (which also takes its closing
force and pad friction from it). `sgjax.geometry.gripper_files` reads and writes a spec as a TOML or
JSON file and holds the shipped presets (`load_gripper("robotiq-2f85")`).

Frame convention (the gripper frame, paper Fig. 5):
  * z is the approach axis, pointing from the palm towards the object;
  * x is the closing axis: the fingers move along +-x, the left finger on -x, the right finger on +x;
  * y = z cross x (right-handed), the direction of the fingers' `finger_width`;
  * the origin is the centre of the closing region's palm-side face, so the closing region of width w
    is the box  |x| <= w/2,  |y| <= finger_width/2,  0 <= z <= finger_length  (fingertips at z = L).
  * The fingers are the boxes  w/2 <= |x| <= w/2 + finger_thickness  over the same y, z ranges, and the
    palm is the box  |x| <= palm_size[0]/2,  |y| <= palm_size[1]/2,  -palm_size[2] <= z <= 0.
A grasp is (pose[4, 4], width): the pose maps gripper-frame points to world, p_w = R p_g + t, so the
columns of R are the gripper axes (x, y, z) in the world frame and t is the origin above.

Refinement (paper Sec. IV-C/IV-D, Fig. 5b): the pose is deepened by `deepen` along +z (towards the
object), then rotated about its own z axis by each of `refine_angles_deg`. The enlarged region used for
the E-RNet crop is the union of the closing regions of the initial pose and the three refined poses.

Everything except `check_width` is JAX, batched over leading axes and jit-friendly (pass the spec as a
static argument); wrong shapes raise ValueError at trace time.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from sgjax.geometry.rotations import points_from_frame, points_to_frame, rot_z

# Defaults of GripperSpec's physical values, equal to what the simulated gripper has always used
# (envs.gripper_model.GripperPhysics: grip_force 25 N per finger, pad friction 1.0).
DEFAULT_CLOSING_FORCE = 25.0
DEFAULT_FINGER_FRICTION = 1.0
PHYSICAL_VALUES = {"closing_force": DEFAULT_CLOSING_FORCE, "finger_friction": DEFAULT_FINGER_FRICTION}


@dataclasses.dataclass(frozen=True)
class GripperSpec:
    """Dimensions of a parallel-jaw gripper (metres, degrees); hashable, so usable as a static jit arg.

    max_opening: largest distance between the inner finger faces.
    finger_length: paper "L", fingertip length along z (depth of the closing region).
    finger_width: finger extent along y (the closing region's y extent).
    finger_thickness: finger extent along x.
    palm_size: (x, y, z) extents of the palm box behind the fingers (z < 0).
    deepen: refinement translation along +z (paper: 0.008 m).
    refine_angles_deg: refinement rotations about z after deepening (paper: -15, 0, +15).
    contact_threshold: paper "delta", the inner-face-to-surface distance at which the template
        width is read off when closing the gripper (paper: 0.0125 m).
    closing_force: the force (N) each finger presses on a grasped object, a datasheet's "grip force";
        the simulated gripper's force limit per finger servo (default 25 N, the value the simulation
        has always used: `envs.gripper_model.GripperPhysics`).
    finger_friction: sliding friction coefficient of the finger pads in the simulation (default 1.0,
        rubber-like; a pad's contacts take it whatever the object's).

    closing_force and finger_friction are physical values of the simulated gripper only: nothing in
    Stage 1, Stage 2 or the crops depends on them. They are init-only (`dataclasses.InitVar`) and kept
    as attributes, not dataclass fields, so that `dataclasses.asdict` (hence the primitive database's
    cache key, `DBConfig.key`, and every saved config) is exactly the geometry, as before they existed;
    `==`, `hash` and `repr` include them where they differ from their defaults (so every key built from
    `repr` is unchanged for the default values), and `dataclasses.replace` keeps them. To save or
    rebuild a complete spec use `sgjax.geometry.gripper_files.gripper_to_dict` / `gripper_from_dict`.
    """

    max_opening: float = 0.08
    finger_length: float = 0.05
    finger_width: float = 0.02
    finger_thickness: float = 0.01
    palm_size: tuple[float, float, float] = (0.10, 0.03, 0.02)
    deepen: float = 0.008
    refine_angles_deg: tuple[float, ...] = (-15.0, 0.0, 15.0)
    contact_threshold: float = 0.0125
    closing_force: dataclasses.InitVar[float] = DEFAULT_CLOSING_FORCE
    finger_friction: dataclasses.InitVar[float] = DEFAULT_FINGER_FRICTION

    def __post_init__(self, closing_force: float, finger_friction: float):
        # Init-only values become plain attributes (not fields: see the class docstring).
        for name, value in (("closing_force", closing_force), ("finger_friction", finger_friction)):
            if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
                raise TypeError(f"GripperSpec.{name} must be a number, got {value!r}")
            if not (np.isfinite(value) and value > 0):
                raise ValueError(f"GripperSpec.{name} must be positive and finite, got {value}")
            object.__setattr__(self, name, float(value))
        # Tuples keep the spec hashable even when lists are passed.
        object.__setattr__(self, "palm_size", tuple(float(v) for v in self.palm_size))
        object.__setattr__(self, "refine_angles_deg", tuple(float(v) for v in self.refine_angles_deg))
        if len(self.palm_size) != 3:
            raise ValueError(f"palm_size must have 3 entries (x, y, z), got {self.palm_size}")
        positive = {
            "max_opening": self.max_opening,
            "finger_length": self.finger_length,
            "finger_width": self.finger_width,
            "finger_thickness": self.finger_thickness,
            "palm_size": min(self.palm_size),
        }
        for name, value in positive.items():
            if not value > 0:
                raise ValueError(f"GripperSpec.{name} must be positive, got {value}")
        if self.deepen < 0 or self.contact_threshold < 0:
            raise ValueError("GripperSpec.deepen and contact_threshold must be non-negative")
        if not self.refine_angles_deg:
            raise ValueError("GripperSpec.refine_angles_deg must not be empty")
        # The palm must carry both fingers at full opening.
        span = self.max_opening + 2 * self.finger_thickness
        if self.palm_size[0] < span - 1e-9:
            raise ValueError(f"palm_size[0]={self.palm_size[0]} is narrower than the open fingers' span {span}")

    @property
    def num_refinements(self) -> int:
        return len(self.refine_angles_deg)

    def physical_values(self) -> dict[str, float]:
        """The init-only physical values: {"closing_force": N, "finger_friction": coefficient}."""
        return {name: getattr(self, name) for name in PHYSICAL_VALUES}

    def _geometry(self) -> tuple:
        return tuple(getattr(self, f.name) for f in dataclasses.fields(self))

    def _changed_physical_values(self) -> tuple[tuple[str, float], ...]:
        """(name, value) of the physical values that differ from their defaults, in PHYSICAL_VALUES order."""
        return tuple((name, getattr(self, name)) for name, default in PHYSICAL_VALUES.items() if getattr(self, name) != default)

    # Written out (dataclasses would compare, hash and print the fields only): with default physical
    # values each is exactly what the dataclass generated before they existed.
    def __eq__(self, other):
        if other.__class__ is not self.__class__:
            return NotImplemented
        return self._geometry() == other._geometry() and self.physical_values() == other.physical_values()

    def __hash__(self):
        changed = self._changed_physical_values()
        return hash(self._geometry() + changed) if changed else hash(self._geometry())

    def __repr__(self):
        parts = [f"{f.name}={getattr(self, f.name)!r}" for f in dataclasses.fields(self) if f.repr]
        parts += [f"{name}={value!r}" for name, value in self._changed_physical_values()]
        return f"{self.__class__.__qualname__}({', '.join(parts)})"


# The Franka Emika Panda hand as boxes, measured on the meshes Contact-GraspNet trains with (cgn-pytorch
# 0.4.3's gripper/mesh/panda_gripper: hand.stl 0.204 x 0.063 m across, 0.058 m from its base to the
# fingers' base, its y extent tapering 0.062 -> 0.036 m towards the fingers; finger.stl 0.054 m long,
# 0.021 m wide, 0.026 -> 0.015 m thick towards the tip). Middle values where the mesh tapers; the
# wrist and arm behind the hand are not modelled. Same stroke (8 cm) as the default GripperSpec, whose
# palm (10 x 3 x 2 cm) and fingers (1 cm thick) are smaller: for replaying a grasp with a Panda hand.
PANDA_HAND = GripperSpec(
    max_opening=0.08,
    finger_length=0.0538,
    finger_width=0.021,
    finger_thickness=0.02,
    palm_size=(0.204, 0.05, 0.058),
)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Box:
    """Oriented boxes; every field may carry the same leading batch axes [...].

    centre: [..., 3] in the world frame.
    rotation: [..., 3, 3] box axes as columns, in the world frame.
    half_extents: [..., 3] along the box axes.
    """

    centre: jax.Array
    rotation: jax.Array
    half_extents: jax.Array

    def __getitem__(self, index) -> Box:
        return jax.tree_util.tree_map(lambda x: x[index], self)


# ---------------------------------------------------------------------------------------------
# Shape checks (static shapes, so they run at trace time).


def _points(points, name: str = "points") -> jax.Array:
    points = jnp.asarray(points)
    if points.ndim < 2 or points.shape[-1] != 3:
        raise ValueError(f"{name} must have shape [..., N, 3], got {points.shape}")
    return points


def _pose(pose) -> jax.Array:
    pose = jnp.asarray(pose)
    if pose.ndim < 2 or pose.shape[-2:] != (4, 4):
        raise ValueError(f"pose must have shape [..., 4, 4], got {pose.shape}")
    return pose


def _width(width, pose: jax.Array) -> jax.Array:
    width = jnp.asarray(width, pose.dtype if jnp.issubdtype(pose.dtype, jnp.floating) else jnp.float32)
    try:
        np.broadcast_shapes(width.shape, pose.shape[:-2])
    except ValueError:
        raise ValueError(
            f"width of shape {width.shape} does not broadcast with the pose batch {pose.shape[:-2]} "
            f"(pose has shape {pose.shape})"
        ) from None
    return width


def _mask(mask, points: jax.Array) -> jax.Array:
    if mask is None:
        return jnp.ones(points.shape[:-1], bool)
    mask = jnp.asarray(mask, bool)
    n = points.shape[-2]
    if mask.ndim < 1 or mask.shape[-1] != n:
        raise ValueError(f"mask must have shape [..., N] with N={n} (points {points.shape}), got {mask.shape}")
    try:
        np.broadcast_shapes(mask.shape, points.shape[:-1])
    except ValueError:
        raise ValueError(f"mask of shape {mask.shape} does not broadcast with points {points.shape}") from None
    return mask


def width_in_range(width: jax.Array, spec: GripperSpec) -> jax.Array:
    """Whether each width lies in [0, spec.max_opening] (False for NaN): [...] -> bool[...]."""
    width = jnp.asarray(width)
    return (width >= 0.0) & (width <= spec.max_opening)


def check_width(width, spec: GripperSpec) -> np.ndarray:
    """Host-side check that every width is finite and within [0, max_opening]; returns it as float64.

    Raises ValueError naming the first offending value and its index.
    """
    w = np.asarray(width, np.float64)
    bad = ~((w >= 0.0) & (w <= spec.max_opening))
    if bad.any():
        index = tuple(int(i) for i in np.argwhere(bad)[0])
        value = w[index] if w.ndim else w
        raise ValueError(
            f"gripper width must be within [0, {spec.max_opening}] m (spec.max_opening); "
            f"got {float(value)} at index {index} ({int(bad.sum())} of {w.size} out of range)"
        )
    return w


# ---------------------------------------------------------------------------------------------
# Frames and poses.


def to_world(points_local: jax.Array, pose: jax.Array) -> jax.Array:
    """Gripper-frame points[..., N, 3] -> world [..., N, 3] (p_w = R p_g + t)."""
    points_local, pose = _points(points_local, "points_local"), _pose(pose)
    rotation, translation = pose[..., :3, :3], pose[..., :3, 3]
    return points_from_frame(points_local, rotation, translation)


def to_gripper_frame(points_world: jax.Array, pose: jax.Array) -> jax.Array:
    """World points[..., N, 3] -> gripper-frame [..., N, 3] (p_g = R^T (p_w - t))."""
    points_world, pose = _points(points_world, "points_world"), _pose(pose)
    rotation, translation = pose[..., :3, :3], pose[..., :3, 3]
    return points_to_frame(points_world, rotation, translation)


def deepened_pose(pose: jax.Array, spec: GripperSpec) -> jax.Array:
    """The pose moved by spec.deepen along its own approach axis (+z): [..., 4, 4] -> [..., 4, 4]."""
    pose = _pose(pose)
    return pose.at[..., :3, 3].add(spec.deepen * pose[..., :3, 2])


def rotated_about_approach(pose: jax.Array, angle: jax.Array | float) -> jax.Array:
    """The pose turned by `angle` radians about its own z axis through its origin.

    pose[..., 4, 4], angle broadcastable to the pose batch -> [..., 4, 4].
    """
    pose = _pose(pose)
    rotation = pose[..., :3, :3] @ rot_z(jnp.asarray(angle, pose.dtype))
    pose = jnp.broadcast_to(pose, (*rotation.shape[:-2], 4, 4))  # the angles may add batch axes
    return pose.at[..., :3, :3].set(rotation)


def refined_pose(pose: jax.Array, variant: jax.Array | int, spec: GripperSpec) -> jax.Array:
    """Refinement `variant` of a grasp pose: deepen, then rotate by spec.refine_angles_deg[variant].

    With the default spec variant 0 is -15 deg, 1 is 0 deg (deepened only), 2 is +15 deg.
    pose[..., 4, 4], variant int or int array broadcastable to the pose batch -> [..., 4, 4].
    """
    if isinstance(variant, (int, np.integer)) and not 0 <= variant < spec.num_refinements:
        raise ValueError(f"variant must be in [0, {spec.num_refinements}), got {variant}")
    angles = jnp.deg2rad(jnp.asarray(spec.refine_angles_deg, jnp.float32))
    return rotated_about_approach(deepened_pose(pose, spec), angles[jnp.asarray(variant)])


def perturbed_poses(pose: jax.Array, shift: float, angle_deg: float) -> jax.Array:
    """Small perturbations of a grasp pose, for judging how robust a score is to where exactly the hand
    lands: pose[..., 4, 4] -> [..., 5, 4, 4], in the pose's own frame: moved by -shift and +shift along
    the finger width (y), backed out by `shift` along the approach (-z), and turned by -angle_deg and
    +angle_deg about the approach axis. The pose itself is not among them."""
    pose = _pose(pose)
    y, z = pose[..., :3, 1], pose[..., :3, 2]
    moved = [pose.at[..., :3, 3].add(offset) for offset in (-shift * y, shift * y, -shift * z)]
    turned = [rotated_about_approach(pose, sign * jnp.deg2rad(angle_deg)) for sign in (-1.0, 1.0)]
    return jnp.stack(moved + turned, axis=-3)


def refined_poses(pose: jax.Array, spec: GripperSpec) -> jax.Array:
    """All refinement variants: pose[..., 4, 4] -> [..., K, 4, 4] with K = spec.num_refinements."""
    deep = deepened_pose(pose, spec)[..., None, :, :]
    angles = jnp.deg2rad(jnp.asarray(spec.refine_angles_deg, deep.dtype))
    return rotated_about_approach(deep, angles)


def enlarged_region_poses(pose: jax.Array, spec: GripperSpec) -> jax.Array:
    """Poses whose closing regions make up the enlarged region (paper Sec. IV-C).

    pose[..., 4, 4] -> [..., 1 + K, 4, 4]: index 0 is the initial pose and index 1 + v is
    `refined_pose(pose, v, spec)` (default: initial, deepened -15 deg, deepened, deepened +15 deg).
    """
    pose = _pose(pose)
    return jnp.concatenate([pose[..., None, :, :], refined_poses(pose, spec)], axis=-3)


# ---------------------------------------------------------------------------------------------
# Regions and boxes.


def closing_region(spec: GripperSpec, width: jax.Array | float) -> tuple[jax.Array, jax.Array]:
    """The closing region in the gripper frame: width[...] -> (centre[..., 3], half_extents[..., 3])."""
    width = jnp.asarray(width, jnp.float32)
    half_w = 0.5 * width
    zero = jnp.zeros_like(half_w)
    half_l = jnp.full_like(half_w, 0.5 * spec.finger_length)
    centre = jnp.stack([zero, zero, half_l], -1)
    half = jnp.stack([half_w, jnp.full_like(half_w, 0.5 * spec.finger_width), half_l], -1)
    return centre, half


def _posed_box(pose: jax.Array, centre_local: jax.Array, half_extents: jax.Array) -> Box:
    """Boxes given in the gripper frame (centre_local, half_extents [..., 3]) placed by pose[..., 4, 4]."""
    rotation, translation = pose[..., :3, :3], pose[..., :3, 3]
    centre = jnp.einsum("...ij,...j->...i", rotation, centre_local) + translation
    batch = jnp.broadcast_shapes(centre.shape[:-1], half_extents.shape[:-1])
    return Box(
        jnp.broadcast_to(centre, (*batch, 3)),
        jnp.broadcast_to(rotation, (*batch, 3, 3)),
        jnp.broadcast_to(half_extents, (*batch, 3)),
    )


def closing_region_box(pose: jax.Array, width: jax.Array | float, spec: GripperSpec) -> Box:
    """The closing region of grasps (pose[..., 4, 4], width[...]) as world-frame boxes [...]."""
    pose = _pose(pose)
    centre, half = closing_region(spec, _width(width, pose))
    return _posed_box(pose, centre.astype(pose.dtype), half.astype(pose.dtype))


def gripper_boxes(pose: jax.Array, width: jax.Array | float, spec: GripperSpec) -> Box:
    """The gripper's collision boxes in the world frame: Box with batch [..., 3].

    Along the new axis: left finger (-x), right finger (+x), palm. The fingers sit just outside the
    closing region, centred at x = -+(width/2 + finger_thickness/2), 0 <= z <= finger_length; the
    palm lies behind the origin, -palm_size[2] <= z <= 0.
    """
    pose = _pose(pose)
    width = _width(width, pose)
    finger_x = 0.5 * width + 0.5 * spec.finger_thickness
    zero, one = jnp.zeros_like(finger_x), jnp.ones_like(finger_x)
    mid_z = 0.5 * spec.finger_length * one
    palm_z = -0.5 * spec.palm_size[2] * one
    centres = jnp.stack(
        [
            jnp.stack([-finger_x, zero, mid_z], -1),
            jnp.stack([finger_x, zero, mid_z], -1),
            jnp.stack([zero, zero, palm_z], -1),
        ],
        -2,
    )
    finger_half = [0.5 * spec.finger_thickness, 0.5 * spec.finger_width, 0.5 * spec.finger_length]
    palm_half = [0.5 * s for s in spec.palm_size]
    halves = jnp.asarray([finger_half, finger_half, palm_half], pose.dtype)
    return _posed_box(pose[..., None, :, :], centres, halves)


def local_regions(
    local: jax.Array, width: jax.Array | float, spec: GripperSpec, margin: float = 0.0, sweep: float = 0.0
) -> tuple[jax.Array, jax.Array]:
    """Region membership of gripper-frame points, without re-transforming them per box.

    local[..., N, 3] (e.g. from `to_gripper_frame`), width broadcastable to [...] ->
    (in_closing_region bool[..., N], in_fingers_or_palm bool[..., N]). The same boxes as
    `closing_region_box` and `gripper_boxes` (the latter grown by `margin`). sweep >= 0: the fingers and
    palm swept back by that much along -z, i.e. every position of the open hand on the straight approach
    over the last `sweep` metres (the closing region is not swept).
    """
    local = _points(local, "local")
    xyz = (local[..., 0], local[..., 1], local[..., 2])
    width = jnp.asarray(width, local.dtype)[..., None]
    closing = in_box(*xyz, closing_box(spec, width))
    right, left, palm = hand_boxes(spec, width, margin, sweep)
    return closing, in_box(*xyz, right) | in_box(*xyz, left) | in_box(*xyz, palm)


# One description of the gripper's regions: axis-aligned boxes in the gripper frame, (lo, hi) per axis,
# each bound a number or an array that broadcasts with the coordinates. Every region test builds its
# bounds here, so that a point on a face is inside or outside for all of them alike.
AxisBox = tuple[tuple, tuple]


def closing_box(spec: GripperSpec, width) -> AxisBox:
    """The closing region of `width`: |x| <= w/2, |y| <= finger_width/2, 0 <= z <= finger_length."""
    half_w = 0.5 * width
    fy = 0.5 * spec.finger_width
    return (-half_w, -fy, 0.0), (half_w, fy, spec.finger_length)


def hand_boxes(spec: GripperSpec, width, margin: float = 0.0, sweep: float = 0.0) -> tuple[AxisBox, AxisBox, AxisBox]:
    """The right finger (+x), left finger (-x) and palm of the hand open to `width`, grown by `margin`
    and swept back by `sweep` along -z (the straight approach's last `sweep` metres)."""
    half_w = 0.5 * width
    fy = 0.5 * spec.finger_width
    fx0, fx1 = half_w - margin, half_w + spec.finger_thickness + margin
    fz0, fz1 = -margin - sweep, spec.finger_length + margin
    right = (fx0, -fy - margin, fz0), (fx1, fy + margin, fz1)
    left = (-fx1, -fy - margin, fz0), (-fx0, fy + margin, fz1)
    px, py = (0.5 * s + margin for s in spec.palm_size[:2])
    palm = (-px, -py, -spec.palm_size[2] - margin - sweep), (px, py, margin)
    return right, left, palm


def hand_samples(spec: GripperSpec, width, sweep: float = 0.0, step: float = 0.005) -> jax.Array:
    """Points filling the open hand (`hand_boxes`: both fingers and the palm, swept back by `sweep` along
    -z), gripper frame: width [...] -> [..., P, 3], a grid on each box with spacing <= `step` along
    every axis, its faces included. P depends on the spec, sweep and step only (the width moves or
    stretches the grids, it does not resize them), so a batch of widths has one shape."""
    if not step > 0.0:
        raise ValueError(f"step must be > 0 metres, got {step}")
    w = jnp.asarray(width, jnp.float32)[..., None]  # [..., 1]
    # (box at this width, box that sets the grid's counts): a finger keeps its size at any width.
    boxes = list(zip(hand_boxes(spec, w, 0.0, sweep), hand_boxes(spec, 0.0, 0.0, sweep)))
    parts = []
    for (lo, hi), (lo0, hi0) in boxes:
        counts = [max(2, int(np.ceil((b - a) / step - 1e-6)) + 1) for a, b in zip(lo0, hi0)]
        unit = np.stack(np.meshgrid(*(np.linspace(0.0, 1.0, c) for c in counts), indexing="ij"), -1).reshape(-1, 3)
        corner = lambda v: jnp.stack(jnp.broadcast_arrays(*(jnp.asarray(c, jnp.float32) for c in v), w), -1)[..., :3]
        lo_, hi_ = corner(lo), corner(hi)  # [..., 1, 3]
        parts.append(lo_ + jnp.asarray(unit, jnp.float32) * (hi_ - lo_))
    return jnp.concatenate(parts, -2)


def in_box(x: jax.Array, y: jax.Array, z: jax.Array, box: AxisBox) -> jax.Array:
    """The one point-in-region test: gripper-frame coordinates x, y, z (equal or broadcasting shapes)
    inside the closed box (lo, hi) -> bool. NaN coordinates are never inside."""
    lo, hi = box
    return (x >= lo[0]) & (x <= hi[0]) & (y >= lo[1]) & (y <= hi[1]) & (z >= lo[2]) & (z <= hi[2])


def _segments_hit_box(start, inv_direction, length, lo, hi) -> jax.Array:
    """Slab test: segments start + t * direction, 0 <= t <= length, against axis-aligned boxes [lo, hi].

    start, inv_direction: per-axis sequences of 3 arrays [...] (1 / direction); length, lo, hi: per-axis
    bounds broadcastable to [...] -> bool [...]. Per-axis arrays, not [..., 3], so that XLA fuses the
    whole test into one loop over the candidate x point pairs (20x faster on CPU than reducing a last
    axis of 3)."""
    enter, leave = 0.0, length
    for a in range(3):
        t1, t2 = (lo[a] - start[a]) * inv_direction[a], (hi[a] - start[a]) * inv_direction[a]
        enter = jnp.maximum(enter, jnp.minimum(t1, t2))
        leave = jnp.minimum(leave, jnp.maximum(t1, t2))
    return enter <= leave


def segment_regions(
    local: jax.Array,
    direction: jax.Array,
    length: float,
    width: jax.Array | float,
    spec: GripperSpec,
    margin: float = 0.0,
    sweep: float = 0.0,
) -> tuple[jax.Array, jax.Array]:
    """`local_regions` for segments instead of points: each gripper-frame point extended by `length`
    along its unit `direction` (e.g. the camera ray behind an observed point: space the camera cannot
    see, which may be occupied).

    local, direction [..., N, 3]; width broadcastable to [...] -> (segment meets the closing region
    bool[..., N], segment meets a finger or the palm bool[..., N]), the boxes exactly as in
    `local_regions` (length 0 gives its point test).
    """
    local = _points(local, "local")
    start = [local[..., a] for a in range(3)]
    # A zero component becomes a tiny one of the same sign: its slab then gives t of +-huge, i.e. the
    # whole line inside (start within the slab) or nowhere (start outside it).
    tiny = 1e-12
    inv = [1.0 / jnp.where(jnp.abs(d) < tiny, jnp.where(d < 0, -tiny, tiny), d) for d in (direction[..., a] for a in range(3))]
    hit = lambda box: _segments_hit_box(start, inv, length, *box)
    width = jnp.asarray(width, local.dtype)[..., None]  # [..., 1]
    right, left, palm = hand_boxes(spec, width, margin, sweep)
    return hit(closing_box(spec, width)), hit(left) | hit(right) | hit(palm)


def finger_stops(local, spec: GripperSpec, valid=None, xp=jnp):
    """The paper's width rule in the gripper frame: a finger face sweeping along x from fully open stops
    where its Euclidean distance to some point reaches delta (`spec.contact_threshold`).

    local [..., S, 3] gripper-frame points, valid [..., S] or None; xp: the array module (jnp, or np for
    the host-side database build). Returns (left, right) [...]: how far from the origin the left face
    (at -x) and the right face (at +x) stop; -inf where no point comes within delta of that face. Closing
    symmetrically, the first face to stop sets the width: 2 * max(left, right).
    """
    x, y, z = local[..., 0], local[..., 1], local[..., 2]
    delta = spec.contact_threshold
    dy = xp.maximum(xp.abs(y) - 0.5 * spec.finger_width, 0.0)
    dz = xp.maximum(xp.maximum(-z, z - spec.finger_length), 0.0)
    lateral2 = dy**2 + dz**2
    near = lateral2 < delta**2
    if valid is not None:
        near = near & valid
    dx = xp.sqrt(xp.maximum(delta**2 - lateral2, 0.0))
    left = xp.max(xp.where(near, dx - x, -xp.inf), axis=-1)
    right = xp.max(xp.where(near, x + dx, -xp.inf), axis=-1)
    return left, right


def adapt_to_cloud(local, valid, poses, widths, spec: GripperSpec, max_shift: float = 0.005):
    """Transferred grasps adapted to the observed object by the paper's width rule (`finger_stops`).

    A matched primitive of another size or a slightly shifted fit leaves the fingers off-centre: each
    grasp moves along its closing axis (by at most max_shift) to centre the observed points between the
    faces' stops, and opens to the width the rule gives there, never below the transferred width (which
    carries the fitted superquadric's estimate of the hidden side), capped at the maximum opening.
    Grasps whose observed points would need more than the maximum opening, or with no observed point
    near a finger, are left as transferred: filters (i) and (ii) judge them.

    local [M, N, 3] object points in each grasp frame, valid [N], poses [M, 4, 4], widths [M]
    -> (poses [M, 4, 4], widths [M]). `recentre_and_widen` gives the shift instead of the moved poses.
    """
    shift, widths = recentre_and_widen(local, valid, widths, spec, max_shift)
    return poses.at[:, :3, 3].add(shift[:, None] * poses[:, :3, 0]), widths


def recentre_and_widen(local, valid, widths, spec: GripperSpec, max_shift: float = 0.005):
    """The rule of `adapt_to_cloud` in the grasp frames: local [M, N, 3], valid [N], widths [M] ->
    (shift [M]: how far each grasp moves along its own closing axis x, widths [M]). Moving a grasp by
    `shift` moves its gripper-frame points by -shift along x."""
    left, right = finger_stops(local, spec, valid[None, :])
    # Only where the observed points fit between the open fingers; elsewhere filter (i) or (ii) decides.
    seen = jnp.isfinite(left) & jnp.isfinite(right)
    shift = jnp.where(seen, jnp.clip(0.5 * (right - left), -max_shift, max_shift), 0.0)
    observed = 2.0 * jnp.maximum(left + shift, right - shift)
    fits = seen & (observed <= spec.max_opening)
    shift = jnp.where(fits, shift, 0.0)
    widths = jnp.where(fits, jnp.minimum(jnp.maximum(widths, observed), spec.max_opening), widths)
    return shift, widths


def lowest_height(pose: jax.Array, width: jax.Array | float, spec: GripperSpec, plane) -> jax.Array:
    """Height above a plane of the lowest corner of the gripper boxes (fingers and palm):
    pose [..., 4, 4], width [...], plane [4] (n, d: the plane n . x + d = 0, n a unit normal) -> [...]."""
    boxes = gripper_boxes(pose, width, spec)  # [..., 3]
    plane = jnp.asarray(plane, boxes.centre.dtype)
    normal, offset = plane[:3], plane[3]
    reach = jnp.sum(jnp.abs(jnp.einsum("i,...bij->...bj", normal, boxes.rotation)) * boxes.half_extents, -1)
    return jnp.min(boxes.centre @ normal + offset - reach, -1)


def closing_centre(poses, spec: GripperSpec, xp=jnp):
    """The closing region's centre (the origin moved finger_length / 2 along the approach z):
    poses [..., 4, 4] -> [..., 3]. xp: jnp, or np on the host."""
    poses = xp.asarray(poses)
    return poses[..., :3, 3] + 0.5 * spec.finger_length * poses[..., :3, 2]


# A grasp this close to one that failed is the same grasp: the closing-region centres within
# AVOID_DISTANCE and the hands within AVOID_ANGLE_DEG of each other (the decluttering harness's memory).
AVOID_DISTANCE = 0.01
AVOID_ANGLE_DEG = 15.0


def near_grasps(poses, others, spec: GripperSpec, max_distance: float = AVOID_DISTANCE,
                max_angle_deg: float = AVOID_ANGLE_DEG, xp=jnp):
    """Whether each grasp is (nearly) the same as one of `others`: poses [K, 4, 4], others [F, 4, 4] -> bool[K].

    Same: the closing-region centres (origin + finger_length / 2 along z) are at most `max_distance`
    apart and the rotation between the two hands is at most `max_angle_deg`, counting a hand turned
    180 deg about its approach axis as the same hand (the parallel jaw is symmetric). F = 0: all False.
    xp: jnp, or np for host-side callers with varying F (no compile per shape).
    """
    poses, others = xp.asarray(poses), xp.asarray(others)
    if poses.ndim != 3 or poses.shape[-2:] != (4, 4) or others.ndim != 3 or others.shape[-2:] != (4, 4):
        raise ValueError(f"poses and others must have shapes [K, 4, 4] and [F, 4, 4], got {poses.shape} and {others.shape}")
    centre = lambda p: closing_centre(p, spec, xp)
    close = xp.linalg.norm(centre(poses)[:, None] - centre(others)[None], axis=-1) <= max_distance + 1e-9
    dots = xp.einsum("kia,fia->kfa", poses[:, :3, :3], others[:, :3, :3])  # axis-by-axis cosines [K, F, 3]
    # Normalised by the rotations' norms (sqrt(3) each when exactly orthonormal): float32 poses are
    # orthonormal only to ~1e-7 per entry, which moves the trace of the same pose by ~1e-6 and would fail
    # a tolerance of a hundredth of a degree (cos 0.01 deg = 1 - 1.5e-8).
    norm = lambda r: xp.sqrt(xp.sum(r * r, axis=(-2, -1)) / 3.0)
    dots = dots / (norm(poses[:, :3, :3])[:, None, None] * norm(others[:, :3, :3])[None, :, None])
    trace = xp.maximum(dots.sum(-1), dots[..., 2] - dots[..., 0] - dots[..., 1])  # R or R turned 180 deg about z
    aligned = 0.5 * (trace - 1.0) >= np.cos(np.deg2rad(max_angle_deg)) - 1e-6
    return xp.any(close & aligned, axis=-1)


def points_in_box(points: jax.Array, box: Box, margin: float = 0.0) -> jax.Array:
    """Whether points[..., N, 3] lie in the closed boxes [...] grown by `margin` -> bool[..., N]."""
    points = _points(points)
    local = points_to_frame(points, box.rotation, box.centre)
    return jnp.all(jnp.abs(local) <= box.half_extents[..., None, :] + margin, axis=-1)


def points_in_closing_region(
    points: jax.Array, pose: jax.Array, width: jax.Array | float, spec: GripperSpec
) -> jax.Array:
    """Whether world points[..., N, 3] lie in the closing region of (pose[..., 4, 4], width[...]).

    Batch axes broadcast, e.g. one cloud [N, 3] against B grasps gives bool[B, N].
    """
    points, pose = _points(points), _pose(pose)
    local = to_gripper_frame(points, pose)
    width = _width(width, pose).astype(local.dtype)[..., None]
    return in_box(local[..., 0], local[..., 1], local[..., 2], closing_box(spec, width))


def points_in_enlarged_region(
    points: jax.Array, pose: jax.Array, width: jax.Array | float, spec: GripperSpec
) -> jax.Array:
    """Whether world points[..., N, 3] lie in the enlarged region of (pose[..., 4, 4], width[...]).

    The enlarged region is the union of the closing regions of `enlarged_region_poses`; -> bool[..., N].
    """
    points, pose = _points(points), _pose(pose)
    width = _width(width, pose)
    inside = points_in_closing_region(points[..., None, :, :], enlarged_region_poses(pose, spec), width[..., None], spec)
    return jnp.any(inside, axis=-2)


def collides_with_points(
    points: jax.Array,
    mask: jax.Array | None,
    pose: jax.Array,
    width: jax.Array | float,
    spec: GripperSpec,
    margin: float = 0.0,
) -> jax.Array:
    """Whether any masked point[..., N, 3] lies in a finger or the palm (boxes grown by margin) -> bool[...].

    mask[..., N] marks the valid points (None: all); points between the fingers do not collide.
    """
    points = _points(points)
    mask = _mask(mask, points)
    pose = _pose(pose)
    boxes = gripper_boxes(pose, width, spec)
    inside = jnp.any(points_in_box(points[..., None, :, :], boxes, margin), axis=-2)
    return jnp.any(inside & mask, axis=-1)
