"""The labelling pipeline (paper Sec. IV-C): simulated scenes -> Stage-1 candidates -> grasp trials -> shards.

Per scene (seeded by (seed, scene index)): drop `n_objects` objects on the table, render the depth
camera, pick one visible target at random, run Stage 1 on its single-view cloud (with the scene cloud
for the collision filter), execute `grasps_per_scene` randomly chosen candidates and their three
refinement variants (deepen 0.008 m, rotate -15 / 0 / +15 deg) in parallel, and store one sample per
executed grasp (`train.dataset.SAMPLE_FIELDS`): its enlarged region cropped from the Stage-2 scene
cloud (`sgjax.geometry.pointcloud.scene_cloud`, the same cloud the planner scores on), the grasp, its label and
the three refinement labels.

Output directory:
    label_config.json               what made the data; a resumed run must match it
    scenes-SSSSSS-EEEEEE.npz        samples of scenes [S, E) (a shard; atomic)
    scenes-SSSSSS-EEEEEE.json       their statistics (written before the shard)
A shard's existence marks its scenes done: an interrupted run resumes with the scenes no shard
covers, so no sample is lost or written twice; asking for more scenes later extends the run.
"""

from __future__ import annotations

import dataclasses
import json
import os
import re
import time
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from envs import camera as camera_lib
from envs import scene as scene_lib
from envs.trial import Outcome, TrialConfig, check_backend, run_grasp_with_refinements
from sgjax.stage2.crops import crop_regions
from sgjax.stage2.scene_cloud import SceneCloudConfig
from sgjax.utils.files import atomic_write_text
from sgjax.geometry.gripper import GripperSpec
from sgjax.stage1.pipeline import Stage1, Stage1Config
from train import dataset

CONFIG_FILE = "label_config.json"
SHARD_PATTERN = re.compile(r"^scenes-(\d{6})-(\d{6})\.npz$")


@dataclasses.dataclass(frozen=True)
class LabelConfig:
    """How samples are made (everything that changes the data; saved with it).

    n_objects: objects per scene (paper: 5). grasps_per_scene: candidates executed per scene, each with
    its 3 refinements (4 trials). scenes_per_shard: scenes per output file (the resume granularity).
    min_target_points: a target must show at least this many camera points (Stage 1's own minimum).
    voxel, max_scene_points, workspace_margin: the Stage-2 scene cloud (`scene_cloud`, a
    `sgjax.stage2.scene_cloud.SceneCloudConfig`) cropped to the workspace plus this margin.
    """

    n_objects: int = 5
    grasps_per_scene: int = 16
    scenes_per_shard: int = 4
    min_target_points: int = 50
    object_set: str = "seen"
    seed: int = 0
    voxel: float = SceneCloudConfig.voxel
    max_scene_points: int = SceneCloudConfig.max_points
    workspace_margin: float = scene_lib.WORKSPACE_MARGIN
    scene: scene_lib.SceneConfig = scene_lib.SceneConfig()
    camera: camera_lib.CameraConfig = camera_lib.CameraConfig()
    trial: TrialConfig = TrialConfig()
    stage1: Stage1Config = Stage1Config()

    def __post_init__(self):
        for name in ("n_objects", "grasps_per_scene", "scenes_per_shard", "min_target_points", "max_scene_points"):
            if getattr(self, name) < 1:
                raise ValueError(f"LabelConfig.{name} must be >= 1, got {getattr(self, name)}")

    @property
    def spec(self) -> GripperSpec:
        return self.stage1.spec

    @property
    def scene_cloud(self) -> SceneCloudConfig:
        """The Stage-2 scene cloud: cropped to the workspace grown by workspace_margin."""
        return scene_lib.stage2_scene_cloud(self.scene, self.workspace_margin, max_points=self.max_scene_points, voxel=self.voxel)

    def to_json(self) -> str:
        return json.dumps(dataclasses.asdict(self), sort_keys=True, default=str)


