"""E-RNet training samples: the shard formats, reading, cropping, the scene-level split, batching, synthetic data.

One sample = one executed grasp (paper Sec. IV-C). Two formats:

* Label shards (`write_label_shard`, written by `train.label`): per sample the grasp, its source,
  outcomes and labels (`LABEL_FIELDS`); per scene its Stage-2 cloud, stored once (`cloud_points`
  [T, 3] float32, the scenes' real points back to back, shuffled; `cloud_offsets` [K + 1]). A sample's
  `cloud_row` is its scene's row. Any Stage-2 input is cut from these clouds later (`crop_label_shard`,
  cached beside the shards), so trying another input needs no new labels.
* Sample shards (`write_shard`): the training view, `SAMPLE_FIELDS`, with the input crop made:

    region         float32[P, 3]  scene points in the enlarged region, GRASP frame (padding rows 0)
    region_mask    bool[P]        True for real points (P = REGION_POINTS = 2048)
    pose           float32[4, 4]  the grasp (gripper -> world)
    width          float32[]      gripper opening (m)
    label          int8[]         1: stable grasp (lift, reorient, 1 N disturbance), 0: not
    refine_labels  int8[3]        the same criterion for deepen 0.008 m + rotate -15 / 0 / +15 deg
    scene_seed     int64[]        the scene it came from (the train / held-out split is by scene)
    object_name    str            the target object
    valid          bool[]         False: the trial could not be run (excluded from training)
    source         int8[]         candidate source (`train.sources.SOURCES` index)
    outcome        int8[]         the initial grasp's trial outcome (`envs.outcome.Outcome`)
    held_out_object bool[]        the target is a held-out object (never trained on)

A shard (compressed .npz) stores each field stacked over its samples ([S, ...]); `object_name` as a
fixed-width unicode array. Regions with more than P points should be randomly subsampled by the writer
(`sgjax.stage2.crops.crop_regions` on a shuffled scene does this).
"""

from __future__ import annotations

import dataclasses
import functools
import glob
import hashlib
import json
import os
import zipfile
from collections.abc import Iterator, Mapping, Sequence

import jax
import numpy as np

from sgjax.stage2.crops import CROPS, HAND_MARGIN, HAND_SWEEP, crop_function, in_enlarged_region_local
from sgjax.stage2.ernet import DEFAULT_SPEC
from sgjax.utils.configs import from_dict
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
    "source": Field(np.dtype(np.int8), ()),
    "outcome": Field(np.dtype(np.int8), ()),
    "held_out_object": Field(np.dtype(bool), ()),
}

# Per-sample fields of a label shard (the crop is made later from the scene clouds).
LABEL_FIELDS: dict[str, Field] = {
    **{k: f for k, f in SAMPLE_FIELDS.items() if k not in ("region", "region_mask")},
    "refine_outcomes": Field(np.dtype(np.int8), (N_REFINEMENTS,)),
    "scene_index": Field(np.dtype(np.int32), ()),
    "cloud_row": Field(np.dtype(np.int32), ()),
}
CLOUD_FIELDS = ("cloud_points", "cloud_offsets")


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


def validate(samples: Mapping[str, np.ndarray], source: str = "samples", fields: Mapping[str, Field] = SAMPLE_FIELDS) -> Samples:
    """Check names, dtypes, shapes and values; -> the columns cast to `fields`' dtypes (SAMPLE_FIELDS,
    or LABEL_FIELDS for a label shard's samples).

    Raises DatasetError naming the source, field and problem (unknown/missing field, wrong shape,
    NaN in a real region point or pose, labels outside {0, 1})."""
    unknown = sorted(set(samples) - set(fields))
    missing = [k for k in fields if k not in samples]
    if unknown or missing:
        raise DatasetError(f"{source}: missing fields {missing}, unknown fields {unknown}")
    n = len(samples["label"]) if np.ndim(samples["label"]) else -1
    out: Samples = {}
    for name, field in fields.items():
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
    if "region" in out and not np.isfinite(out["region"][out["region_mask"]]).all():
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
    return validate(_load(path), path)


def shard_paths(directory: str | os.PathLike) -> list[str]:
    """The shards of a directory, sorted (temporary files of unfinished writes are skipped)."""
    paths = sorted(glob.glob(os.path.join(os.fspath(directory), f"*{SHARD_SUFFIX}")))
    return [p for p in paths if ".tmp-" not in os.path.basename(p)]


