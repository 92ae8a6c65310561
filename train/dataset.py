"""E-RNet training samples: the shard format, reading, the scene-level split, batching, synthetic data.

One sample = one executed grasp (paper Sec. IV-C): the scene points of its enlarged region in the
grasp frame, the grasp, the execution label and the three refinement labels. The labelling pipeline
writes shards with `write_shard` (atomic .npz, no pickles); training reads a directory with
`read_shards`. Field names, dtypes and shapes are `SAMPLE_FIELDS`:

    region         float32[P, 3]  scene points in the enlarged region, GRASP frame (padding rows 0)
    region_mask    bool[P]        True for real points (P = REGION_POINTS = 2048)
    pose           float32[4, 4]  the grasp (gripper -> world)
    width          float32[]      gripper opening (m)
    label          int8[]         1: stable grasp (lift, reorient, 1 N disturbance), 0: not
    refine_labels  int8[3]        the same criterion for deepen 0.008 m + rotate -15 / 0 / +15 deg
    scene_seed     int64[]        the scene it came from (the train / held-out split is by scene)
    object_name    str            the target object
    valid          bool[]         False: the trial could not be run (excluded from training)

A shard (compressed .npz) stores each field stacked over its samples ([S, ...]); `object_name` as a
fixed-width unicode array. Regions with more than P points should be randomly subsampled by the writer
(`sgjax.stage2.crops.crop_regions` on a shuffled scene does this).
"""

from __future__ import annotations

import dataclasses
import glob
import os
import zipfile
from collections.abc import Iterator, Mapping, Sequence

import jax
import numpy as np

from sgjax.stage2.ernet import DEFAULT_SPEC
from sgjax.utils.files import atomic_write
from sgjax.geometry.gripper import GripperSpec

REGION_POINTS = 2048  # P: capacity of a stored enlarged region
N_REFINEMENTS = 3
SHARD_SUFFIX = ".npz"


@dataclasses.dataclass(frozen=True)
class Field:
    dtype: np.dtype
    shape: tuple[int, ...]  # per sample


SAMPLE_FIELDS: dict[str, Field] = {
    "region": Field(np.dtype(np.float32), (REGION_POINTS, 3)),
    "region_mask": Field(np.dtype(bool), (REGION_POINTS,)),
    "pose": Field(np.dtype(np.float32), (4, 4)),
    "width": Field(np.dtype(np.float32), ()),
    "label": Field(np.dtype(np.int8), ()),
    "refine_labels": Field(np.dtype(np.int8), (N_REFINEMENTS,)),
    "scene_seed": Field(np.dtype(np.int64), ()),
    "object_name": Field(np.dtype(str), ()),
    "valid": Field(np.dtype(bool), ()),
}


class DatasetError(ValueError):
    """A shard or sample that does not follow SAMPLE_FIELDS, with a message naming the problem."""


Samples = dict[str, np.ndarray]  # field -> array stacked over samples [S, ...]


def _as_columns(samples: Mapping[str, np.ndarray] | Sequence[Mapping[str, object]]) -> dict[str, np.ndarray]:
    """A list of per-sample dicts or a dict of stacked arrays -> dict of stacked arrays."""
    if isinstance(samples, Mapping):
        return {k: np.asarray(v) for k, v in samples.items()}
    samples = list(samples)
    if not samples:
        raise DatasetError("no samples to write")
    missing = [k for k in SAMPLE_FIELDS if k not in samples[0]]
    if missing:
        raise DatasetError(f"sample 0 lacks fields {missing}")
    return {k: np.stack([np.asarray(s[k]) for s in samples]) for k in SAMPLE_FIELDS}


