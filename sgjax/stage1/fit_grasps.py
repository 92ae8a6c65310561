"""Top-down grasps on the fitted superquadric itself, beside the transferred templates.

Stage 1 offers an object only the template grasps of the K2 primitives its fit matches. When the
single-view fit names its axes so that the database's matching shape ranks low (a flat lens-like object
lying on the table: docs/benchmark.md), none of those templates closes where the object can be held,
although the fit knows its size and where it lies. These grasps come from the fit directly: straight
down along the support plane's normal, closing across each of the fit's two horizontal axes (optionally
also turned about the normal, `FitGraspConfig.yaws_deg`), centred on the fit, with the fingertips between the table and the fit's centre, i.e.
below the widest section of a rounded or pinched object, where a squeeze presses it onto the table
instead of pushing it out of the fingers. They go through the same width adaptation and coarse filters
as the transferred grasps, and E-RNet judges them.

The planner offers them in both its plans by default (`PlannerConfig.fit_grasps`); Stage 1 alone does
not (`Stage1Config.fit_grasps` None: the paper's candidates). Pure JAX, fixed shapes; nothing raises
inside jit.
"""

from __future__ import annotations

import dataclasses
from typing import ClassVar

import jax
import jax.numpy as jnp
import numpy as np

from sgjax.geometry.gripper import GripperSpec
from sgjax.geometry.rotations import so3_exp
from sgjax.geometry.superquadric import Superquadric


@dataclasses.dataclass(frozen=True)
class FitGraspConfig:
    """Which grasps on the fit (hashable: part of `Stage1Config`).

    yaws_deg: rotations of each horizontal axis about the plane's normal (0: across the axis itself).
        Default straight across only: on the lone lens-like object the grasps 0-10 deg off its short
        axis held 90 % of the time and 10-20 deg off 62 %, and in dense clutter of unseen objects, on
        identical states, the ±15 deg turns E-RNet chose failed where the straight grasp held (28 failures
        became successes and 7 successes failures over 1,434 states; docs/benchmark.md).
    heights: fingertip heights as fractions of the fit centre's height above the support plane (0.5:
        halfway between the table and the centre, below a rounded object's widest section).
    min_clearance: the fingertips stay at least this far above the plane (metres).
    palm_clearance: and at most `finger_length - palm_clearance` below the fit's top, so that on a tall
        object the palm stays above it (metres).
    min_margin: a direction across which the fit is wider than `max_opening - min_margin` gets no grasp.
    normal_test: whether the coarse filter's normal test (iii) applies to them. Off by default: they close
        through the fit's centre across its axis, antipodal on the fit by construction, and below a
        rounded or pinched object's widest section, where the observed normals tilt away from the
        closing axis (on a lens-like object lying flat the test removes every grasp that holds it).
        The other tests apply.
    """

    yaws_deg: tuple[float, ...] = (0.0,)
    heights: tuple[float, ...] = (0.5,)
    min_clearance: float = 0.003
    palm_clearance: float = 0.005
    min_margin: float = 0.004
    normal_test: bool = False
    # Options measured and not adopted (docs/experiments.md): saved configs holding their old defaults still load.
    RETIRED_FIELDS: ClassVar[dict] = {"first_plan": True}

    def __post_init__(self):
        object.__setattr__(self, "yaws_deg", tuple(float(v) for v in self.yaws_deg))
        object.__setattr__(self, "heights", tuple(float(v) for v in self.heights))
        if not self.yaws_deg or not self.heights:
            raise ValueError("FitGraspConfig needs at least one yaw and one height")
        if any(not 0.0 < h <= 2.0 for h in self.heights):
            raise ValueError(f"heights are fractions of the fit centre's height in (0, 2], got {self.heights}")
        if min(self.min_clearance, self.palm_clearance, self.min_margin) < 0.0:
            raise ValueError("min_clearance, palm_clearance and min_margin must be >= 0")

    @property
    def count(self) -> int:
        """Grasps per object: 2 horizontal axes x yaws x heights."""
        return 2 * len(self.yaws_deg) * len(self.heights)


def fit_top_down_grasps(sq: Superquadric, plane: jax.Array, spec: GripperSpec,
                        cfg: FitGraspConfig) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Top-down grasps on one fitted superquadric (module doc).

    sq: one superquadric (scale [3], epsilon [2], rotation [3, 3], translation [3]); plane [4]: (n, d)
    with free space n . x + d > 0 (a zero normal, `filters.NO_PLANE`: no table, no grasps).
    -> poses [F, 4, 4] (gripper frame -> world), widths [F], valid [F] with F = `cfg.count`, axis-major
    (first horizontal axis: yaws x heights, then the second).
    """
    normal, offset = plane[:3], plane[3]
    has_plane = jnp.linalg.norm(normal) > 0.5
    up = normal / jnp.maximum(jnp.linalg.norm(normal), 1e-9)
    axes = sq.rotation  # columns: the fit's axes in the world frame
    cosines = jnp.abs(axes.T @ up)  # [3]
    vertical = jnp.argmax(cosines)
    # The fit's half-extent along a direction: the support function of the superellipse with the fit's
    # semi-axes and its cross-section exponent eps2 (dual norm q = 2 / (2 - eps2): a box's sum at
    # eps2 -> 0, an ellipsoid's Euclidean norm at 1), exact along the fit's own axes. eps2 shapes the
    # section across the fit's z axis; for a fit lying on its side it stands in for the vertical
    # section's eps1 (only the widths of the yawed grasps use it, and the cloud adapts them after).
    q = 2.0 / (2.0 - jnp.clip(sq.epsilon[1], 0.1, 1.9))
    extent = lambda d: jnp.sum(jnp.abs(sq.scale * (axes.T @ d)) ** q) ** (1.0 / q)
    centre_height = jnp.dot(up, sq.translation) + offset
    top = centre_height + extent(up)
    on_plane = sq.translation - centre_height * up  # the fit's centre dropped onto the table
    poses, widths, valid = [], [], []
    for k in range(2):
        # The k-th of the two axes other than the most vertical one, flattened onto the plane.
        index = jnp.where(vertical <= k, k + 1, k)
        flat = axes[:, index] - jnp.dot(axes[:, index], up) * up
        flat_norm = jnp.linalg.norm(flat)
        flat = flat / jnp.maximum(flat_norm, 1e-9)
        for yaw in cfg.yaws_deg:
            x = so3_exp(up * np.radians(yaw)) @ flat
            across = 2.0 * extent(x)
            width = jnp.minimum(across + 2.0 * spec.contact_threshold, spec.max_opening)
            ok = (has_plane & (flat_norm > 1e-3) & (across <= spec.max_opening - cfg.min_margin)
                  & (centre_height > 0.0) & jnp.all(sq.scale > 0.0))
            rotation = jnp.eye(4).at[:3, 0].set(x).at[:3, 1].set(jnp.cross(-up, x)).at[:3, 2].set(-up)
            for fraction in cfg.heights:
                tips = jnp.maximum(fraction * centre_height, cfg.min_clearance)
                tips = jnp.maximum(tips, top - (spec.finger_length - cfg.palm_clearance))
                poses.append(rotation.at[:3, 3].set(on_plane + (tips + spec.finger_length) * up))
                widths.append(width)
                valid.append(ok)
    return jnp.stack(poses), jnp.stack(widths), jnp.stack(valid)
