"""How well a refinement is judged, on labelled scenes: the refine head alone (the paper's rule) against the
refined pose re-scored by the evaluation head (`sgjax.planner.PlannerConfig.refine_rescore`)
(`benchmarks/refine_rescore.py`).

Every labelled sample carries the simulated outcome of each of its K refinements. For each, the refined
pose's enlarged region is cropped from the scene's stored cloud and scored by E-RNet's evaluation head, as
the planner does at run time; the table compares three scores of a refinement on the samples the planner
would refine (evaluation <= the threshold): the refine head's, that evaluation, and their geometric mean
(`rescored_refinement`): ROC AUC against the refinement's outcome, and how many pass the threshold and
how often those succeed (the policy executes a refinement above a fixed 0.7).
"""

from __future__ import annotations

import os

import jax
import numpy as np

from sgjax.geometry import gripper
from sgjax.planner import rescored_refinement
from train import dataset, judgement, sources, trainer
from train.score_data import load_eval_step


def rescore_directory(data: str | os.PathLike, model: str | os.PathLike | None = None, progress: bool = True) -> dict[str, np.ndarray]:
    """E-RNet's scores of every valid sample of a labelled directory and of its refined poses.

    model: a `sgjax train` run directory (None: the shipped default). -> columns [S] (S valid samples):
    eval_prob, refine_prob [S, K], judged [S, K] (the evaluation head's score of the sample's refinement
    k, cropped at the refined pose; 0 where that crop has no anchor point), refine_labels [S, K],
    label, source, scene_seed."""
    from tqdm.auto import tqdm

    scorer, eval_step, params = load_eval_step(model, "ernet")
    crop = getattr(scorer.config, "crop", "enlarged")
    spec = trainer.TrainConfig(model=scorer.config).spec  # the spec the eval step crops with
    key = jax.random.key(0)
    paths = dataset.shard_paths(data)
    if not paths:
        raise dataset.DatasetError(f"{data}: no label shards")
    columns = []
    for path in tqdm(paths, desc="shards", disable=not progress):
        samples, clouds = dataset.read_label_shard(path)
        samples = dataset.select(samples, np.flatnonzero(samples["valid"]))
        if not len(samples["label"]):
            continue
        base = trainer.score_samples(eval_step, params, dataset.crop_samples(samples, clouds, spec, crop), 128, key)[1]
        judged = []
        for k in range(spec.num_refinements):
            moved = {**samples, "pose": np.asarray(gripper.refined_pose(samples["pose"], k, spec), np.float32)}
            out = trainer.score_samples(eval_step, params, dataset.crop_samples(moved, clouds, spec, crop), 128, key)[1]
            judged.append(np.where(out["weight"] > 0, out["prob"], 0.0))
        keep = base["weight"] > 0  # samples with an anchor point at their own pose (the planner's valid)
        columns.append({"eval_prob": base["prob"][keep], "refine_prob": base["refine_prob"][keep],
                        "judged": np.stack(judged, 1)[keep],
                        **{k: np.asarray(samples[k])[keep] for k in ("refine_labels", "label", "source", "scene_seed")}})
    if not columns:
        raise dataset.DatasetError(f"{data}: no valid samples")
    return {k: np.concatenate([c[k] for c in columns]) for k in columns[0]}


def table(columns: dict[str, np.ndarray], threshold: float = 0.7) -> str:
    """Markdown: per group of samples the planner would refine (evaluation <= threshold: all, then per
    source), per score of a refinement (the refine head, the re-evaluation, their geometric mean): ROC AUC
    against the refinements' outcomes, refinements scoring above `threshold` and the share of those that
    succeed; and the same for the best-scored variant of each sample."""
    low = columns["eval_prob"] <= threshold
    head, judged = columns["refine_prob"], columns["judged"]
    scores = {"refine head": head, "evaluation at the refined pose": judged,
              "geometric mean (refine_rescore)": rescored_refinement(head, judged)}
    labels = columns["refine_labels"] == 1
    groups = [("all", low)] + [(name, low & (columns["source"] == i)) for i, name in enumerate(sources.SOURCES)]

    def f(v):
        return "–" if v is None or not np.isfinite(v) else f"{v:.3f}"

    lines = [f"| samples (evaluation <= {threshold:g}) | n | score of a refinement | AUC | refinements > {threshold:g} | "
             "succeed | best variant > {0:g} | succeed |".format(threshold),
             "|---|---:|---|---:|---:|---:|---:|---:|"]
    for name, rows in groups:
        if not rows.any():
            continue
        for score_name, s in scores.items():
            s_rows, y_rows = s[rows], labels[rows]
            passed = s_rows > threshold
            best = np.argmax(s_rows, axis=1)
            best_score, best_label = s_rows[np.arange(len(best)), best], y_rows[np.arange(len(best)), best]
            best_passed = best_score > threshold
            auc = judgement.roc_auc(s_rows.reshape(-1), y_rows.reshape(-1))
            lines.append(f"| {name} | {int(rows.sum())} | {score_name} | {f(auc)} | {int(passed.sum())} | "
                         f"{f(y_rows[passed].mean() if passed.any() else np.nan)} | {int(best_passed.sum())} | "
                         f"{f(best_label[best_passed].mean() if best_passed.any() else np.nan)} |")
    return "\n".join(lines)