@dataclasses.dataclass
class LabelSummary:
    """What a labelling run produced (all shards in the directory, not only this call's)."""

    scenes: int
    samples: int
    valid_samples: int
    positives: float  # fraction of valid samples with label 1
    refine_positives: list[float]  # per refinement variant
    trials: int
    invalid_trials: int
    outcomes: dict[str, int]
    scenes_without_samples: dict[str, int]  # reason -> scenes
    seconds: float  # simulated-and-computed wall time summed over shards
    trials_per_second: float

    def lines(self) -> list[str]:
        skipped = ", ".join(f"{k}: {v}" for k, v in sorted(self.scenes_without_samples.items())) or "none"
        return [
            (
                f"scenes {self.scenes}, samples {self.samples} ({self.valid_samples} valid), "
                f"positive rate {self.positives:.1%}, refine positives "
                + " / ".join(f"{p:.1%}" for p in self.refine_positives)
            ),
            (
                f"trials {self.trials} ({self.invalid_trials} invalid), "
                f"{self.trials_per_second:.1f} trials/s end to end over {self.seconds:.0f} s"
            ),
            "outcomes: " + ", ".join(f"{k} {v}" for k, v in self.outcomes.items() if v),
            f"scenes without samples: {skipped}",
        ]


def scene_seed(seed: int, index: int) -> int:
    """The seed of scene `index` of a run seeded `seed` (independent streams, stable across versions)."""
    return int(np.random.SeedSequence([seed, index]).generate_state(1, np.uint32)[0])


def stage2_cloud(points: np.ndarray, config: LabelConfig, labels: np.ndarray | None = None, seed: int = 0):
    """The Stage-2 scene cloud of an observation: workspace crop, voxel grid, fixed size.

    points [N, 3] world -> (points [max_scene_points, 3], mask, labels or None); see scene_cloud.
    """
    return config.scene_cloud.make(points, labels, seed)


_crop = jax.jit(crop_regions, static_argnames=("spec", "n_points"))


def _empty_samples() -> dict[str, np.ndarray]:
    return {k: np.zeros((0, *f.shape), f.dtype) for k, f in dataset.SAMPLE_FIELDS.items()}


