"""The lever arm of labelled grasps: how far each grasp's closing line runs from its target's visible
centroid along the finger width (`sgjax.geometry.gripper.lever_arm`), and what preferring short lever
arms does to the top-scored grasp (`benchmarks/lever_arm.py`; `PlannerConfig.lever_weight`).

E-RNet sees the scene around the fingers, not where the rest of the object's weight lies. A label shard
stores the scene cloud without the camera's segmentation, so each scene is rebuilt (it depends only on
the labelling config, the objects and its index: `train.label.labelled_scene`) and observed again with
the labelling's camera and seed, which gives the same points and their object labels. The target of a
sample is the object of its name on the table (the one nearest the closing region's centre when the
scene holds two of it).
"""

from __future__ import annotations

import os
from collections.abc import Sequence

import jax
import numpy as np
from tqdm import tqdm

from envs import camera as camera_lib
from sgjax.geometry.gripper import closing_centre, lever_arm
from train import dataset, score_data, trainer
from train.label import labelled_scene, prepare_objects, read_config
from train.sources import source_index

COLUMNS = ("row", "scene_seed", "source", "label", "eval_prob", "target", "lever")


def lever_directory(directory: str | os.PathLike, model: str | os.PathLike | None = None,
                    progress: bool = True) -> dict[str, np.ndarray]:
    """Every valid sample of a labelled directory that E-RNet scores (an anchor point in its closing
    region) -> columns [S]: row (in `dataset.read_shards` order), scene_seed, source, label, eval_prob
    (`model`: a run directory, None: the shipped E-RNet), target (the object's index in its scene, -1
    when not found, e.g. after a rebuild on other meshes), lever (metres; NaN without a target or when
    it shows no point)."""
    config = read_config(directory)
    objects, _ = prepare_objects(config, progress=False)
    scorer, eval_step, params = score_data.load_eval_step(model)
    samples = dataset.read_shards([directory], scorer.config.crop)
    per = trainer.score_samples(eval_step, params, samples, 128, jax.random.key(0))[1]
    # read_shards keeps the label shards' order, so their scene indices line up with the crops' rows.
    index = np.concatenate([dataset.read_label_shard(p)[0]["scene_index"] for p in dataset.shard_paths(directory)])
    if len(index) != len(samples["label"]):
        raise dataset.DatasetError(f"{directory}: holds sample shards as well as label shards; give a labelled directory")
    lever = np.full(len(index), np.nan)
    target = np.full(len(index), -1)
    spec = config.spec
    for scene_index in tqdm(np.unique(index), desc="scenes", disable=not progress):
        rows = np.flatnonzero(index == scene_index)
        scene, _ = labelled_scene(int(scene_index), objects, config)
        obs = camera_lib.observe(scene, config.camera, seed=int(samples["scene_seed"][rows[0]]))
        names = [scene.assets[k].name if scene.present[k] else None for k in range(scene.n_objects)]
        coms = scene.object_poses()[:, :3]
        poses = samples["pose"][rows].astype(np.float64)
        centres = closing_centre(poses, spec, xp=np)
        centroids = np.full((len(rows), 3), np.nan)
        for i, (name, centre) in enumerate(zip(samples["object_name"][rows], centres)):
            same = [k for k, n in enumerate(names) if n == name]
            if not same:
                continue
            k = target[rows[i]] = min(same, key=lambda k: np.linalg.norm(coms[k] - centre))
            seen = obs.points[obs.point_labels == k]
            if len(seen):
                centroids[i] = seen.mean(0)
        lever[rows] = lever_arm(poses, centroids, spec, xp=np)
    keep = samples["valid"] & (per["weight"] > 0)
    out = {"row": np.arange(len(index)), "scene_seed": samples["scene_seed"], "source": samples["source"],
           "label": samples["label"].astype(bool), "eval_prob": per["prob"], "target": target, "lever": lever}
    return {k: np.asarray(v)[keep] for k, v in out.items()}


def planner_picks(columns: dict[str, np.ndarray], weight: float, threshold: float = 0.7) -> np.ndarray:
    """The sample the planner executes in each scene with `PlannerConfig.lever_weight` = weight, among the
    given samples (columns of `lever_directory`) -> their indices [scenes], in scene order. The highest
    eval_prob (ties: the first) when it does not pass the threshold; else, among the passing samples on
    that sample's object, the highest eval_prob - weight * lever arm. Weight 0: E-RNet's top sample, as
    `train.judgement.top_success` counts it."""
    e = np.asarray(columns["eval_prob"], np.float64)
    rank = e - weight * np.nan_to_num(columns["lever"], nan=0.0)
    picks = []
    for scene in np.unique(columns["scene_seed"]):
        rows = np.flatnonzero(columns["scene_seed"] == scene)
        best = rows[np.argmax(e[rows])]
        if e[best] > threshold:
            rows = rows[(columns["target"][rows] == columns["target"][best]) & (e[rows] > threshold)]
            best = rows[np.argmax(rank[rows])]
        picks.append(best)
    return np.asarray(picks, np.int64)


def table(columns: dict[str, np.ndarray], weights: Sequence[float] = (0.0, 0.5, 1.0, 2.0, 4.0, 8.0),
          threshold: float = 0.7, bins: Sequence[float] = (0.0, 0.01, 0.02, 0.03, 0.05, np.inf)) -> str:
    """Markdown: per scene, the success of the planner's pick among the Stage-1 samples for each weight;
    and the success of Stage-1 samples E-RNet passes, by lever arm."""
    s1 = columns["source"] == source_index("stage1")
    stage1 = {k: np.asarray(v)[s1] for k, v in columns.items()}
    label, e, arm = stage1["label"], stage1["eval_prob"], stage1["lever"]
    lines = ["| lever weight (per m) | the planner's Stage-1 pick succeeds |", "|---:|---:|"]
    for w in weights:
        lines.append(f"| {w:g} | {label[planner_picks(stage1, w, threshold)].mean():.4f} |")
    lines += ["", f"Stage-1 samples with eval_prob > {threshold:g}, by lever arm:", "",
              "| lever arm (cm) | samples | success |", "|---|---:|---:|"]
    passing = e > threshold
    for lo, hi in zip(bins[:-1], bins[1:]):
        rows = passing & (arm >= lo) & (arm < hi)
        rate = f"{label[rows].mean():.3f}" if rows.any() else "–"
        lines.append(f"| {lo * 100:g}-{hi * 100:g} | {int(rows.sum())} | {rate} |")
    return "\n".join(lines)