def validate(samples: Mapping[str, np.ndarray], source: str = "samples") -> Samples:
    """Check names, dtypes, shapes and values; -> the columns cast to SAMPLE_FIELDS dtypes.

    Raises DatasetError naming the source, field and problem (unknown/missing field, wrong shape,
    NaN in a real region point or pose, labels outside {0, 1})."""
    unknown = sorted(set(samples) - set(SAMPLE_FIELDS))
    missing = [k for k in SAMPLE_FIELDS if k not in samples]
    if unknown or missing:
        raise DatasetError(f"{source}: missing fields {missing}, unknown fields {unknown}")
    n = len(samples["label"]) if np.ndim(samples["label"]) else -1
    out: Samples = {}
    for name, field in SAMPLE_FIELDS.items():
        value = np.asarray(samples[name])
        if value.shape != (n, *field.shape):
            raise DatasetError(f"{source}: field {name!r} has shape {value.shape}, expected {(n, *field.shape)}")
        if field.dtype.kind == "U":
            if value.dtype.kind not in "US":
                raise DatasetError(f"{source}: field {name!r} must be strings, got {value.dtype}")
            out[name] = value.astype(str)
            continue
        if field.dtype.kind in "bi" and value.dtype.kind not in "biu":
            raise DatasetError(f"{source}: field {name!r} must be {field.dtype}, got {value.dtype}")
        out[name] = value.astype(field.dtype)
    if n == 0:
        return out
    real = out["region_mask"]
    if not np.isfinite(out["region"][real]).all():
        raise DatasetError(f"{source}: NaN or inf in real region points")
    if not np.isfinite(out["pose"]).all() or not np.isfinite(out["width"]).all():
        raise DatasetError(f"{source}: NaN or inf in pose or width")
    for name in ("label", "refine_labels"):
        if not np.isin(out[name], (0, 1)).all():
            raise DatasetError(f"{source}: field {name!r} must hold 0 or 1")
    return out


def write_shard(path: str | os.PathLike, samples: Mapping[str, np.ndarray] | Sequence[Mapping[str, object]]) -> str:
    """Write samples (dict of stacked arrays, or a list of per-sample dicts) as one .npz shard,
    atomically (a reader never sees half a shard). Returns the path written (".npz" appended)."""
    path = os.fspath(path)
    if not path.endswith(SHARD_SUFFIX):
        path += SHARD_SUFFIX
    columns = validate(_as_columns(samples), path)
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    atomic_write(path, lambda tmp: np.savez_compressed(tmp, **columns))  # padding compresses ~6x
    return path


def read_shard(path: str | os.PathLike) -> Samples:
    """One shard -> validated columns. Raises DatasetError for unreadable or malformed files."""
    path = os.fspath(path)
    try:
        with np.load(path, allow_pickle=False) as data:
            columns = {k: data[k] for k in data.files}
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as exc:
        raise DatasetError(f"{path}: not a readable .npz shard ({exc})") from None
    return validate(columns, path)


def shard_paths(directory: str | os.PathLike) -> list[str]:
    """The shards of a directory, sorted (temporary files of unfinished writes are skipped)."""
    paths = sorted(glob.glob(os.path.join(os.fspath(directory), f"*{SHARD_SUFFIX}")))
    return [p for p in paths if ".tmp-" not in os.path.basename(p)]


def read_shards(directory: str | os.PathLike) -> Samples:
    """All shards of a directory concatenated (sorted by file name, so the order is deterministic)."""
    if not os.path.isdir(directory):
        raise DatasetError(f"{directory}: not a directory")
    paths = shard_paths(directory)
    if not paths:
        raise DatasetError(f"{directory}: no {SHARD_SUFFIX} shards")
    parts = [read_shard(p) for p in paths]
    return {k: np.concatenate([p[k] for p in parts]) for k in SAMPLE_FIELDS}


def num_samples(samples: Mapping[str, np.ndarray]) -> int:
    return len(samples["label"])


def select(samples: Mapping[str, np.ndarray], index: np.ndarray) -> Samples:
    """Rows `index` of every field."""
    return {k: v[index] for k, v in samples.items()}


# ---------------------------------------------------------------------------------------------
# Split and batching.


