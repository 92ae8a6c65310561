"""The labelling pipeline (paper Sec. IV-C): simulated scenes -> candidates of several sources -> trials -> shards.

Per scene (seeded by (seed, scene index)): drop `n_objects` objects on the table, render the depth
camera, run Stage 1 on every visible object's single-view cloud, pick up to `targets_per_scene`
targets at random, and on each execute grasps of several candidate sources (`train.sources`: Stage 1
as the planner runs it, Stage 1 with only the paper's filters, GPD-style samples, perturbations of
them; `LabelConfig.per_source` grasps of each) together with their three refinement variants
(deepen 0.008 m, rotate -15 / 0 / +15 deg), all in one batch of parallel trials. One sample per
executed grasp (`train.dataset.LABEL_FIELDS`: grasp, source, outcome, label and refinement labels).
The scene's Stage-2 cloud (`sgjax.stage2.scene_cloud`, the cloud the planner scores on) is stored once
per scene, shuffled, so that any Stage-2 input (the paper's enlarged region, or a larger crop) is cut
from it later (`train.dataset.crop_label_shard`) without labelling again.

Held out: `held_out_objects` (seen objects never trained on) appear only in every
`held_out_object_every`-th scene, where they are the only targets; their samples carry
`held_out_object`. Held-out scenes of the training objects are chosen at training time by scene
(`train.dataset.split_by_scene`).

Output directory:
    label_config.json               what made the data; a resumed run must match it (for a gripper other
                                    than the default, its whole spec in "gripper": closing force, friction)
    scenes-SSSSSS-EEEEEE.npz        samples and clouds of scenes [S, E) (a shard; atomic)
    scenes-SSSSSS-EEEEEE.json       their statistics (written before the shard)
A shard's existence marks its scenes done: an interrupted run resumes with the scenes no shard
covers, so no sample is lost or written twice; asking for more scenes later extends the run.

Beyond one process: shards follow a fixed grid of `scenes_per_shard` scenes from the first scene
(`scene_blocks`), and a scene's samples depend only on (config, scene index), so the grid's blocks can
be labelled anywhere, in any order. `label(..., shard=(K, N))` takes block b when b % N == K (a job
array's worker K of N writing to one shared directory); `train.label_ray` hands blocks to Ray actors.
Either way the directory ends up with the files of one serial run (docs/labelling-at-scale.md).
"""

from __future__ import annotations

import dataclasses
import json
import os
import re
import socket
import time
from collections.abc import Callable, Sequence
from typing import Any, ClassVar

import numpy as np

from envs import camera as camera_lib
from envs import scene as scene_lib
from envs import sensors
from envs import sealed
from envs.outcome import Outcome
from envs.trial import TrialConfig, check_backend, run_grasp_with_refinements
from sgjax.geometry.gripper import GripperSpec
from sgjax.geometry.gripper_files import gripper_from_dict, gripper_to_dict
from sgjax.perception import PerceptionError
from sgjax.samplers.gpd import GPDConfig
from sgjax.stage1.pipeline import Stage1, Stage1Config
from sgjax.stage2.scene_cloud import SceneCloudConfig
from sgjax.utils.configs import from_dict
from sgjax.utils.files import atomic_write_text
from train import dataset, sources

CONFIG_FILE = "label_config.json"
GRIPPER_ENTRY = "gripper"  # label_config.json: the whole gripper (`gripper_to_dict`), for a non-default gripper
SHARD_PATTERN = re.compile(r"^scenes-(\d{6})-(\d{6})\.npz$")
# Seen objects never trained on (one thin, one round, one box-like, one flat extrusion): every
# held_out_object_every-th scene is built around them, and no other scene contains them.
SEEN_HELD_OUT = ("ycb/044_flat_screwdriver", "ycb/058_golf_ball", "ycb/073-c_lego_duplo", "procedural/extrusion_011")
DEFAULT_PER_SOURCE = (("stage1", 8), ("stage1_paper", 8), ("gpd", 8), ("perturbed", 8))