def label_scene(
    index: int, objects: Sequence, stage1: Stage1, config: LabelConfig, backend: str = "cpu", nthread: int = 0
) -> tuple[dict[str, np.ndarray], dict]:
    """Samples of scene `index` (fields of SAMPLE_FIELDS, [S, ...]) and its statistics."""
    seed = scene_seed(config.seed, index)
    rng = np.random.default_rng(seed)
    stats = {"scene": index, "scene_seed": seed, "trials": 0, "outcomes": {}, "skipped": None}
    try:
        scene = scene_lib.make_scene(objects, config.n_objects, seed, config.scene, config.spec)
    except ValueError as exc:  # an unloadable mesh; recorded, the run goes on
        stats["skipped"] = f"scene failed: {exc}"
        return _empty_samples(), stats
    obs = camera_lib.observe(scene, config.camera, seed=seed)
    counts = np.bincount(obs.point_labels[obs.point_labels >= 0], minlength=scene.n_objects)
    visible = np.flatnonzero((counts >= config.min_target_points) & scene.present)
    if len(visible) == 0:
        stats["skipped"] = "no visible target"
        return _empty_samples(), stats
    # Stage 1 on every visible object in one call (padded to n_objects clouds: one compile), then
    # a random target among those with candidates, so fewer scenes go to waste.
    clouds = [obs.object_cloud(int(k)) for k in visible]
    clouds += [clouds[0]] * (config.n_objects - len(clouds))
    scenes = [obs.points] * len(clouds)
    views = np.tile(np.asarray(config.camera.position, np.float32), (len(clouds), 1))
    found = stage1.batch(clouds, scenes, views, seed % (2**31), scene_lib.TABLE_PLANE)[: len(visible)]
    usable = [i for i, c in enumerate(found) if len(c)]
    if not usable:
        stats["skipped"] = "no candidates"
        stats["reason"] = "; ".join(f"{scene.assets[k].name}: {c.reason}" for k, c in zip(visible, found))
        return _empty_samples(), stats
    pick = int(rng.choice(usable))
    target, candidates = int(visible[pick]), found[pick]
    g = min(config.grasps_per_scene, len(candidates))
    chosen = np.sort(rng.choice(len(candidates), size=g, replace=False))
    poses, widths = candidates.poses[chosen], np.clip(candidates.widths[chosen], 0.0, config.spec.max_opening)
    labels, result = run_grasp_with_refinements(
        scene, target, poses, widths, backend=backend, config=config.trial, nthread=nthread
    )
    outcome = result.outcome.reshape(g, -1)
    stats["trials"] = int(outcome.size)
    stats["outcomes"] = result.counts()

    cloud, mask, _ = stage2_cloud(obs.points, config, seed=seed)
    order = rng.permutation(len(cloud))  # crop_regions keeps the first region points in scene order
    padded_poses = np.tile(np.eye(4, dtype=np.float32), (config.grasps_per_scene, 1, 1))
    padded_widths = np.zeros(config.grasps_per_scene, np.float32)
    padded_poses[:g], padded_widths[:g] = poses, widths
    region = _crop(
        jnp.asarray(cloud[order]),
        jnp.asarray(padded_poses),
        jnp.asarray(padded_widths),
        spec=config.spec,
        n_points=dataset.REGION_POINTS,
        scene_mask=jnp.asarray(mask[order]),
    )
    samples = {
        "region": np.asarray(region.points)[:g],
        "region_mask": np.asarray(region.mask)[:g],
        "pose": poses.astype(np.float32),
        "width": widths.astype(np.float32),
        "label": labels[:, 0].astype(np.int8),
        "refine_labels": labels[:, 1:].astype(np.int8),
        "scene_seed": np.full(g, seed, np.int64),
        "object_name": np.array([scene.assets[target].name] * g),
        "valid": ~(outcome == Outcome.INVALID).any(axis=1),
    }
    return samples, stats


def _covered(out_dir: str) -> set[int]:
    done: set[int] = set()
    for name in os.listdir(out_dir):
        match = SHARD_PATTERN.match(name)
        if match:
            done.update(range(int(match.group(1)), int(match.group(2))))
    return done


def _runs(indices: list[int], size: int) -> list[tuple[int, int]]:
    """Group sorted scene indices into [start, end) runs of consecutive indices, at most `size` long."""
    runs: list[tuple[int, int]] = []
    for i in indices:
        if runs and runs[-1][1] == i and i - runs[-1][0] < size:
            runs[-1] = (runs[-1][0], i + 1)
        else:
            runs.append((i, i + 1))
    return runs


def _check_config(out_dir: str, config: LabelConfig) -> None:
    path = os.path.join(out_dir, CONFIG_FILE)
    text = config.to_json()
    if os.path.exists(path):
        with open(path) as fh:
            saved = fh.read()
        if saved != text:
            raise ValueError(
                f"{out_dir} holds data made with a different labelling config ({path}); "
                "use a new --out directory or the same options"
            )
    else:
        os.makedirs(out_dir, exist_ok=True)
        atomic_write_text(path, text)