def _splitmix64(x: np.ndarray) -> np.ndarray:
    """A fixed 64-bit integer hash (splitmix64 finaliser), independent of Python's hash seed."""
    with np.errstate(over="ignore"):
        z = x.astype(np.uint64) + np.uint64(0x9E3779B97F4A7C15)
        z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
        z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
        return z ^ (z >> np.uint64(31))


def split_by_scene(scene_seed: np.ndarray, held_out_fraction: float = 0.1, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Deterministic train / held-out split by scene: scene_seed[S] -> (train_index, held_out_index).

    A scene goes to the held-out set iff hash(scene_seed, seed) < fraction, so the assignment of a
    scene never depends on the order or number of shards, and no scene is in both sets.
    """
    if not 0.0 <= held_out_fraction < 1.0:
        raise ValueError(f"held_out_fraction must be in [0, 1), got {held_out_fraction}")
    scene_seed = np.asarray(scene_seed, np.int64)
    mixed = _splitmix64(scene_seed.view(np.uint64) ^ _splitmix64(np.asarray([seed], np.uint64)))
    held = (mixed >> np.uint64(11)).astype(np.float64) / float(1 << 53) < held_out_fraction
    return np.flatnonzero(~held), np.flatnonzero(held)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Batch:
    """A fixed-size batch (numpy or device arrays): the training fields plus `weight` [B] (0 for
    padding rows of the last batch, 1 otherwise)."""

    region: np.ndarray
    region_mask: np.ndarray
    width: np.ndarray
    label: np.ndarray
    refine_labels: np.ndarray
    weight: np.ndarray


TRAIN_FIELDS = ("region", "region_mask", "width", "label", "refine_labels")


def batch_indices(n: int, batch_size: int, rng: np.random.Generator | None) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """(index[B], weight[B]) per batch over n samples: shuffled when `rng` is given; the last batch is
    padded with index 0 / weight 0 so every batch has the same shape (one compile)."""
    order = rng.permutation(n) if rng is not None else np.arange(n)
    for start in range(0, n, batch_size):
        index = order[start : start + batch_size]
        weight = np.ones(batch_size, np.float32)
        if len(index) < batch_size:
            weight[len(index) :] = 0.0
            index = np.concatenate([index, np.zeros(batch_size - len(index), index.dtype)])
        yield index, weight


def make_batch(samples: Mapping[str, np.ndarray], index: np.ndarray, weight: np.ndarray) -> Batch:
    """Array slices of preloaded columns (no per-sample Python work)."""
    return Batch(**{k: samples[k][index] for k in TRAIN_FIELDS}, weight=weight)


# ---------------------------------------------------------------------------------------------
# Synthetic data (tests and demos without the simulator).


def synthetic_samples(
    n: int,
    seed: int = 0,
    spec: GripperSpec = DEFAULT_SPEC,
    samples_per_scene: int = 4,
    surface_points: int = 3000,
) -> Samples:
    """n samples of a box seen in the grasp frame, labelled by geometry like a parallel-jaw grasp.

    The box (random size) extends from depth z0 along the approach axis past the fingertips, turned
    by yaw phi about the approach axis and shifted along the closing axis. A grasp (pose variant with
    yaw offset theta and extra depth d) is stable iff the box fits between the fingers, reaches at
    least 20 mm between them (finger_length - (z0 - d)) and |phi - theta| <= 8 deg. The label uses
    (theta, d) = (0, 0); refine label v uses (refine_angles_deg[v], spec.deepen) — so labels are a
    function of the visible geometry, as in the simulator.
    """
    rng = np.random.default_rng(seed)
    width = rng.uniform(0.05, spec.max_opening, n)
    half_x = rng.uniform(0.006, 0.03, n)  # box half-extent across the closing axis
    half_y = rng.uniform(0.01, 0.04, n)
    angles = np.asarray(spec.refine_angles_deg)
    # Yaw: half near 0, the rest near one of the refinement angles, so every label occurs often.
    centre = np.where(rng.random(n) < 0.5, 0.0, rng.choice(angles, n))
    phi = np.deg2rad(centre + rng.uniform(-12.0, 12.0, n))
    z0 = rng.uniform(0.01, 0.042, n)
    shift = rng.uniform(-0.006, 0.006, n)
    depth = 0.12

    def stable(theta_deg: np.ndarray, deepen: float) -> np.ndarray:
        rel = phi - np.deg2rad(theta_deg)
        extent = half_x * np.abs(np.cos(rel)) + half_y * np.abs(np.sin(rel)) + np.abs(shift * np.cos(np.deg2rad(theta_deg)))
        fits = extent < 0.5 * width - 0.002
        reach = spec.finger_length - (z0 - deepen) >= 0.02
        return fits & reach & (np.abs(np.rad2deg(rel)) <= 8.0)

    label = stable(np.zeros(n), 0.0)
    refine = np.stack([stable(np.full(n, a), spec.deepen) for a in angles], -1)

    # Box surface points (all six faces, by area) in the box frame, then into the grasp frame.
    size = np.stack([2 * half_x, 2 * half_y, np.full(n, depth)], -1)
    u = rng.random((n, surface_points, 3))
    face_area = np.stack([size[:, 1] * size[:, 2], size[:, 0] * size[:, 2], size[:, 0] * size[:, 1]], -1)
    cum = np.cumsum(face_area, -1) / face_area.sum(-1, keepdims=True)
    axis = (rng.random((n, surface_points))[..., None] > cum[:, None, :2]).sum(-1)  # face normal
    local = (u - 0.5) * size[:, None, :]
    side = np.where(rng.random((n, surface_points)) < 0.5, -0.5, 0.5)
    np.put_along_axis(local, axis[..., None], (side * np.take_along_axis(size, axis, -1))[..., None], -1)
    local[..., 2] += 0.5 * depth  # z from 0 (near face) to depth
    c, s = np.cos(phi)[:, None], np.sin(phi)[:, None]
    x = c * local[..., 0] - s * local[..., 1] + shift[:, None]
    y = s * local[..., 0] + c * local[..., 1]
    z = local[..., 2] + z0[:, None]
    points = np.stack([x, y, z], -1).astype(np.float32)

    inside = _enlarged_mask(points, width, spec)
    region = np.zeros((n, REGION_POINTS, 3), np.float32)
    mask = np.zeros((n, REGION_POINTS), bool)
    keys = np.where(inside, rng.random(inside.shape), 2.0)  # random order, region points first
    order = np.argsort(keys, axis=-1)[:, :REGION_POINTS]
    take = np.take_along_axis(inside, order, -1)
    region[:, : order.shape[1]] = np.where(take[..., None], np.take_along_axis(points, order[..., None], 1), 0.0)
    mask[:, : order.shape[1]] = take

    pose = np.tile(np.eye(4, dtype=np.float32), (n, 1, 1))
    pose[:, :3, 3] = rng.uniform(-0.2, 0.2, (n, 3))
    return validate(
        {
            "region": region,
            "region_mask": mask,
            "pose": pose,
            "width": width.astype(np.float32),
            "label": label.astype(np.int8),
            "refine_labels": refine.astype(np.int8),
            "scene_seed": (seed * 1_000_003 + np.arange(n) // samples_per_scene).astype(np.int64),
            "object_name": np.full(n, "synthetic_box"),
            "valid": np.ones(n, bool),
        },
        "synthetic samples",
    )


def _enlarged_mask(points: np.ndarray, width: np.ndarray, spec: GripperSpec) -> np.ndarray:
    """Grasp-frame points[n, N, 3] in the enlarged region of widths[n] (sgjax.geometry.gripper geometry)."""
    from sgjax.stage2.crops import in_enlarged_region_local

    return np.asarray(in_enlarged_region_local(points, width.astype(np.float32), spec))
