"""Training of the PointNetGPD baseline (`sgjax.stage2.pointnetgpd`) on the E-RNet shards.

The same samples as E-RNet (`train.dataset` shards from `train/label.py`), of which PointNetGPD uses
the enlarged region (cropped here to the closing region of the sample's width) and `label` only. The
loop is E-RNet's (`train.trainer.run_training`: the scene-level train / held-out split, fixed-size
batches, prefetching, orbax checkpoints every epoch with exact resume, metrics.json / .csv,
curves.png); the settings are `train.trainer.TrainConfig` with a `PointNetGPDConfig` as its model.

    from train.train_pointnetgpd import default_config, train
    result = train("shards/", "runs/pointnetgpd", default_config(epochs=100))

or `sgjax train --network pointnetgpd --data shards/ --out runs/pointnetgpd`. Load the result with
`sgjax.stage2.pointnetgpd.load_model(run_dir)`; the benchmark methods `pointnetgpd` and `s1+pointnetgpd`
take the run directory as their `model`.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np
from flax import nnx

from sgjax.stage2.pointnetgpd import (
    NETWORK,
    PointNetGPD,
    PointNetGPDConfig,
    load_model,
    loss,
    prepare_inputs,
    probability,
)
from train import dataset
from train.trainer import (
    TrainConfig,
    TrainResult,
    classification_stats,
    initial_model,
    jit_steps,
    make_optimizer,
    run_training,
    steps_builder,
)


def default_config(**overrides) -> TrainConfig:
    """TrainConfig with the light PointNetGPD as its model (the other settings as for E-RNet)."""
    return TrainConfig(**{"model": PointNetGPDConfig(), **overrides})


@steps_builder
def make_steps(graphdef: nnx.GraphDef, config: TrainConfig):
    """-> (tx, train_step, eval_step), jitted once per batch shape and cached (`trainer.steps_builder`).

    train_step(params, opt_state, batch, key, lr_scale) -> (params, opt_state, stats)
    eval_step(params, batch, key) -> stats   (no noise)
    Stats are the trainer's weighted sums without the refinement entries.
    """
    model_config, spec = config.model, config.spec

    def forward(params, batch: dataset.Batch, key, noise_std: float):
        model = nnx.merge(graphdef, params)
        inputs = prepare_inputs(batch.region, batch.region_mask, batch.width, spec, model_config, key=key, noise_std=noise_std)
        weight = batch.weight * inputs.valid  # an empty closing region: nothing to classify, excluded
        logits = model(inputs)
        return loss(logits, batch.label, model_config, weight), (logits, weight)

    def stats(batch, value, aux):
        logits, weight = aux
        sums = classification_stats(probability(logits), logits, batch.label, weight, batch.weight, config.threshold)
        return {**sums, "loss": value * sums["n"], "eval_loss": value * sums["n"]}

    def per_sample(aux):
        logits, weight = aux
        return {"prob": probability(logits), "weight": weight}

    return jit_steps(make_optimizer(config), forward, stats, model_config.noise_std, per_sample)


def train(
    data: str | os.PathLike | Sequence[str | os.PathLike] | Mapping[str, np.ndarray],
    run_dir: str | os.PathLike,
    config: TrainConfig | None = None,
    *,
    progress: bool = True,
    on_step: Callable[[int, int], None] | None = None,
    init: str | os.PathLike | None = None,
    extra_meta: Mapping[str, Any] | None = None,
) -> TrainResult:
    """Train PointNetGPD on shards in `data` (a directory, several of disjoint scenes, or validated columns) into `run_dir`.

    config: a TrainConfig whose `model` is a PointNetGPDConfig (None: `default_config()`). Resumes
    like `train.trainer.train`. Writes run_dir/{checkpoints/, metrics.json, metrics.csv, curves.png}
    with meta["network"] = "pointnetgpd" and, as every run of `run_training`, meta["gripper"]: the gripper
    of the labelled directories (`config.spec`, which must be theirs: `train.label.data_gripper`). init: a PointNetGPD run directory to start from, as in
    `train.trainer.train`. extra_meta: JSON entries stored in every checkpoint's meta too (the recipe and
    commit, `train.recipe`); it cannot replace meta["network"].
    """
    config = default_config() if config is None else config
    if not isinstance(config.model, PointNetGPDConfig):
        raise TypeError(f"config.model must be a PointNetGPDConfig, got {type(config.model).__name__}")
    if init is None:
        model = PointNetGPD(config.model, rngs=nnx.Rngs(config.seed))
    else:
        model = initial_model(init, config.model, lambda path: load_model(path)[0])
    return run_training(model, make_steps, data, run_dir, config, meta={**(extra_meta or {}), "network": NETWORK},
                        progress=progress, on_step=on_step, init=init)