@dataclasses.dataclass(frozen=True)
class LabelConfig:
    """How samples are made (everything that changes the data; saved with it).

    n_objects: objects per scene (paper: 5). targets_per_scene: objects whose grasps are executed.
    per_source: (source, grasps) pairs: per target, that many grasps drawn at random from each source
    (`train.sources.DRAWN`; fewer when a source has fewer), each with its 3 refinements (4 trials).
    scenes_per_shard: scenes per output file (the resume granularity).
    min_target_points: a target must show at least this many camera points (Stage 1's own minimum).
    held_out_objects / held_out_object_every: see the module docstring; () for none.
    voxel, max_scene_points, workspace_margin: the Stage-2 scene cloud (`scene_cloud`, a
    `sgjax.stage2.scene_cloud.SceneCloudConfig`) cropped to the workspace plus this margin.
    sensor: the depth the samples are made from (`envs.sensors`): "exact" (the exact render) or a sensor
    model's frame seen through the front end of a real frame with perfect masks
    (`envs.sensors.sensed_observation`), so that E-RNet can learn a real camera's crops.
    """

    n_objects: int = 5
    targets_per_scene: int = 2
    per_source: tuple[tuple[str, int], ...] = DEFAULT_PER_SOURCE
    scenes_per_shard: int = 4
    min_target_points: int = 50
    object_set: str = "seen"
    held_out_objects: tuple[str, ...] = SEEN_HELD_OUT
    held_out_object_every: int = 20
    seed: int = 0
    voxel: float = SceneCloudConfig.voxel
    max_scene_points: int = SceneCloudConfig.max_points
    workspace_margin: float = scene_lib.WORKSPACE_MARGIN
    scene: scene_lib.SceneConfig = scene_lib.SceneConfig()
    camera: camera_lib.CameraConfig = camera_lib.CameraConfig()
    trial: TrialConfig = TrialConfig()
    stage1: Stage1Config = Stage1Config()
    # 32 x 7 samples per target on its neighbourhood (the benchmark's gpd method draws 128 x 7 on the
    # whole scene): a few kept grasps per target are all a label source needs, at a fraction of the cost.
    gpd: GPDConfig = GPDConfig(num_samples=32, max_points=2048)
    perturbation: sources.Perturbation = sources.Perturbation()
    sensor: str = "exact"
    # Retired (docs/experiments.md): the relabelled-matches source's count; a saved default still loads.
    RETIRED_FIELDS: ClassVar[dict] = {"relabel_extra": 5}

    def __post_init__(self):
        for name in ("n_objects", "targets_per_scene", "scenes_per_shard", "min_target_points", "max_scene_points"):
            if getattr(self, name) < 1:
                raise ValueError(f"LabelConfig.{name} must be >= 1, got {getattr(self, name)}")
        if self.held_out_object_every < 2:
            raise ValueError(f"LabelConfig.held_out_object_every must be >= 2, got {self.held_out_object_every}")
        per_source = tuple((str(name), int(count)) for name, count in self.per_source)
        for name, count in per_source:
            sources.source_index(name)  # raises naming the known sources
            if name not in sources.DRAWN:
                raise ValueError(f"LabelConfig.per_source: {name} only names samples of directories labelled by "
                                 f"earlier versions; the sources drawn are {', '.join(sources.DRAWN)}")
            if count < 0:
                raise ValueError(f"LabelConfig.per_source: {name} must have >= 0 grasps, got {count}")
        if len({name for name, _ in per_source}) != len(per_source) or not any(c for _, c in per_source):
            raise ValueError(f"LabelConfig.per_source must name each source once and ask for some grasps, got {per_source}")
        sensors.get_sensor(self.sensor)  # raises naming the sensors
        sealed.check_labelling(self.object_set, self.seed)
        if self.gpd.spec != self.spec:
            raise ValueError("LabelConfig.gpd.spec differs from the Stage-1 gripper spec")
        object.__setattr__(self, "per_source", per_source)
        object.__setattr__(self, "held_out_objects", tuple(str(n) for n in self.held_out_objects))

    @property
    def spec(self) -> GripperSpec:
        return self.stage1.spec

    @property
    def grasps_per_target(self) -> int:
        return sum(count for _, count in self.per_source)

    @property
    def scene_cloud(self) -> SceneCloudConfig:
        """The Stage-2 scene cloud: cropped to the workspace grown by workspace_margin."""
        return scene_lib.stage2_scene_cloud(self.scene, self.workspace_margin, max_points=self.max_scene_points, voxel=self.voxel)

    def held_out_scene(self, index: int) -> bool:
        """Whether scene `index` is built around the held-out objects."""
        return bool(self.held_out_objects) and index % self.held_out_object_every == self.held_out_object_every - 1

    def with_gripper(self, gripper: GripperSpec) -> LabelConfig:
        """This config labelling with `gripper`: Stage 1's and the GPD-style sampler's spec (the two that
        must agree), which the simulated gripper of every scene is built from too (`labelled_scene`)."""
        if self.spec == gripper and self.gpd.spec == gripper:
            return self
        return dataclasses.replace(self, stage1=dataclasses.replace(self.stage1, spec=gripper),
                                   gpd=dataclasses.replace(self.gpd, spec=gripper))

    def to_json(self) -> str:
        """The config as label_config.json holds it: `dataclasses.asdict`, which keeps a GripperSpec's
        geometry only, and for any gripper but the default one a "gripper" entry, the whole spec as a
        gripper file's table (`gripper_to_dict`: its closing force and pad friction too). A default
        gripper's config is written as it always was."""
        data = dataclasses.asdict(self)
        if self.spec != GripperSpec():
            data[GRIPPER_ENTRY] = gripper_to_dict(self.spec)
        return json.dumps(data, sort_keys=True, default=str)

    @classmethod
    def from_json(cls, text: str) -> LabelConfig:
        """The config `to_json` wrote (ValueError naming a field this version does not know, or a
        "gripper" entry that does not read or disagrees with stage1.spec's geometry). Without a
        "gripper" entry (the default gripper, and every directory written before the entry existed) the
        gripper is stage1.spec with the default closing force and friction."""
        data = json.loads(text)
        record = data.pop(GRIPPER_ENTRY, None) if isinstance(data, dict) else None
        config = from_dict(cls, data)  # ValueError for anything but a mapping of fields
        if record is None:
            return config
        gripper = gripper_from_dict(record, f"{CONFIG_FILE}: {GRIPPER_ENTRY}")
        if dataclasses.asdict(gripper) != dataclasses.asdict(config.spec):
            raise ValueError(f"{CONFIG_FILE}: its {GRIPPER_ENTRY} entry and stage1.spec are different grippers")
        return config.with_gripper(gripper)



