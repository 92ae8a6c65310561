"""Distillation: E-RNet's judgement of exact depth taught to its view through a sensor (`sgjax distill`).

Through a depth sensor E-RNet judges the planner's candidates worse than on the exact render of the same
state: with E-RNet scoring the exact cloud while everything else saw the RealSense model, SuperGrasp's
seen-20 development cells gained 3.2 GSR points (docs/experiments.md, 2026-12-07). A distillation set
hands a student those judgements for the sensor's crops. Per scene (the labelling's scenes,
`train.label.labelled_scene`, of `n_objects[index % len]` objects): the sensor's frame through the front
end (`envs.sensors.front_end`, the planner's first hypothesis), the planner's candidates on it (Stage 1
and the neighbours' fits, every object; `per_scene` of them at random) plus `perturbed` copies (the
robust choice judges perturbed poses too), and the teacher's P(success) and refinements' P(success) of
each on the exact render's Stage-2 cloud of the same state (`Planner.judge`). No grasp is simulated:
1-2 s a scene on 2 cores (600 scenes: 20 min).

Shards are label shards (`train.dataset`, 4 scenes each, written atomically; a rerun skips the written
ones) with soft labels and two clouds a scene, the sensor's Stage-2 cloud and the exact render's: each
candidate once on each, with the same targets, so that on exact depth the student keeps the teacher's
judgement. `sgjax train --data DIR --init TEACHER_RUN` continues the teacher on them.
"""

from __future__ import annotations

import dataclasses
import json
import os
from collections.abc import Sequence

import numpy as np

from envs import sensors
from envs.scene import stage2_scene_cloud
from sgjax import presets
from sgjax.geometry.gripper import GripperSpec
from sgjax.geometry.gripper_files import gripper_to_dict
from sgjax.geometry.pointcloud import table_plane
from sgjax.perception import PerceptionError
from sgjax.planner import Planner
from sgjax.utils.files import atomic_write_text
from train import dataset, sources
from train.label import (DISTILL_CONFIG_FILE, LabelConfig, label_config, labelled_scene, prepare_objects, scene_blocks,
                         scene_seed, shard_base)

CONFIG_FILE = DISTILL_CONFIG_FILE


@dataclasses.dataclass(frozen=True)
class DistillConfig:
    """sensor: the depth the student sees (`envs.sensors`, not "exact"); masks: the front end's objects
    ("clusters": segmented, as a user's frame; "truth": the render's masks); n_objects: scene `index`
    holds n_objects[index % len(n_objects)] objects; per_scene: candidates kept a scene (at random);
    perturbed: perturbed copies of kept ones added (`train.sources.perturb`); seed, objects: the scenes
    (`train.label.LabelConfig`'s); teacher: the teacher's run directory ("": the gripper's shipped
    E-RNet); scenes_per_shard: scenes a shard."""

    sensor: str = "realsense"
    masks: str = "clusters"
    n_objects: tuple[int, ...] = (10, 20)
    per_scene: int = 96
    perturbed: int = 32
    seed: int = 7
    objects: str = "seen"
    teacher: str = ""
    scenes_per_shard: int = 4

    def __post_init__(self):
        sensor = sensors.get_sensor(self.sensor)  # raises naming the sensors
        if sensor.is_exact:
            raise ValueError("distillation teaches a sensor's view: sensor must not be 'exact'")
        if self.masks not in ("truth", "clusters"):
            raise ValueError(f"masks must be 'truth' or 'clusters', got {self.masks!r}")
        if not self.n_objects or min(self.n_objects) < 1:
            raise ValueError(f"n_objects must name one or more counts >= 1, got {self.n_objects}")
        if self.per_scene < 1 or self.perturbed < 0 or self.scenes_per_shard < 1:
            raise ValueError(f"need per_scene >= 1, perturbed >= 0, scenes_per_shard >= 1, got {self.per_scene}, "
                             f"{self.perturbed}, {self.scenes_per_shard}")

    def scenes(self, gripper: GripperSpec | None = None) -> list[LabelConfig]:
        """The LabelConfig of each scene size (n_objects[k]), for `gripper` (None: the default one)."""
        # As `sgjax label` builds them (`label_config`): the seen set's held-out objects stay out of the
        # scenes, another set has none.
        return [label_config(objects=self.objects, seed=self.seed, n_objects=n, gripper=gripper) for n in self.n_objects]


def teacher_planner(config: DistillConfig, gripper: GripperSpec | None = None, db=None) -> Planner:
    """The planner whose candidates and judgement make the set: the default preset for `gripper`, the
    Stage-2 scene cloud as in labelling, the teacher's network (`config.teacher`, or the gripper's shipped one)."""
    spec = GripperSpec() if gripper is None else gripper
    planner_config = presets.get("default", gripper=gripper, scene_cloud=stage2_scene_cloud())
    if db is None and spec != GripperSpec():
        from sgjax.stage1.database import DBConfig, load_database

        db = load_database(DBConfig.for_gripper(spec), progress=False)
    return Planner(model=config.teacher or None, db=db, config=planner_config)


