"""Training of the PointNetGPD baseline (`sgjax.pointnetgpd`) on the E-RNet shards.

The same samples as E-RNet (`train.dataset` shards from `train/label.py`), of which PointNetGPD uses
the enlarged region (cropped here to the closing region of the sample's width) and `label` only. The
loop is E-RNet's (`train.trainer.run_training`: the scene-level train / held-out split, fixed-size
batches, prefetching, orbax checkpoints every epoch with exact resume, metrics.json / .csv,
curves.png); the settings are `train.trainer.TrainConfig` with a `PointNetGPDConfig` as its model.

    from train.train_pointnetgpd import default_config, train
    result = train("shards/", "runs/pointnetgpd", default_config(epochs=100))

or `sgjax train --network pointnetgpd --data shards/ --out runs/pointnetgpd`. Load the result with
`sgjax.pointnetgpd.load_model(run_dir)`; the benchmark methods `pointnetgpd` and `s1+pointnetgpd`
take the run directory as their `model`.
"""

from __future__ import annotations

import dataclasses
import functools
import os
from collections.abc import Callable, Mapping

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import nnx

from sgjax.pointnetgpd import (
    NETWORK,
    PointNetGPD,
    PointNetGPDConfig,
    loss,
    prepare_inputs,
    probability,
)
from train import dataset
from train.trainer import TrainConfig, TrainResult, make_optimizer, run_training


def default_config(**overrides) -> TrainConfig:
    """TrainConfig with the light PointNetGPD as its model (the other settings as for E-RNet)."""
    return TrainConfig(**{"model": PointNetGPDConfig(), **overrides})


def make_steps(graphdef: nnx.GraphDef, config: TrainConfig):
    """-> (tx, train_step, eval_step), jitted once per batch shape and cached as `trainer.make_steps`.

    train_step(params, opt_state, batch, key) -> (params, opt_state, stats)
    eval_step(params, batch, key) -> stats   (no noise)
    Stats are the trainer's weighted sums without the refinement entries.
    """
    step_config = dataclasses.replace(config, epochs=1, seed=0, held_out_fraction=0.0, prefetch=1)
    return _make_steps(graphdef, step_config)


@functools.lru_cache(maxsize=8)
def _make_steps(graphdef: nnx.GraphDef, config: TrainConfig):
    model_config, spec = config.model, config.spec
    tx = make_optimizer(config)

    def forward(params, batch: dataset.Batch, key, noise_std: float):
        model = nnx.merge(graphdef, params)
        inputs = prepare_inputs(batch.region, batch.region_mask, batch.width, spec, model_config, key=key, noise_std=noise_std)
        weight = batch.weight * inputs.valid  # an empty closing region: nothing to classify, excluded
        logits = model(inputs)
        value = loss(logits, batch.label, model_config, weight)
        return value, (logits, weight)

    def stats(logits, batch, weight, value):
        label = batch.label.astype(jnp.int32)
        predicted = probability(logits) >= config.threshold
        n = jnp.sum(weight)
        return {
            "n": n,
            "skipped": jnp.sum(batch.weight * (weight == 0)),
            "loss": value * n,
            "eval_loss": value * n,
            "correct": jnp.sum(weight * (jnp.argmax(logits, -1) == label)),
            "tp": jnp.sum(weight * (predicted & (label == 1))),
            "fp": jnp.sum(weight * (predicted & (label == 0))),
            "fn": jnp.sum(weight * (~predicted & (label == 1))),
        }

    def train_step(params, opt_state, batch, key):
        (value, (logits, weight)), grads = jax.value_and_grad(forward, has_aux=True)(
            params, batch, key, model_config.noise_std
        )
        updates, opt_state = tx.update(grads, opt_state, params)
        params = optax.apply_updates(params, updates)
        return params, opt_state, stats(logits, batch, weight, value)

    def eval_step(params, batch, key):
        value, (logits, weight) = forward(params, batch, key, 0.0)
        return stats(logits, batch, weight, value)

    return tx, jax.jit(train_step, donate_argnums=(0, 1)), jax.jit(eval_step)


def train(
    data: str | os.PathLike | Mapping[str, np.ndarray],
    run_dir: str | os.PathLike,
    config: TrainConfig | None = None,
    *,
    progress: bool = True,
    on_step: Callable[[int, int], None] | None = None,
) -> TrainResult:
    """Train PointNetGPD on shards in `data` (a directory, or validated columns) into `run_dir`.

    config: a TrainConfig whose `model` is a PointNetGPDConfig (None: `default_config()`). Resumes
    like `train.trainer.train`. Writes run_dir/{checkpoints/, metrics.json, metrics.csv, curves.png}
    with meta["network"] = "pointnetgpd".
    """
    config = default_config() if config is None else config
    if not isinstance(config.model, PointNetGPDConfig):
        raise TypeError(f"config.model must be a PointNetGPDConfig, got {type(config.model).__name__}")
    model = PointNetGPD(config.model, rngs=nnx.Rngs(config.seed))
    return run_training(model, make_steps, data, run_dir, config, meta={"network": NETWORK}, progress=progress, on_step=on_step)