# ---------------------------------------------------------------------------------------------
# The label options of `sgjax label`, shared by the CLI and recipes.


def parse_per_source(text: str, field: str = "--per-source") -> tuple[tuple[str, int], ...]:
    """"stage1=8,gpd=4" -> (("stage1", 8), ("gpd", 4)); ValueError naming `field` for a malformed item."""
    out = []
    for item in text.split(","):
        name, _, count = item.partition("=")
        if not count.strip().isdigit():
            raise ValueError(f"{field}: {item!r} is not SOURCE=COUNT (e.g. stage1=8,gpd=8)")
        out.append((name.strip(), int(count)))
    return tuple(out)


def label_config(
    *,
    objects: str = "seen",
    seed: int = 0,
    camera: str = "exact",
    n_objects: int = 5,
    targets_per_scene: int = 2,
    per_source: str | None = None,
    held_out_objects: str | None = None,
    note: Callable[[str], None] | None = None,
    gripper: GripperSpec | None = None,
):
    """The `train.label.LabelConfig` of `sgjax label`'s options (the CLI and recipes both build it here:
    a labelled directory compares its stored config with the requested one, so a recipe resumes a set
    that `sgjax label` started only if both make the same config).

    per_source: "SOURCE=N,..." (None: LabelConfig's default); held_out_objects: "NAME,..." or ""/"none"
    for none (None: the default held-out objects for the seen set, none for other sets, said through
    `note`); gripper: the gripper to label with (`LabelConfig.with_gripper`; None: the default one).
    Raises ValueError naming the option.
    """
    extra: dict[str, Any] = {}
    if per_source is not None:
        extra["per_source"] = parse_per_source(per_source)
    if held_out_objects is not None:
        extra["held_out_objects"] = () if held_out_objects in ("", "none") else tuple(held_out_objects.split(","))
    elif objects != "seen":  # the default held-out objects are seen-set members
        extra["held_out_objects"] = ()
        if note is not None:
            note(f"no held-out objects in {objects!r} (name some with --held-out-objects)")
    config = LabelConfig(
        n_objects=n_objects, targets_per_scene=targets_per_scene, object_set=objects, seed=seed, sensor=camera, **extra
    )
    return config if gripper is None else config.with_gripper(gripper)

def read_config(out_dir: str | os.PathLike) -> LabelConfig:
    """The LabelConfig a labelled directory was made with (its label_config.json)."""
    path = os.path.join(os.fspath(out_dir), CONFIG_FILE)
    if not os.path.exists(path):
        raise FileNotFoundError(f"{path} not found: not a labelled directory (sgjax label --out)")
    with open(path) as fh:
        return LabelConfig.from_json(fh.read())


def directory_gripper(directory: str | os.PathLike) -> GripperSpec:
    """The whole gripper a labelled directory was made with: its label_config.json's "gripper" entry, else
    (the default gripper, a directory written before the entry existed) its stage1.spec with the default
    force and friction; the default gripper without a label_config.json. Only the gripper is read, so
    a config this version would not read whole still gives it (as `train.dataset.directory_spec`)."""
    path = os.path.join(os.fspath(directory), CONFIG_FILE)
    if not os.path.exists(path):
        return GripperSpec()
    with open(path) as fh:
        saved = json.load(fh)
    record = saved.get(GRIPPER_ENTRY) if isinstance(saved, dict) else None
    if record is not None:
        return gripper_from_dict(record, f"{path}: {GRIPPER_ENTRY}")
    try:
        return from_dict(GripperSpec, saved["stage1"]["spec"])
    except (KeyError, TypeError) as exc:
        raise ValueError(f"{path}: no readable stage1.spec ({exc!r})") from None