def distill_scene(index: int, objects: Sequence, config: DistillConfig, scene_configs: Sequence[LabelConfig],
                  planner: Planner) -> tuple[dict[str, np.ndarray], list[np.ndarray]] | None:
    """Scene `index` -> (LABEL_FIELDS samples with soft labels, [sensor cloud, exact cloud]) or None when
    the front end finds nothing or no candidate has a point between its fingers. Rows 0..G-1 are the
    candidates on the sensor's cloud (cloud_row 0), rows G..2G-1 the same on the exact one (cloud_row 1)."""
    scene_config = scene_configs[index % len(scene_configs)]
    if scene_config.held_out_scene(index):  # labelling's held-out objects stay out of the student's data too
        return None
    seed = scene_seed(scene_config.seed, index)
    scene, rng = labelled_scene(index, objects, scene_config)
    camera = scene_config.camera
    try:
        sensed = sensors.sense(scene, camera, config.sensor, seed=seed)
        frame = next(sensors.front_end(sensed, camera, config.masks).hypotheses())
    except PerceptionError:
        return None
    points, labels = frame.table_and_objects()
    points = points.astype(np.float64)
    plane = table_plane(points, labels)
    base = planner.config
    if plane is not None:  # as the benchmark's harness plans a frame: its table the support plane
        planner.config = dataclasses.replace(base, support_plane=plane)
    try:
        plan = planner.plan(points, labels, np.asarray(camera.position, np.float64), seed)
    finally:
        planner.config = base
    found = [c for c in plan.candidates if c is not None and len(c.widths)]
    if not found:
        return None
    poses = np.concatenate([np.asarray(c.poses, np.float64).reshape(-1, 4, 4) for c in found])
    widths = np.concatenate([np.asarray(c.widths, np.float64) for c in found])
    keep = rng.permutation(len(poses))[: config.per_scene]
    poses, widths = poses[keep], widths[keep]
    if config.perturbed:
        copies = rng.integers(0, len(poses), config.perturbed)
        poses = np.concatenate([poses, sources.perturb(poses[copies], rng, base.spec)])
        widths = np.concatenate([widths, widths[copies]])
    widths = np.clip(widths, 0.0, base.spec.max_opening)
    exact = np.asarray(sensed.truth.points, np.float64)
    judged = planner.judge(exact, poses, widths, seed)
    ok = judged["valid"]
    if not ok.any():
        return None
    poses, widths = poses[ok].astype(np.float32), widths[ok].astype(np.float32)
    eval_prob, refine_prob = judged["eval_prob"][ok], judged["refine_prob"][ok]
    g = len(poses)
    twice = lambda a: np.concatenate([a, a])
    samples = {
        "pose": twice(poses),
        "width": twice(widths),
        "label": twice(np.clip(eval_prob, 0.0, 1.0).astype(np.float32)),
        "refine_labels": twice(np.clip(refine_prob, 0.0, 1.0).astype(np.float32)),
        "outcome": np.full(2 * g, -1, np.int8),  # no trial was run
        "refine_outcomes": np.full((2 * g, refine_prob.shape[1]), -1, np.int8),
        "source": np.full(2 * g, sources.source_index("stage1"), np.int8),
        "scene_seed": np.full(2 * g, seed, np.int64),
        "scene_index": np.full(2 * g, index, np.int32),
        "cloud_row": np.repeat(np.arange(2, dtype=np.int32), g),
        "object_name": np.full(2 * g, ""),
        "held_out_object": np.zeros(2 * g, bool),
        "valid": np.ones(2 * g, bool),
    }
    clouds = [planner.stage2_cloud(points, seed), planner.stage2_cloud(exact, seed)]
    return samples, clouds


def _check_out_dir(out_dir: str, config: DistillConfig, gripper: GripperSpec) -> None:
    """Write the set's config, or refuse a directory made with another one (its shards would not match)."""
    path = os.path.join(out_dir, CONFIG_FILE)
    mine = {"distill": dataclasses.asdict(config), "gripper": gripper_to_dict(gripper)}  # read by `label.directory_gripper`
    text = json.dumps(mine, indent=1, sort_keys=True, default=list)
    if os.path.exists(path):
        with open(path) as f:
            if json.load(f) != json.loads(text):
                raise ValueError(f"{out_dir} holds a distillation set made with another config ({path}); "
                                 "give another --out")
        return
    atomic_write_text(path, text)


def distill(first: int, end: int, out_dir: str | os.PathLike, config: DistillConfig = DistillConfig(),
            gripper: GripperSpec | None = None, objects: Sequence | None = None, planner: Planner | None = None,
            progress: bool = True) -> list[str]:
    """Scenes first..end-1 into label shards in out_dir (resumable: written shards are skipped) -> the
    shards written now. objects: the scene objects (default: `config.objects` prepared as labelling does);
    planner: the teacher's (default `teacher_planner`)."""
    from tqdm import tqdm

    spec = GripperSpec() if gripper is None else gripper
    out_dir = os.fspath(out_dir)
    os.makedirs(out_dir, exist_ok=True)
    _check_out_dir(out_dir, config, spec)
    scene_configs = config.scenes(gripper)
    if objects is None:
        objects, _ = prepare_objects(scene_configs[0], progress=progress)
    blocks = [(a, b) for a, b in scene_blocks(first, end, config.scenes_per_shard)
              if not os.path.exists(os.path.join(out_dir, _shard_name(a, b)))]
    if blocks and planner is None:
        planner = teacher_planner(config, gripper)
    written = []
    for a, b in tqdm(blocks, desc="distill", unit="shard", disable=not progress):
        scenes = [distill_scene(index, objects, config, scene_configs, planner) for index in range(a, b)]
        columns, clouds = dataset.join_scenes([scene for scene in scenes if scene is not None])
        path = os.path.join(out_dir, _shard_name(a, b))
        dataset.write_label_shard(path, columns, clouds)
        written.append(path)
    return written


def _shard_name(first: int, end: int) -> str:
    """The shard of scenes [first, end), named as labelling names its shards."""
    return shard_base(first, end) + dataset.SHARD_SUFFIX