def read_shards(directories: str | os.PathLike | Sequence[str | os.PathLike], crop: str = "enlarged") -> Samples:
    """All shards of a directory, or of several, concatenated (directories in the order given, shards
    sorted by file name, so the order is deterministic), as SAMPLE_FIELDS: label shards are cropped
    (`crop_label_shard`, cached), sample shards read as they are. Several directories must hold
    disjoint scenes (no scene seed in two of them: the same scene twice would be counted twice and
    could straddle the held-out split) made with one gripper spec; DatasetError names the clash."""
    dirs = [directories] if isinstance(directories, (str, os.PathLike)) else list(directories)
    if not dirs:
        raise DatasetError("no data directories given")
    parts, scenes, specs = [], {}, {}
    for directory in dirs:
        if not os.path.isdir(directory):
            raise DatasetError(f"{directory}: not a directory")
        paths = shard_paths(directory)
        if not paths:
            raise DatasetError(f"{directory}: no {SHARD_SUFFIX} shards")
        spec = specs[os.fspath(directory)] = directory_spec(directory)
        part = [crop_label_shard(p, spec, crop) if is_label_shard(p) else read_shard(p) for p in paths]
        part = {k: np.concatenate([p[k] for p in part]) for k in SAMPLE_FIELDS}
        own = set(np.unique(part["scene_seed"]).tolist())
        for other, theirs in scenes.items():
            if own & theirs:
                raise DatasetError(f"{directory} and {other} hold {len(own & theirs)} of the same scenes (scene seeds); "
                                   "give directories of disjoint scenes (sgjax label --first-scene)")
        scenes[os.fspath(directory)] = own
        parts.append(part)
    if len(set(specs.values())) > 1:
        raise DatasetError(f"the directories were made with different gripper specs: {specs}")
    return {k: np.concatenate([p[k] for p in parts]) for k in SAMPLE_FIELDS}


# ---------------------------------------------------------------------------------------------
# Label shards: samples without crops, plus each scene's Stage-2 cloud.


def empty_labels() -> Samples:
    """A label shard's sample columns with no rows."""
    return {k: np.zeros((0, *f.shape), f.dtype) for k, f in LABEL_FIELDS.items()}


def write_label_shard(path: str | os.PathLike, samples: Mapping[str, np.ndarray], clouds: Sequence[np.ndarray]) -> str:
    """Write a label shard atomically: samples (LABEL_FIELDS columns) whose `cloud_row` indexes
    `clouds` (each [C_k, 3], the scene's real Stage-2 points in the order crops read them)."""
    path = os.fspath(path)
    if not path.endswith(SHARD_SUFFIX):
        path += SHARD_SUFFIX
    columns = validate(samples, path, LABEL_FIELDS)
    rows = columns["cloud_row"]
    if len(rows) and (rows.min() < 0 or rows.max() >= len(clouds)):
        raise DatasetError(f"{path}: cloud_row outside [0, {len(clouds)})")
    clouds = [np.asarray(c, np.float32).reshape(-1, 3) for c in clouds]
    if any(not np.isfinite(c).all() for c in clouds):
        raise DatasetError(f"{path}: NaN or inf in a scene cloud")
    offsets = np.cumsum([0] + [len(c) for c in clouds]).astype(np.int64)
    points = np.concatenate(clouds) if clouds else np.zeros((0, 3), np.float32)
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    atomic_write(path, lambda tmp: np.savez_compressed(tmp, **columns, cloud_points=points, cloud_offsets=offsets))
    return path


def _load(path: str) -> dict[str, np.ndarray]:
    try:
        with np.load(path, allow_pickle=False) as data:
            return {k: data[k] for k in data.files}
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as exc:
        raise DatasetError(f"{path}: not a readable .npz shard ({exc})") from None


def is_label_shard(path: str | os.PathLike) -> bool:
    """Whether a shard holds scene clouds (a label shard) rather than crops."""
    try:
        with zipfile.ZipFile(os.fspath(path)) as archive:
            return "cloud_points.npy" in archive.namelist()
    except (OSError, zipfile.BadZipFile) as exc:
        raise DatasetError(f"{path}: not a readable .npz shard ({exc})") from None


def read_label_shard(path: str | os.PathLike) -> tuple[Samples, list[np.ndarray]]:
    """A label shard -> (validated LABEL_FIELDS columns, the scene clouds [C_k, 3])."""
    path = os.fspath(path)
    columns = _load(path)
    if not all(k in columns for k in CLOUD_FIELDS):
        raise DatasetError(f"{path}: not a label shard (no {' / '.join(CLOUD_FIELDS)})")
    points, offsets = columns.pop("cloud_points"), columns.pop("cloud_offsets")
    if offsets.ndim != 1 or len(offsets) == 0 or offsets[0] != 0 or offsets[-1] != len(points) or np.any(np.diff(offsets) < 0):
        raise DatasetError(f"{path}: cloud_offsets do not partition cloud_points")
    samples = validate(columns, path, LABEL_FIELDS)
    clouds = [points[a:b] for a, b in zip(offsets[:-1], offsets[1:])]
    if len(samples["cloud_row"]) and samples["cloud_row"].max() >= len(clouds):
        raise DatasetError(f"{path}: cloud_row beyond its {len(clouds)} clouds")
    return samples, clouds