def data_gripper(directories: str | os.PathLike | Sequence[str | os.PathLike]) -> GripperSpec:
    """The gripper labelled directories were made with, the whole spec (`directory_gripper`); a
    directory without a label_config.json (shards written otherwise, e.g. `sgjax train --synthetic`)
    counts as the default gripper, as `train.dataset.directory_spec` crops it. Raises ValueError (one
    line) when they were made for different grippers: a network is trained for one."""
    from sgjax.stage2.checkpoint import describe_gripper

    dirs = [directories] if isinstance(directories, (str, os.PathLike)) else list(directories)
    found = {os.fspath(directory): directory_gripper(directory) for directory in dirs}
    specs = list(dict.fromkeys(found.values()))
    if len(specs) > 1:
        first = next(iter(found))
        other = next(d for d, s in found.items() if s != found[first])
        raise ValueError(
            f"the label directories were made for different grippers: {first} for {describe_gripper(found[first], found[other])}, "
            f"{other} for {describe_gripper(found[other], found[first])}: train on directories of one gripper"
        )
    return specs[0] if specs else GripperSpec()


@dataclasses.dataclass
class LabelSummary:
    """What a labelling run produced (all shards in the directory, not only this call's)."""

    scenes: int
    samples: int
    valid_samples: int
    positives: float  # fraction of valid samples with label 1
    refine_positives: list[float]  # per refinement variant
    per_source: dict[str, tuple[int, float]]  # source -> (valid samples, positive rate)
    held_out_object_samples: int
    trials: int
    invalid_trials: int
    outcomes: dict[str, int]
    scenes_without_samples: dict[str, int]  # reason -> scenes
    seconds: float  # simulated-and-computed wall time summed over shards
    trials_per_second: float

    @classmethod
    def empty(cls) -> LabelSummary:
        """The summary of a directory without shards."""
        outcomes = {o.name.lower(): 0 for o in Outcome}
        return cls(0, 0, 0, 0.0, [0.0] * 3, {}, 0, 0, 0, outcomes, {}, 0.0, 0.0)

    def lines(self) -> list[str]:
        skipped = ", ".join(f"{k}: {v}" for k, v in sorted(self.scenes_without_samples.items())) or "none"
        return [
            (
                f"scenes {self.scenes}, samples {self.samples} ({self.valid_samples} valid, "
                f"{self.held_out_object_samples} on held-out objects), positive rate {self.positives:.1%}, "
                "refine positives " + " / ".join(f"{p:.1%}" for p in self.refine_positives)
            ),
            "per source: " + ", ".join(f"{k} {n} ({p:.1%} positive)" for k, (n, p) in self.per_source.items()),
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


@dataclasses.dataclass
class Labellers:
    """What labels a scene: Stage 1 as the planner runs it and Stage 1 with the paper's filters only."""

    stage1: Stage1
    stage1_paper: Stage1

    @classmethod
    def make(cls, config: LabelConfig, stage1: Stage1 | None = None) -> Labellers:
        """stage1: a Stage1 of config.stage1 (default: on the full primitive database)."""
        if stage1 is None:  # the database of the config's gripper (the shipped one for the default gripper)
            from sgjax.stage1.database import DBConfig, load_database

            stage1 = Stage1(load_database(DBConfig.for_gripper(config.spec)), config.stage1)
        if stage1.config != config.stage1:
            raise ValueError("stage1.config differs from config.stage1")
        return cls(stage1, Stage1(stage1.db, sources.paper_filters(config.stage1)))


def scene_objects(index: int, objects: Sequence, config: LabelConfig, rng: np.random.Generator) -> tuple[list, int]:
    """The objects scene `index` is drawn from and how many it holds: the training objects, or (a
    held-out-object scene) one or two held-out objects plus training objects, all of them placed."""
    held = set(config.held_out_objects)
    train_pool = [o for o in objects if o.name not in held]
    if not config.held_out_scene(index):
        return train_pool, config.n_objects
    held_pool = [o for o in objects if o.name in held]
    k = min(len(held_pool), config.n_objects, int(rng.integers(1, 3)))
    chosen = [held_pool[i] for i in rng.choice(len(held_pool), k, replace=False)]
    rest = config.n_objects - k
    if rest:
        chosen += [train_pool[i] for i in rng.choice(len(train_pool), rest, replace=rest > len(train_pool))]
    return chosen, len(chosen)


def _pick(rng: np.random.Generator, n: int, k: int) -> np.ndarray:
    return np.sort(rng.choice(n, size=min(k, n), replace=False)) if n else np.zeros(0, np.int64)


def scene_candidates(
    obs, visible: np.ndarray, order: np.ndarray, labellers: Labellers, config: LabelConfig, seed: int
) -> tuple[list[int], dict[str, dict[int, tuple[np.ndarray, np.ndarray]]]]:
    """The targets and every non-perturbed source's candidates on them: (targets, {source: {target:
    (poses, widths)}}). Stage 1 runs on every visible object in one call; the GPD-style sampler, the
    costliest per object, only on the objects of `order` (candidate targets, in preference order) until
    targets_per_scene of them have a candidate from some source."""
    wanted = {name for name, count in config.per_source if count}
    perturbed = "perturbed" in wanted
    clouds = [obs.object_cloud(int(k)) for k in visible]
    clouds += [clouds[0]] * (config.n_objects - len(clouds))  # padded to n_objects clouds: one compile
    views = np.tile(np.asarray(config.camera.position, np.float32), (len(clouds), 1))
    found: dict[str, dict[int, tuple[np.ndarray, np.ndarray]]] = {}
    for name, stage1, scenes in (
        ("stage1", labellers.stage1, [obs.points] * len(clouds)),
        ("stage1_paper", labellers.stage1_paper, None),
    ):
        if name in wanted or perturbed:
            batch = stage1.batch(clouds, scenes, views, seed % (2**31), scene_lib.TABLE_PLANE)[: len(visible)]
            found[name] = {int(k): (c.poses, c.widths) for k, c in zip(visible, batch)}
    targets: list[int] = []
    use_gpd = "gpd" in wanted or perturbed
    if use_gpd:
        found["gpd"] = {}
    for k in (int(k) for k in order):
        if len(targets) == config.targets_per_scene:
            break
        if use_gpd:
            found["gpd"].update(
                sources.gpd_candidates(obs.points, obs.point_labels, [k], config.camera.position, (seed + k) % (2**31), config.gpd)
            )
        if any(len(f[k][0]) for f in found.values()):
            targets.append(k)
    return targets, found


def choose_grasps(
    found: dict[str, dict[int, tuple[np.ndarray, np.ndarray]]], target: int, config: LabelConfig, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The grasps executed on `target`: (poses [G, 4, 4], widths [G], source codes [G]), per_source many
    of each source drawn at random; perturbed ones from everything the other sources offer."""
    poses, widths, codes = [], [], []
    pool = [found[name][target] for name in found if len(found[name][target][0])]
    for name, count in config.per_source:
        if not count:
            continue
        if name == "perturbed":
            if not pool:
                continue
            all_poses = np.concatenate([p for p, _ in pool])
            all_widths = np.concatenate([w for _, w in pool])
            pick = rng.integers(0, len(all_poses), count)
            chosen = sources.perturb(all_poses[pick], rng, config.spec, config.perturbation), all_widths[pick]
        else:
            p, w = found[name][target]
            pick = _pick(rng, len(p), count)
            chosen = p[pick], w[pick]
        poses.append(np.asarray(chosen[0], np.float64))
        widths.append(np.clip(np.asarray(chosen[1], np.float64), 0.0, config.spec.max_opening))
        codes.append(np.full(len(chosen[0]), sources.source_index(name), np.int8))
    if not poses:
        return np.zeros((0, 4, 4)), np.zeros(0), np.zeros(0, np.int8)
    return np.concatenate(poses), np.concatenate(widths), np.concatenate(codes)


def _no_samples() -> tuple[dict[str, np.ndarray], np.ndarray]:
    return dataset.empty_labels(), np.zeros((0, 3), np.float32)


def labelled_scene(index: int, objects: Sequence, config: LabelConfig) -> tuple[scene_lib.Scene, np.random.Generator]:
    """Scene `index` of a labelling run, rebuilt exactly (it depends only on the config, the objects
    and the index) -> (the settled scene, the scene's random generator as labelling goes on with it).
    Its samples' grasps replay on it to their recorded outcomes.
    Raises ValueError when a mesh cannot be loaded."""
    seed = scene_seed(config.seed, index)
    rng = np.random.default_rng(seed)
    pool, n_objects = scene_objects(index, objects, config, rng)
    return scene_lib.make_scene(pool, n_objects, seed, config.scene, config.spec), rng


def label_scene(
    index: int, objects: Sequence, labellers: Labellers, config: LabelConfig, backend: str = "cpu", nthread: int = 0
) -> tuple[dict[str, np.ndarray], np.ndarray, dict]:
    """Scene `index` -> (samples: fields of LABEL_FIELDS [S, ...] (cloud_row 0), its Stage-2 cloud
    [C, 3] (the real points, shuffled), statistics)."""
    seed = scene_seed(config.seed, index)
    held_scene = config.held_out_scene(index)
    stats = {"scene": index, "scene_seed": seed, "trials": 0, "outcomes": {}, "skipped": None, "held_out_objects": held_scene}
    timing = stats["seconds"] = {}
    began = time.perf_counter()
    try:
        scene, rng = labelled_scene(index, objects, config)
    except ValueError as exc:  # an unloadable mesh; recorded, the run goes on
        stats["skipped"] = f"scene failed: {exc}"
        return (*_no_samples(), stats)
    try:
        obs = sensors.sensed_observation(scene, config.camera, config.sensor, seed=seed)
    except PerceptionError as exc:  # a sensor's frame the front end cannot use; recorded, the run goes on
        stats["skipped"] = f"front end: {exc}"
        return (*_no_samples(), stats)
    timing["scene"] = time.perf_counter() - began
    counts = np.bincount(obs.point_labels[obs.point_labels >= 0], minlength=scene.n_objects)
    visible = np.flatnonzero((counts >= config.min_target_points) & scene.present)
    held = np.array([scene.assets[k].name in config.held_out_objects for k in range(scene.n_objects)], bool)
    eligible = visible[held[visible]] if held_scene else visible
    if len(eligible) == 0:
        stats["skipped"] = "no visible target"
        return (*_no_samples(), stats)
    mark = time.perf_counter()
    targets, found = scene_candidates(obs, visible, rng.permutation(eligible), labellers, config, seed)
    timing["candidates"] = time.perf_counter() - mark
    if not targets:
        stats["skipped"] = "no candidates"
        return (*_no_samples(), stats)
    parts = [(t, *choose_grasps(found, t, config, rng)) for t in targets]
    target_of = np.concatenate([np.full(len(p), t) for t, p, _, _ in parts])
    poses = np.concatenate([p for _, p, _, _ in parts])
    widths = np.concatenate([w for _, _, w, _ in parts])
    codes = np.concatenate([c for _, _, _, c in parts])
    mark = time.perf_counter()
    labels, result = run_grasp_with_refinements(
        scene, target_of, poses, widths, backend=backend, config=config.trial, nthread=nthread
    )
    timing["trials"] = time.perf_counter() - mark
    outcome = result.outcome.reshape(len(poses), -1)
    stats["trials"] = int(outcome.size)
    stats["outcomes"] = result.counts()
    stats["targets"] = [scene.assets[t].name for t in targets]

    mark = time.perf_counter()
    cloud, mask, _ = stage2_cloud(obs.points, config, seed=seed)
    order = rng.permutation(len(cloud))  # crops keep the first region points in scene order: shuffle once
    cloud = cloud[order][mask[order]].astype(np.float32)
    g = len(poses)
    samples = {
        "pose": poses.astype(np.float32),
        "width": widths.astype(np.float32),
        "label": labels[:, 0].astype(np.int8),
        "refine_labels": labels[:, 1:].astype(np.int8),
        "outcome": outcome[:, 0].astype(np.int8),
        "refine_outcomes": outcome[:, 1:].astype(np.int8),
        "source": codes,
        "scene_seed": np.full(g, seed, np.int64),
        "scene_index": np.full(g, index, np.int32),
        "cloud_row": np.zeros(g, np.int32),
        "object_name": np.array([scene.assets[t].name for t in target_of]),
        "held_out_object": held[target_of],
        "valid": ~(outcome == Outcome.INVALID).any(axis=1),
    }
    timing["cloud"] = time.perf_counter() - mark
    return samples, cloud, stats


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


def parse_shard(text: str) -> tuple[int, int]:
    """"K/N" -> (K, N): worker K of N (0 <= K < N); ValueError names what is wrong."""
    k, slash, n = str(text).partition("/")
    if not slash or not k.strip().isdigit() or not n.strip().isdigit():
        raise ValueError(f"--shard must be K/N with whole numbers, e.g. 0/4, got {text!r}")
    return check_shard((int(k), int(n)))


def check_shard(shard: tuple[int, int]) -> tuple[int, int]:
    """-> (K, N) as ints, or ValueError unless N >= 1 and 0 <= K < N."""
    k, n = (int(v) for v in shard)
    if n < 1 or not 0 <= k < n:
        raise ValueError(f"shard K/N needs N >= 1 and 0 <= K < N (workers are numbered from 0), got {k}/{n}")
    return k, n


def scene_blocks(first_scene: int, n_scenes: int, scenes_per_shard: int) -> list[tuple[int, int]]:
    """The fixed grid of [start, end) blocks over scenes first_scene..n_scenes-1: scenes_per_shard scenes
    each from first_scene on (the last one shorter). Block b goes to worker b mod N of a job array."""
    return [(s, min(s + scenes_per_shard, n_scenes)) for s in range(first_scene, n_scenes, scenes_per_shard)]


def pending_blocks(
    out_dir: str | os.PathLike,
    n_scenes: int,
    config: LabelConfig,
    first_scene: int = 0,
    shard: tuple[int, int] | None = None,
) -> list[tuple[int, int]]:
    """The [start, end) shards still to write: for each grid block (`scene_blocks`; with shard=(K, N)
    only blocks b with b % N == K), the runs of its scenes that no shard in out_dir covers yet.

    In a fresh directory these are exactly the grid blocks, so a serial run, N job-array workers and a
    Ray run all write the same files. A scene belongs to one block and a block to one worker, so no two
    workers of one array ever write the same scene.
    """
    if not 0 <= first_scene < n_scenes:
        raise ValueError(f"need 0 <= first_scene < n_scenes, got first_scene {first_scene} and n_scenes {n_scenes}")
    k, n = check_shard(shard) if shard is not None else (0, 1)
    out_dir = os.fspath(out_dir)
    done = _covered(out_dir) if os.path.isdir(out_dir) else set()
    todo: list[tuple[int, int]] = []
    for b, (start, end) in enumerate(scene_blocks(first_scene, n_scenes, config.scenes_per_shard)):
        if b % n == k:
            todo += _runs([i for i in range(start, end) if i not in done], config.scenes_per_shard)
    return todo


def same_config(saved: str, config: LabelConfig) -> bool:
    """Whether label_config.json text `saved` is `config`: the same text, or read back (`from_json`) an
    equal config, the whole gripper included (closing force and friction: `GripperSpec.__eq__`). Compared
    as configs, not as text: a field added since (at its default) reads back the same, and a directory
    written before the "gripper" entry existed reads back as the default gripper."""
    if saved == config.to_json():
        return True
    try:
        return LabelConfig.from_json(saved) == config
    except ValueError:  # a field this version does not know, a gripper entry that does not read
        return False


def check_out_dir(out_dir: str, config: LabelConfig) -> None:
    """Create out_dir with `label_config.json`, or check that the config saved there is `config`;
    ValueError if it holds data made with another config."""
    path = os.path.join(out_dir, CONFIG_FILE)
    text = config.to_json()
    if not os.path.exists(path):
        os.makedirs(out_dir, exist_ok=True)
        atomic_write_text(path, text)
    # Read back even after writing it: workers of a job array starting together on an empty shared
    # directory race to write it, and one with other options must not go on to mix its data in.
    with open(path) as fh:
        saved = fh.read()
    if not same_config(saved, config):
        raise ValueError(
            f"{out_dir} holds data made with a different labelling config ({path}); "
            "use a new --out directory or the same options"
        )


def prepare_objects(config: LabelConfig, objects: Sequence | None = None, progress: bool = True) -> tuple[list, dict]:
    """The object set a labelling run draws from and its identity (recorded with every shard):
    (objects, identity). objects: prepared ObjectAssets (default: `load_object_set(config.object_set)`,
    preparing what the cache lacks). Raises ValueError for an empty set or held-out objects it lacks."""
    from envs.objects import load_object_set, object_set_identity

    if objects is None:  # a named set that lost a member raises ObjectSetError naming it
        objects = load_object_set(config.object_set, progress=progress, workers=os.cpu_count() or 1)
    objects = list(objects)
    if not objects:
        raise ValueError(f"object set {config.object_set!r} is empty")
    identity = object_set_identity(config.object_set, objects)
    names = {o.name for o in objects}
    missing = [n for n in config.held_out_objects if n not in names]
    if missing:
        raise ValueError(
            f"held-out objects {missing} are not in object set {config.object_set!r}; "
            "name members of the set (LabelConfig.held_out_objects, --held-out-objects) or none"
        )
    if len(names - set(config.held_out_objects)) == 0:
        raise ValueError(f"object set {config.object_set!r} has no object left to train on besides the held-out ones")
    return objects, identity


def label_block(
    out_dir: str | os.PathLike,
    start: int,
    end: int,
    objects: Sequence,
    labellers: Labellers,
    config: LabelConfig,
    identity: dict,
    backend: str = "cpu",
    nthread: int = 0,
    on_scene: Callable[[int, int], None] | None = None,
) -> list[dict]:
    """Label scenes [start, end) that no shard in out_dir covers yet and write them as shards (one per run
    of consecutive uncovered scenes; normally the whole block or nothing) -> one record per shard written
    ({"start", "end", "samples", "trials", "seconds", ...}; [] when the block was already on disk).

    Each shard is written atomically (statistics first, samples last: the .npz marks its scenes done),
    so a worker that dies mid-block leaves nothing behind that a rerun would not redo. Samples depend
    only on (config, scene index), never on which process labels a scene or in which order.
    on_scene(index, samples) is called after each scene (progress bars, fault-injection hooks).
    """
    out_dir = os.fspath(out_dir)
    # Checked again here, not only when the work was planned: another worker (a re-queued block whose
    # first owner was only presumed dead) may have finished it meanwhile.
    done = _covered(out_dir)
    records = []
    for run_start, run_end in _runs([i for i in range(start, end) if i not in done], config.scenes_per_shard):
        began = time.perf_counter()
        parts, clouds, stats = [], [], []
        for index in range(run_start, run_end):
            samples, cloud, scene_stats = label_scene(index, objects, labellers, config, backend, nthread)
            if len(samples["label"]):
                samples["cloud_row"][:] = len(clouds)
                parts.append(samples)
                clouds.append(cloud)
            stats.append(scene_stats)
            if on_scene is not None:
                on_scene(index, len(samples["label"]))
        samples = {k: np.concatenate([p[k] for p in parts]) for k in dataset.LABEL_FIELDS} if parts else dataset.empty_labels()
        base = os.path.join(out_dir, f"scenes-{run_start:06d}-{run_end:06d}")
        seconds = time.perf_counter() - began
        worker = f"{socket.gethostname()}:{os.getpid()}"
        record = {"scenes": stats, "seconds": seconds, "objects": identity, "worker": worker}
        atomic_write_text(base + ".json", json.dumps(record))
        dataset.write_label_shard(base + dataset.SHARD_SUFFIX, samples, clouds)  # written last: marks the scenes done
        records.append({
            "start": run_start, "end": run_end, "samples": len(samples["label"]),
            "trials": sum(s["trials"] for s in stats), "seconds": seconds, "worker": worker,
        })
    return records


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
    first_scene: int = 0,
    shard: tuple[int, int] | None = None,
) -> LabelSummary:
    """Label scenes first_scene..n_scenes-1 into `out_dir`, skipping scenes already there; -> the summary.

    objects: prepared ObjectAssets (default: `load_object_set(config.object_set)`); stage1: a Stage1
    (default: the full primitive database). Raises ValueError if out_dir holds data of another config.
    first_scene > 0 continues a series of scenes in a new directory (e.g. after a code change that
    changes the config): training reads several directories of one seed if their scenes are disjoint.
    shard=(K, N): label only the grid blocks of worker K of N (`pending_blocks`), for job arrays whose
    N workers share out_dir; together they write exactly the files of one serial run. The summary
    covers every shard in out_dir (other workers' too).
    """
    if shard is not None:
        shard = check_shard(shard)
    if not 0 <= first_scene < n_scenes:
        raise ValueError(f"need 0 <= first_scene < n_scenes, got first_scene {first_scene} and n_scenes {n_scenes}")
    check_backend(backend)
    out_dir = os.fspath(out_dir)
    check_out_dir(out_dir, config)
    objects, identity = prepare_objects(config, objects, progress)
    labellers = Labellers.make(config, stage1)
    todo = pending_blocks(out_dir, n_scenes, config, first_scene, shard)
    bar = None
    if progress:
        from tqdm import tqdm

        k, n = shard or (0, 1)
        blocks = scene_blocks(first_scene, n_scenes, config.scenes_per_shard)
        total = sum(e - s for b, (s, e) in enumerate(blocks) if b % n == k)
        bar = tqdm(total=total, initial=total - sum(e - s for s, e in todo), unit="scene", desc="label")
    for start, end in todo:
        records = label_block(
            out_dir, start, end, objects, labellers, config, identity, backend, nthread,
            on_scene=None if bar is None else lambda _index, _samples: bar.update(1),
        )
        if bar is not None and records:
            bar.set_postfix(samples=records[-1]["samples"])
    if bar is not None:
        bar.close()
    if not todo and not dataset.shard_paths(out_dir):
        # A job-array worker with no block of its own (more workers than blocks), before any other
        # worker's shard is on disk: nothing to summarise, and nothing wrong.
        return LabelSummary.empty()
    return summarize(out_dir)


def summarize(out_dir: str | os.PathLike) -> LabelSummary:
    """Statistics of every finished shard in a labelling directory."""
    out_dir = os.fspath(out_dir)
    shards = [os.path.join(out_dir, n) for n in sorted(os.listdir(out_dir)) if SHARD_PATTERN.match(n)]
    if not shards:
        raise dataset.DatasetError(f"{out_dir}: no labelled shards")
    fields = ("label", "refine_labels", "valid", "source", "held_out_object")
    read = [dataset.read_label_shard(p)[0] for p in shards]
    samples = {k: np.concatenate([r[k] for r in read]) for k in fields}
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
    per_source = {}
    for code, name in enumerate(sources.SOURCES):
        rows = valid & (samples["source"] == code)
        if rows.any():
            per_source[name] = (int(rows.sum()), float(samples["label"][rows].mean()))
    return LabelSummary(
        scenes=scenes,
        samples=len(valid),
        valid_samples=n_valid,
        positives=float(samples["label"][valid].mean()) if n_valid else 0.0,
        refine_positives=[float(v) for v in samples["refine_labels"][valid].mean(0)] if n_valid else [0.0] * 3,
        per_source=per_source,
        held_out_object_samples=int((valid & samples["held_out_object"]).sum()),
        trials=trials,
        invalid_trials=outcomes["invalid"],
        outcomes=outcomes,
        scenes_without_samples=skipped,
        seconds=seconds,
        trials_per_second=trials / seconds if seconds > 0 else 0.0,
    )
