"""Judge a trained scorer on a labelled directory: `sgjax score-data` (any checkpoint, any labels).

The trainer reports its judgement metrics on its own held-out split after every epoch; this scores
any checkpoint (the shipped default, a run directory, the PointNetGPD baseline) on any labelled
directory, e.g. labels of a new seed that no checkpoint was trained on. Samples are cropped as the
network expects (`ERNetConfig.crop`), scored with the trainer's own evaluation step (no noise, a fixed
downsampling key), and judged by `train.judgement.judge` in three groups: all valid samples, the
held-out objects only, and the rest.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from typing import Any

import jax
import numpy as np
from flax import nnx

from train import dataset, trainer


def load_scorer(model: str | os.PathLike | None, network: str = "ernet"):
    """-> (model, make_steps) for `network` ("ernet" or "pointnetgpd"); model None: the shipped default."""
    if network == "ernet":
        from sgjax.stage2.ernet import as_model

        return as_model(model), trainer.make_steps
    if network == "pointnetgpd":
        from sgjax.stage2.pointnetgpd import as_model as as_pointnetgpd
        from train import train_pointnetgpd

        return as_pointnetgpd(model), train_pointnetgpd.make_steps
    raise ValueError(f"network must be 'ernet' or 'pointnetgpd', got {network!r}")


def load_eval_step(model: str | os.PathLike | None, network: str = "ernet", batch_size: int = 128):
    """-> (scorer, eval_step, params): `load_scorer`'s model, the trainer's evaluation step for it (no
    noise; per-sample outputs) and its parameters, ready for `trainer.score_samples`."""
    scorer, make_steps = load_scorer(model, network)
    graphdef, params = nnx.split(scorer)
    _, _, eval_step = make_steps(graphdef, trainer.TrainConfig(model=scorer.config, batch_size=batch_size))
    return scorer, eval_step, params


def score_directory(data: str | os.PathLike | Sequence[str | os.PathLike], model=None, network: str = "ernet",
                    batch_size: int = 128, held_out: float | None = None, seed: int = 0,
                    resamples: int = 1000) -> dict[str, Any]:
    """Judge a scorer on every valid sample of a labelled directory (or several, of disjoint scenes).

    held_out: judge only the scenes that a `sgjax train` run with this held-out fraction and `seed` holds
    out of these directories (`dataset.split_by_scene`, a hash per scene, so the same scenes whatever
    other directories a run read), and the held-out objects: runs trained on different data are then
    compared on scenes none of them trained on. None: every sample.
    resamples: scene draws behind the 95 % intervals of AUC and of the top grasp's success
    ("auc_interval", "top1_interval", also per source; 0: none).

    -> the judgement of all samples (`train.judgement.judge`: "auc", "per_source" {name: {"auc", ...}},
    "ece", "top1_success", "random_success", ...) plus "classifier" (the summed metrics at the
    threshold: accuracy, precision, recall) and the judgement of two groups, "held_out_objects" and
    "seen_objects" (None when empty)."""
    if resamples < 0:
        raise ValueError(f"resamples must be >= 0, got {resamples}")
    scorer, eval_step, params = load_eval_step(model, network, batch_size)
    samples = dataset.read_shards(data, getattr(scorer.config, "crop", "enlarged"))
    keep = samples["valid"]
    if held_out is not None:
        scenes = np.zeros(len(keep), bool)
        scenes[dataset.split_by_scene(samples["scene_seed"], held_out, seed)[1]] = True
        keep = keep & (scenes | samples["held_out_object"])
    samples = dataset.select(samples, np.flatnonzero(keep))
    if not len(samples["label"]):
        raise dataset.DatasetError(f"{data}: no valid samples" + ("" if held_out is None else " in the held-out scenes"))
    key = jax.random.key(0)
    groups = {
        "all": np.ones(len(samples["label"]), bool),
        "held_out_objects": samples["held_out_object"],
        "seen_objects": ~samples["held_out_object"],
    }
    scored: dict[str, Any] = {}
    for name, rows in groups.items():
        part = {k: samples[k][rows] for k in trainer.EVAL_FIELDS}
        scored[name] = trainer.evaluate_params(eval_step, params, part, batch_size, key, resamples=resamples) if rows.any() else None
    overall = scored.pop("all")
    judged = overall.pop("judgement")
    return {**judged, "classifier": overall, **{name: (m or {}).get("judgement") for name, m in scored.items()}}


def report_table(result: dict[str, Any]) -> str:
    """`score_directory`'s result as a markdown table: all samples, each source, each object group."""
    def f(v, digits=3):
        return "–" if v is None else f"{v:.{digits}f}"

    def with_interval(m, name):
        interval = m.get(f"{name}_interval")
        value = m.get("auc" if name == "auc" else "top1_success")
        return f(value) if not interval else f"{f(value)} ({f(interval[0])}–{f(interval[1])})"

    rows = [("all", result)] + [(f"source {name}", m) for name, m in (result.get("per_source") or {}).items()]
    rows += [(name.replace("_", " "), result.get(name)) for name in ("seen_objects", "held_out_objects") if result.get(name)]
    lines = ["| samples | n | positive rate | AUC | refine AUC | ECE | collisions' mean score | top Stage-1 grasp succeeds | random one |",
             "|---|---:|---:|---:|---|---:|---:|---:|---:|"]
    for name, m in rows:
        refine = "/".join(f(v) for v in m.get("refine_auc") or []) or "–"
        lines.append(f"| {name} | {m['samples']} | {f(m.get('positive_rate'))} | {with_interval(m, 'auc')} | {refine} | {f(m.get('ece'))} "
                     f"| {f(m.get('collision_score'))} | {with_interval(m, 'top1')} | {f(m.get('random_success'))} |")
    if result.get("top1_per_scene"):
        lines += ["", f"The top Stage-1 grasp of each of {result['top1_scenes']} scenes is picked among "
                      f"{result['top1_per_scene']:.1f} Stage-1 samples on average; its success rises with that number."]
    missed = {name: n for name, n in (result.get("top1_outcomes") or {}).items() if name != "success"}
    if missed:
        lines += ["", "Where it failed, its trial ended: "
                  + ", ".join(f"{name} {n}" for name, n in sorted(missed.items(), key=lambda kv: -kv[1])) + " (scenes)."]
    return "\n".join(lines)