def directory_spec(directory: str | os.PathLike) -> GripperSpec:
    """The gripper a labelled directory was made with (its label_config.json), else DEFAULT_SPEC."""
    path = os.path.join(os.fspath(directory), "label_config.json")
    if not os.path.exists(path):
        return DEFAULT_SPEC
    with open(path) as fh:
        saved = json.load(fh)
    try:
        return from_dict(GripperSpec, saved["stage1"]["spec"])
    except (KeyError, TypeError, ValueError) as exc:
        raise DatasetError(f"{path}: no readable stage1.spec ({exc})") from None


# A label shard is cropped to one of the Stage-2 inputs (`sgjax.stage2.crops.CROPS`): the paper's enlarged
# region, or that region together with the hand's swept volume (E-RNet's hand input). The version names
# the cached crops' layout.
CROP_VERSION = 1


def _bucket(n: int, least: int) -> int:
    """The next power of two >= max(n, least): few distinct shapes, so few compiles."""
    return 1 << max(int(n) - 1, least - 1, 0).bit_length()


def crop_samples(samples: Mapping[str, np.ndarray], clouds: Sequence[np.ndarray], spec: GripperSpec, crop: str = "enlarged") -> Samples:
    """LABEL_FIELDS samples and their scene clouds -> SAMPLE_FIELDS samples with the `crop` input made
    (REGION_POINTS points): "enlarged", the paper's enlarged region (`sgjax.stage2.crops.crop_regions`),
    or "swept", that region and the hand's swept volume (`crop_swept_regions`)."""
    if crop not in CROPS:
        raise DatasetError(f"unknown crop {crop!r}; known: {', '.join(CROPS)}")
    n = len(samples["label"])
    region = np.zeros((n, REGION_POINTS, 3), np.float32)
    region_mask = np.zeros((n, REGION_POINTS), bool)
    fn = _jitted_crop(crop_function(crop))
    for row, cloud in enumerate(clouds):
        index = np.flatnonzero(samples["cloud_row"] == row)
        if not len(index):
            continue
        c, g = _bucket(len(cloud), 1024), _bucket(len(index), 16)
        points = np.zeros((c, 3), np.float32)
        points[: len(cloud)] = cloud
        poses = np.tile(np.eye(4, dtype=np.float32), (g, 1, 1))
        widths = np.zeros(g, np.float32)
        poses[: len(index)], widths[: len(index)] = samples["pose"][index], samples["width"][index]
        out = fn(points, poses, widths, spec=spec, n_points=REGION_POINTS, scene_mask=np.arange(c) < len(cloud))
        region[index] = np.asarray(out.points)[: len(index)]
        region_mask[index] = np.asarray(out.mask)[: len(index)]
    kept = {k: np.asarray(samples[k]) for k in SAMPLE_FIELDS if k not in ("region", "region_mask")}
    return validate({**kept, "region": region, "region_mask": region_mask}, "cropped samples")


@functools.cache
def _jitted_crop(fn):
    return jax.jit(fn, static_argnames=("spec", "n_points"))


def crop_label_shard(path: str | os.PathLike, spec: GripperSpec = DEFAULT_SPEC, crop: str = "enlarged") -> Samples:
    """A label shard cropped to `crop` (`crop_samples`), cached beside it in crops/<crop>-v<N>-<spec
    hash>/ (shards never change once written, so a cached crop stays valid)."""
    path = os.fspath(path)
    described = repr(spec) + (f" sweep {HAND_SWEEP} margin {HAND_MARGIN}" if crop == "swept" else "")
    key = hashlib.sha256(described.encode()).hexdigest()[:10]
    cached = os.path.join(os.path.dirname(path), "crops", f"{crop}-v{CROP_VERSION}-{key}", os.path.basename(path))
    if os.path.exists(cached) and os.path.getmtime(cached) >= os.path.getmtime(path):
        return read_shard(cached)
    samples, clouds = read_label_shard(path)
    cropped = crop_samples(samples, clouds, spec, crop)
    write_shard(cached, cropped)
    return cropped


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
            "source": np.zeros(n, np.int8),
            "outcome": np.where(label, 0, 3).astype(np.int8),  # success / dropped at lift
            "held_out_object": np.zeros(n, bool),
        },
        "synthetic samples",
    )


def _enlarged_mask(points: np.ndarray, width: np.ndarray, spec: GripperSpec) -> np.ndarray:
    """Grasp-frame points[n, N, 3] in the enlarged region of widths[n] (sgjax.geometry.gripper geometry)."""
    return np.asarray(in_enlarged_region_local(points, width.astype(np.float32), spec))
