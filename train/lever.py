"""The lever arm of labelled grasps: how far each grasp's closing line runs from its target's visible
centroid along the finger width (`sgjax.geometry.gripper.lever_arm`), and what preferring short lever
arms does to the top-scored grasp (`benchmarks/lever_arm.py`; `PlannerConfig.lever_weight`). Beside it,
where the superquadric Stage 1 fits to the target's visible cloud puts the object's centre (the fit
completes the hidden side), as an offset in the grasp frame (`fit_offset`, `fit_table`).

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
from sgjax.geometry import pointcloud
from sgjax.geometry.gripper import closing_centre, lever_arm
from sgjax.stage1 import ems
from train import dataset, judgement, score_data, trainer
from train.label import labelled_scene, prepare_objects, read_config
from train.sources import source_index

COLUMNS = ("row", "scene_seed", "source", "label", "eval_prob", "target", "lever", "fit_offset")
MIN_FIT_POINTS = 10  # fewer visible points than this: no fit (as Stage 1, whose EMS needs a few)


def lever_directory(directory: str | os.PathLike, model: str | os.PathLike | None = None,
                    progress: bool = True) -> dict[str, np.ndarray]:
    """Every valid sample of a labelled directory that E-RNet scores (an anchor point in its closing
    region) -> columns [S]: row (in `dataset.read_shards` order), scene_seed, source, label, eval_prob
    (`model`: a run directory, None: the shipped E-RNet), target (the object's index in its scene, -1
    when not found, e.g. after a rebuild on other meshes), lever (metres; NaN without a target or when
    it shows no point), fit_offset [S, 3] (metres, grasp frame: the centre of the superquadric fitted to
    the target's visible points, with the camera as viewpoint and Stage 1's EMS settings, minus the
    closing region's centre; NaN without a target or with fewer than MIN_FIT_POINTS points)."""
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
    fit_offset = np.full((len(index), 3), np.nan)
    spec, stage1 = config.spec, config.stage1
    viewpoint = np.asarray(config.camera.position, np.float32)
    for scene_index in tqdm(np.unique(index), desc="scenes", disable=not progress):
        rows = np.flatnonzero(index == scene_index)
        scene, _ = labelled_scene(int(scene_index), objects, config)
        obs = camera_lib.observe(scene, config.camera, seed=int(samples["scene_seed"][rows[0]]))
        names = [scene.assets[k].name if scene.present[k] else None for k in range(scene.n_objects)]
        coms = scene.object_poses()[:, :3]
        visible = [obs.points[obs.point_labels == k] for k in range(scene.n_objects)]  # each object's points
        poses = samples["pose"][rows].astype(np.float64)
        centres = closing_centre(poses, spec, xp=np)
        centroids = np.full((len(rows), 3), np.nan)
        for i, (name, centre) in enumerate(zip(samples["object_name"][rows], centres)):
            same = [k for k, n in enumerate(names) if n == name]
            if not same:
                continue
            k = target[rows[i]] = min(same, key=lambda k: np.linalg.norm(coms[k] - centre))
            if len(visible[k]):
                centroids[i] = visible[k].mean(0)
        lever[rows] = lever_arm(poses, centroids, spec, xp=np)
        fitted = [k for k in np.unique(target[rows]) if k >= 0 and len(visible[k]) >= MIN_FIT_POINTS]
        if fitted:
            # One batch per scene, padded to the scene's object count so that every scene reuses one compile.
            limit = stage1.max_object_points
            clouds = [pointcloud.downsample(visible[k], limit, 0) for k in fitted]
            clouds += [clouds[0]] * (scene.n_objects - len(clouds))
            batch, mask = pointcloud.pad_clouds(clouds, limit, n_points=limit)
            centre = np.asarray(ems.fit_superquadrics(batch, mask, stage1.ems, viewpoint).translation, np.float64)
            for i, row in enumerate(rows):
                if target[row] in fitted:
                    fit_offset[row] = poses[i, :3, :3].T @ (centre[fitted.index(target[row])] - centres[i])
    keep = samples["valid"] & (per["weight"] > 0)
    out = {"row": np.arange(len(index)), "scene_seed": samples["scene_seed"], "source": samples["source"],
           "label": samples["label"].astype(bool), "eval_prob": per["prob"], "target": target, "lever": lever,
           "fit_offset": fit_offset}
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


def fit_table(columns: dict[str, np.ndarray], weights: Sequence[float] = (0.0, 0.5, 1.0, 2.0, 4.0),
              confident: float = 0.85) -> str:
    """Markdown: among Stage-1 samples scored above `confident` with a fit, the AUC of success against
    failure for the fitted centre's offset (|offset| along each grasp axis, smaller = better) and for the
    score itself; and per scene, the success of the top Stage-1 sample ranked by logit(eval_prob) - w *
    |offset along x| (cm; x: the closing axis; no penalty without a fit). Weight 0 is E-RNet's top grasp."""
    s1 = columns["source"] == source_index("stage1")
    label, e, off = columns["label"][s1], columns["eval_prob"][s1].astype(np.float64), columns["fit_offset"][s1]
    sure = (e > confident) & np.isfinite(off[:, 0])
    aucs = [judgement.roc_auc(-np.abs(off[sure, a]), label[sure]) for a in range(3)]
    cell = lambda v: "–" if v is None else f"{v:.3f}"  # noqa: E731
    lines = [f"Stage-1 samples scored above {confident:g} with a fit ({int(sure.sum())}): AUC of success against "
             "failure",
             "", "| score | fit offset x (closing) | y (finger width) | z (approach) |", "|---:|---:|---:|---:|",
             f"| {cell(judgement.roc_auc(e[sure], label[sure]))} | {' | '.join(cell(v) for v in aucs)} |", "",
             "| weight (per cm of x offset) | top Stage-1 sample succeeds |", "|---:|---:|"]
    p = np.clip(e, 1e-6, 1 - 1e-6)
    logit, penalty = np.log(p / (1 - p)), 100 * np.nan_to_num(np.abs(off[:, 0]), nan=0.0)
    for w in weights:
        rate = judgement.top_success(logit - w * penalty, label, columns["scene_seed"][s1])
        lines.append(f"| {w:g} | {cell(rate)} |")
    return "\n".join(lines)