def label(
    out_dir: str | os.PathLike,
    n_scenes: int,
    config: LabelConfig = LabelConfig(),
    *,
    objects: Sequence | None = None,
    stage1: Stage1 | None = None,
    backend: str = "cpu",
    nthread: int = 0,
    progress: bool = True,
) -> LabelSummary:
    """Label scenes 0..n_scenes-1 into `out_dir`, skipping scenes already there; -> the summary.

    objects: prepared ObjectAssets (default: `load_object_set(config.object_set)`); stage1: a Stage1
    (default: the full primitive database). Raises ValueError if out_dir holds data of another config.
    """
    if n_scenes < 1:
        raise ValueError(f"n_scenes must be >= 1, got {n_scenes}")
    check_backend(backend)
    out_dir = os.fspath(out_dir)
    _check_config(out_dir, config)
    from envs.objects import load_object_set, object_set_identity

    if objects is None:  # a named set that lost a member raises ObjectSetError naming it
        objects = load_object_set(config.object_set, progress=progress, workers=os.cpu_count() or 1)
    if not objects:
        raise ValueError(f"object set {config.object_set!r} is empty")
    identity = object_set_identity(config.object_set, objects)
    stage1 = Stage1(None, config.stage1) if stage1 is None else stage1
    if stage1.config != config.stage1:
        raise ValueError("stage1.config differs from config.stage1")
    done = _covered(out_dir)
    todo = _runs([i for i in range(n_scenes) if i not in done], config.scenes_per_shard)
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=n_scenes, initial=n_scenes - sum(e - s for s, e in todo), unit="scene", desc="label")
    for start, end in todo:
        began = time.perf_counter()
        parts, stats = [], []
        for index in range(start, end):
            samples, scene_stats = label_scene(index, objects, stage1, config, backend, nthread)
            parts.append(samples)
            stats.append(scene_stats)
            if bar is not None:
                bar.update(1)
        samples = {k: np.concatenate([p[k] for p in parts]) for k in dataset.SAMPLE_FIELDS}
        base = os.path.join(out_dir, f"scenes-{start:06d}-{end:06d}")
        record = {"scenes": stats, "seconds": time.perf_counter() - began, "objects": identity}
        atomic_write_text(base + ".json", json.dumps(record))
        dataset.write_shard(base + dataset.SHARD_SUFFIX, samples)  # written last: marks the scenes done
        if bar is not None:
            bar.set_postfix(samples=sum(len(p["label"]) for p in parts))
    if bar is not None:
        bar.close()
    return summarize(out_dir)


def summarize(out_dir: str | os.PathLike) -> LabelSummary:
    """Statistics of every finished shard in a labelling directory."""
    out_dir = os.fspath(out_dir)
    shards = [os.path.join(out_dir, n) for n in sorted(os.listdir(out_dir)) if SHARD_PATTERN.match(n)]
    if not shards:
        raise dataset.DatasetError(f"{out_dir}: no labelled shards")
    samples = {k: np.concatenate([dataset.read_shard(p)[k] for p in shards]) for k in ("label", "refine_labels", "valid")}
    outcomes = {o.name.lower(): 0 for o in Outcome}
    skipped: dict[str, int] = {}
    scenes, trials, seconds = 0, 0, 0.0
    for path in shards:
        meta = path[: -len(dataset.SHARD_SUFFIX)] + ".json"
        if not os.path.exists(meta):
            continue
        with open(meta) as fh:
            record = json.load(fh)
        seconds += record["seconds"]
        for scene in record["scenes"]:
            scenes += 1
            trials += scene["trials"]
            for k, v in scene["outcomes"].items():
                outcomes[k] += v
            if scene["skipped"]:
                key = scene["skipped"].split(":")[0]
                skipped[key] = skipped.get(key, 0) + 1
    valid = samples["valid"]
    n_valid = int(valid.sum())
    return LabelSummary(
        scenes=scenes,
        samples=len(valid),
        valid_samples=n_valid,
        positives=float(samples["label"][valid].mean()) if n_valid else 0.0,
        refine_positives=[float(v) for v in samples["refine_labels"][valid].mean(0)] if n_valid else [0.0] * 3,
        trials=trials,
        invalid_trials=outcomes["invalid"],
        outcomes=outcomes,
        scenes_without_samples=skipped,
        seconds=seconds,
        trials_per_second=trials / seconds if seconds > 0 else 0.0,
    )
