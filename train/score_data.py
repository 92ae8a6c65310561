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


def score_directory(data: str | os.PathLike | Sequence[str | os.PathLike], model=None, network: str = "ernet", batch_size: int = 128) -> dict[str, Any]:
    """Metrics of a scorer on every valid sample of a labelled directory (or several, of disjoint scenes) -> {"all", "held_out_objects",
    "other"}: each `trainer.evaluate_params`' output (summed metrics and "judgement"), or None when
    the group is empty."""
    scorer, make_steps = load_scorer(model, network)
    config = trainer.TrainConfig(model=scorer.config, batch_size=batch_size)
    samples = dataset.read_shards(data, getattr(scorer.config, "crop", "enlarged"))
    samples = dataset.select(samples, np.flatnonzero(samples["valid"]))
    if not len(samples["label"]):
        raise dataset.DatasetError(f"{data}: no valid samples")
    graphdef, params = nnx.split(scorer)
    _, _, eval_step = make_steps(graphdef, config)
    key = jax.random.key(0)
    groups = {
        "all": np.ones(len(samples["label"]), bool),
        "held_out_objects": samples["held_out_object"],
        "other": ~samples["held_out_object"],
    }
    out: dict[str, Any] = {}
    for name, rows in groups.items():
        part = {k: samples[k][rows] for k in trainer.EVAL_FIELDS}
        out[name] = trainer.evaluate_params(eval_step, params, part, batch_size, key) if rows.any() else None
    return out
