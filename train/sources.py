"""Where labelled grasps come from: the candidate sources of a labelled scene (issue "Stage 2, part 1").

E-RNet must judge any candidate the planner may hand it, including the ones Stage 1's extra filters
would have removed. Each labelled scene therefore mixes grasps from several sources, and every sample
records its source (`SOURCES`, stored as its index); `sgjax label` draws these (`DRAWN`):

  stage1        Stage 1 as the planner runs it (all filters; the scene cloud for filter (iv)).
  stage1_paper  Stage 1 with only the paper's three filters (i)-(iii) plus the table (v): no scene
                collision test, no camera-ray shadows or obstacle margin, hidden contacts accepted. What
                the extra filters remove is labelled instead of never being seen.
  gpd           GPD-style antipodal samples on the target (`sgjax.samplers.gpd`), every neighbour an
                obstacle, picked at random among the kept ones (not the best-ranked: a spread of quality).
  perturbed     grasps of the sources above moved by 0.5-2 cm and turned by 5-20 deg about the centre
                of the closing region: near misses and hard negatives.

Two more codes name the samples of directories labelled by earlier versions, so that those stay readable
and their per-source judgement keeps its rows: stage1_relabel (Stage 1 with matches of the fit's other
axis labellings appended, only those matches' grasps) and finalist (the planner's finalists on replayed
benchmark states). Neither is drawn any more (docs/experiments.md).

Everything here is host-side NumPy around jitted, fixed-shape JAX calls (one compile per config).
"""

from __future__ import annotations

import dataclasses

import jax
import numpy as np

from sgjax.geometry.gripper import GripperSpec
from sgjax.samplers import gpd as gpd_sampler
from sgjax.stage1.pipeline import Stage1Config

# Appended only: a stored code is an index into this tuple, so older label directories stay readable.
SOURCES = ("stage1", "stage1_paper", "gpd", "perturbed", "stage1_relabel", "finalist")
# The sources `sgjax label` can draw; the others only name samples of directories labelled before.
DRAWN = ("stage1", "stage1_paper", "gpd", "perturbed")


def source_index(name: str) -> int:
    """The stored code of a source name (its index in SOURCES); ValueError names the known ones."""
    if name not in SOURCES:
        raise ValueError(f"unknown candidate source {name!r}; known: {', '.join(SOURCES)}")
    return SOURCES.index(name)


def paper_filters(config: Stage1Config) -> Stage1Config:
    """`config` with only the paper's coarse filters (i)-(iii) and the table (v) judging candidates.

    Filter (iv) is off because this source is run without a scene cloud; its shadow and margin settings
    are zeroed too, and a finger whose contact face is hidden is not held against the grasp."""
    relaxed = dataclasses.replace(config.filter, hidden_contacts="accept", shadow_depth=0.0, obstacle_margin=0.0)
    return dataclasses.replace(config, filter=relaxed)


@dataclasses.dataclass(frozen=True)
class Perturbation:
    """Ranges of the perturbed source: a translation of uniform length in [translation] (m) in a uniform
    direction, then a rotation of uniform angle in [angle_deg] about a uniform axis through the centre of
    the closing region."""

    translation: tuple[float, float] = (0.005, 0.02)
    angle_deg: tuple[float, float] = (5.0, 20.0)

    def __post_init__(self):
        for name in ("translation", "angle_deg"):
            lo, hi = getattr(self, name)
            if not 0.0 <= lo <= hi:
                raise ValueError(f"Perturbation.{name} must be (lo, hi) with 0 <= lo <= hi, got {(lo, hi)}")
            object.__setattr__(self, name, (float(lo), float(hi)))


def _unit(rng: np.random.Generator, n: int) -> np.ndarray:
    v = rng.normal(size=(n, 3))
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _axis_angle(axis: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """Rotation matrices [n, 3, 3] of unit axes [n, 3] and angles [n] (Rodrigues)."""
    k = np.zeros((len(axis), 3, 3))
    k[:, 0, 1], k[:, 0, 2], k[:, 1, 2] = -axis[:, 2], axis[:, 1], -axis[:, 0]
    k = k - k.transpose(0, 2, 1)
    s, c = np.sin(angle)[:, None, None], np.cos(angle)[:, None, None]
    return np.eye(3) + s * k + (1.0 - c) * (k @ k)


def perturb(poses: np.ndarray, rng: np.random.Generator, spec: GripperSpec, ranges: Perturbation = Perturbation()) -> np.ndarray:
    """poses [n, 4, 4] -> perturbed copies [n, 4, 4] (float64), each turned about its closing region's
    centre (0, 0, finger_length / 2 in the gripper frame) and moved, by amounts drawn from `ranges`."""
    poses = np.asarray(poses, np.float64)
    n = len(poses)
    if n == 0:
        return poses.reshape(0, 4, 4)
    turn = _axis_angle(_unit(rng, n), np.deg2rad(rng.uniform(*ranges.angle_deg, n)))
    shift = _unit(rng, n) * rng.uniform(*ranges.translation, n)[:, None]
    rotation, origin = poses[:, :3, :3], poses[:, :3, 3]
    centre = origin + rotation[:, :, 2] * (0.5 * spec.finger_length)
    out = poses.copy()
    out[:, :3, :3] = turn @ rotation
    out[:, :3, 3] = centre + shift - (turn @ rotation)[:, :, 2] * (0.5 * spec.finger_length)
    return out


def gpd_candidates(
    points: np.ndarray,
    labels: np.ndarray,
    targets: list[int],
    viewpoint: np.ndarray,
    seed: int,
    config: gpd_sampler.GPDConfig,
    margin: float = 0.12,
) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """GPD-style candidates on each target of an observed scene: {target: (poses [k, 4, 4], widths [k])},
    the kept ones (collision-free with every observed object and the table, enough points between the
    fingers), in sampling order. points [P, 3] world, labels [P] (object index, < 0 table); margin: the
    neighbourhood of the target's box (m) whose objects count as obstacles (beyond a hand's reach)."""
    points = np.asarray(points, np.float32).reshape(-1, 3)
    labels = np.asarray(labels).reshape(-1)
    view = np.asarray(viewpoint, np.float32).reshape(3)
    m = config.num_samples * config.num_angles
    out = {}
    for i, target in enumerate(targets):
        own = points[labels == target]
        if len(own):
            # Only points within reach of a hand on the target can collide with it: the sampler (its
            # normals are a kNN over every point) works on that neighbourhood and the table's points.
            lo, hi = own.min(0) - margin, own.max(0) + margin
            near = (labels < 0) | np.all((points >= lo) & (points <= hi), axis=1)
        else:
            near = np.zeros(len(points), bool)
        cloud, mask, table_z, _, cloud_labels = gpd_sampler.prepare_labelled_cloud(points[near], labels[near], config, seed)
        on_target = cloud_labels == target
        if not on_target.any():
            out[target] = (np.zeros((0, 4, 4)), np.zeros(0))
            continue
        key = jax.random.fold_in(jax.random.key(seed), i)
        sampled = gpd_sampler.candidates(cloud, mask, view, np.float32(table_z), key, config, sample_mask=on_target)
        found = gpd_sampler.evaluate(
            sampled["poses"].reshape(m, 4, 4), sampled["valid"].reshape(m), cloud, mask, sampled["normals"],
            np.float32(table_z), config,
        )
        keep = np.asarray(found["valid"])
        out[target] = (np.asarray(found["poses"], np.float64)[keep], np.asarray(found["widths"], np.float64)[keep])
    return out
