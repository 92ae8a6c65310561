"""E-RNet training loop (paper Sec. IV-E): Adam + weight decay, batch 128, per-epoch metrics,
orbax checkpoints every epoch with exact resume, progress bar, metrics.json / metrics.csv / curves.png.

    from train.trainer import TrainConfig, train
    result = train("shards/", "runs/ernet", TrainConfig(epochs=100))

`run_training` is that loop for any network on these shards (the PointNetGPD baseline,
train/train_pointnetgpd.py, brings its own model and steps and reuses everything else).

Determinism: the model init, the per-epoch shuffle (numpy, seeded by (seed, epoch)) and the per-step
noise/shuffle keys (fold_in(seed, epoch, step)) depend only on the seed, so a run interrupted at any
point and restarted with the same command continues from its last completed epoch and ends with the
same parameters and metrics as an uninterrupted run (tests/test_training.py checks this).

Data parallelism (`devices=N`, `sgjax train --devices N`): a `jax.sharding.Mesh` over the first N
devices with one axis "data"; every batch is split along its leading (sample) axis, the parameters
and the optimiser state are replicated, and jit (GSPMD) partitions the same step functions, inserting
the gradient all-reduce itself. Checkpoints hold plain arrays and are restored onto whatever device
count the resumed run asks for (tests/test_training_sharded.py).

Weight decay: the paper uses "Adam with weight decay 3e-4" (PyTorch's torch.optim.Adam(weight_decay=),
an L2 term added to the gradient before the Adam moments); that is optax.add_decayed_weights before
optax.adam, our default. `decoupled_weight_decay=True` gives AdamW (optax.adamw) instead.
"""

from __future__ import annotations

import csv
import dataclasses
import functools
import io
import json
import math
import os
import queue
import threading
from collections.abc import Callable, Iterable, Mapping, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import nnx

from sgjax.geometry.gripper_files import gripper_to_dict
from sgjax.stage2.checkpoint import CHECKPOINT_DIR, GRIPPER_ITEM, META_ITEM, OPT_STATE_ITEM, PARAMS_ITEM
from sgjax.stage2.ernet import (
    DEFAULT_SPEC,
    ERNet,
    ERNetConfig,
    ernet_loss,
    load_model,
    prepare_inputs,
)
from sgjax.utils.files import atomic_write, atomic_write_text
from sgjax.geometry.gripper import GripperSpec
from train import dataset

# ---------------------------------------------------------------------------------------------
# Configuration.

DEFAULT_MODEL = ERNetConfig()


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """Training settings (paper: 100 epochs, batch 128, Adam lr 1e-3, weight decay 3e-4).

    held_out_fraction: share of scenes (not samples) held out for evaluation.
    threshold: evaluation score above which a grasp counts as predicted stable (paper: 0.7).
    decoupled_weight_decay: False = Adam + L2 (the paper, PyTorch Adam); True = AdamW.
    prefetch: batches prepared ahead by the loader thread.
    lr_decay_epochs: the last N epochs lower the learning rate along a half cosine from `lr` to 0,
        step by step (a constant-then-decay schedule); 0 (default, the paper): constant `lr`. Like
        `epochs`, it only shapes the schedule's tail, so a resumed run may add or change it.
    devices: data-parallel width: each batch is split over the first `devices` JAX devices (a mesh
        axis "data"), parameters and optimiser state are replicated; `batch_size` must be divisible
        by it. 1 (default): one device, as before. It changes where the step runs, not what it
        computes (up to the order of float sums), so a resumed run may change it.
    spec: the gripper of the training data (`train.label.data_gripper`: a labelled directory records
        it); a run on directories labelled for another gripper is refused. Every checkpoint's meta
        records it whole (meta["gripper"], `sgjax.stage2.checkpoint.meta_gripper`).
    """

    epochs: int = 100
    batch_size: int = 128
    lr: float = 1e-3
    weight_decay: float = 3e-4
    decoupled_weight_decay: bool = False
    seed: int = 0
    held_out_fraction: float = 0.1
    threshold: float = 0.7
    prefetch: int = 4
    lr_decay_epochs: int = 0
    devices: int = 1
    model: ERNetConfig = DEFAULT_MODEL
    spec: GripperSpec = DEFAULT_SPEC

    def __post_init__(self):
        if self.epochs < 1 or self.batch_size < 1 or self.prefetch < 1:
            raise ValueError("epochs, batch_size and prefetch must be >= 1")
        if not self.lr > 0 or self.weight_decay < 0:
            raise ValueError("lr must be > 0 and weight_decay >= 0")
        if not 0.0 < self.threshold < 1.0:
            raise ValueError("threshold must be in (0, 1)")
        if not 0 <= self.lr_decay_epochs <= self.epochs:
            raise ValueError(f"lr_decay_epochs must be in [0, epochs={self.epochs}], got {self.lr_decay_epochs}")
        if self.devices < 1:
            raise ValueError(f"devices must be >= 1, got {self.devices}")
        if self.batch_size % self.devices:
            raise ValueError(
                f"batch_size {self.batch_size} is not divisible by devices={self.devices}: every device takes "
                f"an equal slice of each batch (try batch_size {self.devices * max(1, round(self.batch_size / self.devices))})"
            )

    def lr_scale(self, epoch: int, step: int, steps_per_epoch: int) -> float:
        """The learning rate's factor at `step` (0-based) of `epoch` (0-based): 1 until the last
        `lr_decay_epochs` epochs, then a half cosine down to 0 at the end of the last epoch."""
        if self.lr_decay_epochs == 0:
            return 1.0
        start = self.epochs - self.lr_decay_epochs
        t = (epoch - start + step / max(steps_per_epoch, 1)) / self.lr_decay_epochs
        return 1.0 if t <= 0 else 0.5 * (1.0 + math.cos(math.pi * min(t, 1.0)))

    def resume_key(self) -> dict[str, Any]:
        """Settings that must not change when a run is resumed (everything but `epochs`, `prefetch`,
        `lr_decay_epochs` and `devices`)."""
        d = dataclasses.asdict(self)
        # `devices` is left out too: a checkpoint restores onto any device count, and runs written
        # before the setting existed keep their fingerprint.
        for name in ("epochs", "prefetch", "lr_decay_epochs", "devices"):
            d.pop(name)
        return json.loads(json.dumps(d))  # tuples -> lists, as stored in JSON


def make_optimizer(config: TrainConfig) -> optax.GradientTransformation:
    if config.decoupled_weight_decay:
        return optax.adamw(config.lr, weight_decay=config.weight_decay)
    return optax.chain(optax.add_decayed_weights(config.weight_decay), optax.adam(config.lr))


# ---------------------------------------------------------------------------------------------
# Jitted steps.


def classification_stats(prob, logits, label, weight, batch_weight, threshold: float) -> dict[str, jax.Array]:
    """Weighted sums of a binary grasp classifier over one batch (summed per epoch, see `summarise`).

    prob [B] P(success), logits [B, 2], label [B] in {0, 1}, weight [B] (0: excluded), batch_weight [B]
    (0: padding) -> n, skipped (real samples excluded), correct, tp, fp, fn at `threshold`.
    """
    label = label.astype(jnp.int32)
    predicted = prob >= threshold
    return {
        "n": jnp.sum(weight),
        "skipped": jnp.sum(batch_weight * (weight == 0)),
        "correct": jnp.sum(weight * (jnp.argmax(logits, -1) == label)),
        "tp": jnp.sum(weight * (predicted & (label == 1))),
        "fp": jnp.sum(weight * (predicted & (label == 0))),
        "fn": jnp.sum(weight * (~predicted & (label == 1))),
    }


def _batch_stats(output, batch: dataset.Batch, weight, loss, parts, threshold: float) -> dict[str, jax.Array]:
    """E-RNet's weighted sums over one batch: the classifier's plus losses and refinement accuracy."""
    stats = classification_stats(output.eval_prob, output.eval_logits, batch.label, weight, batch.weight, threshold)
    n = stats["n"]
    refine_ok = (output.refine_prob >= 0.5) == (batch.refine_labels == 1)
    return {
        **stats,
        "loss": loss * n,
        "eval_loss": parts["eval"] * n,
        "refine_loss": parts["refine"] * n,
        "refine_correct": jnp.sum(weight[:, None] * refine_ok, axis=0),
    }


def step_config(config: TrainConfig) -> TrainConfig:
    """The part of a TrainConfig the jitted steps depend on (the cache key of `make_steps`): not the
    epochs, seed, split, prefetch or schedule (its factor is an argument), so a resumed run or a
    notebook re-run does not recompile. Not `devices` either: the steps are the same functions on any
    mesh, and jit keys its compilations by the inputs' shardings itself."""
    return dataclasses.replace(config, epochs=1, seed=0, held_out_fraction=0.0, prefetch=1, lr_decay_epochs=0, devices=1)


def jit_steps(tx: optax.GradientTransformation, forward: Callable, stats: Callable, noise_std: float,
              per_sample: Callable | None = None):
    """-> (tx, train_step, eval_step) for any network of this trainer.

    forward(params, batch, key, noise_std) -> (loss, aux); stats(batch, loss, aux) -> dict of sums;
    per_sample(aux) -> {"prob": [B], "weight": [B], optionally "refine_prob": [B, K]} (the judgement
    metrics' inputs, `train.judgement`).
    train_step(params, opt_state, batch, key, lr_scale) -> (params, opt_state, stats) (params and
    state donated; lr_scale [] multiplies the step, the schedule's factor, traced so it never recompiles);
    eval_step(params, batch, key) -> stats, without input noise, with stats["per_sample"] when given.
    """

    def train_step(params, opt_state, batch, key, lr_scale):
        (loss, aux), grads = jax.value_and_grad(forward, has_aux=True)(params, batch, key, noise_std)
        updates, opt_state = tx.update(grads, opt_state, params)
        # Scaling the final step is scaling the learning rate (Adam's moments do not see it), and
        # keeps the optimiser state's structure, so a run can take a schedule when resumed.
        updates = jax.tree.map(lambda u: u * lr_scale, updates)
        return optax.apply_updates(params, updates), opt_state, stats(batch, loss, aux)

    def eval_step(params, batch, key):
        loss, aux = forward(params, batch, key, 0.0)
        out = stats(batch, loss, aux)
        return out if per_sample is None else {**out, "per_sample": per_sample(aux)}

    return tx, jax.jit(train_step, donate_argnums=(0, 1)), jax.jit(eval_step)


def steps_builder(build: Callable[[nnx.GraphDef, TrainConfig], tuple]) -> Callable[[nnx.GraphDef, TrainConfig], tuple]:
    """Decorate a `build(graphdef, config) -> (tx, train_step, eval_step)` so that its result is cached
    by what the steps depend on (`step_config`): every `train` call with the same model and optimiser
    settings (a resumed run with more epochs, a notebook re-run) reuses one compilation."""
    cached = functools.lru_cache(maxsize=8)(build)

    @functools.wraps(build)
    def make(graphdef: nnx.GraphDef, config: TrainConfig) -> tuple:
        return cached(graphdef, step_config(config))

    return make


@steps_builder
def make_steps(graphdef: nnx.GraphDef, config: TrainConfig):
    """E-RNet's -> (tx, train_step, eval_step), jitted once per batch shape (see `steps_builder`).

    train_step(params, opt_state, batch, key, lr_scale) -> (params, opt_state, stats)
    eval_step(params, batch, key) -> stats  (no noise; `key` fixes the downsampling)
    """
    model_config, spec = config.model, config.spec

    def forward(params, batch: dataset.Batch, key, noise_std: float):
        model = nnx.merge(graphdef, params)
        inputs = prepare_inputs(
            batch.region, batch.region_mask, batch.width, spec, model_config, key=key, noise_std=noise_std
        )
        # Samples without a point in the initial closing region have no anchor feature: excluded.
        weight = batch.weight * inputs.valid
        output = model(inputs)
        loss, parts = ernet_loss(output, batch.label, batch.refine_labels, model_config, weight)
        return loss, (output, parts, weight)

    def stats(batch, loss, aux):
        output, parts, weight = aux
        return _batch_stats(output, batch, weight, loss, parts, config.threshold)

    def per_sample(aux):
        output, _, weight = aux
        return {"prob": output.eval_prob, "refine_prob": output.refine_prob, "weight": weight}

    return jit_steps(make_optimizer(config), forward, stats, model_config.noise_std, per_sample)


def summarise(stats: Mapping[str, Any]) -> dict[str, Any]:
    """Summed batch stats -> metrics (None where undefined, e.g. precision with no positive call, or
    the refinement metrics of a network without a refinement head: no "refine_*" stats)."""
    s = {k: np.asarray(v, np.float64) for k, v in stats.items()}
    n = float(s["n"])

    def ratio(a, b):
        return float(a / b) if b > 0 else None

    return {
        "samples": int(n),
        "skipped_no_anchor": int(s["skipped"]),
        "loss": ratio(s["loss"], n),
        "eval_loss": ratio(s["eval_loss"], n),
        "refine_loss": ratio(s["refine_loss"], n) if "refine_loss" in s else None,
        "accuracy": ratio(s["correct"], n),
        "precision": ratio(s["tp"], s["tp"] + s["fp"]),
        "recall": ratio(s["tp"], s["tp"] + s["fn"]),
        "refine_accuracy": [ratio(c, n) for c in s["refine_correct"]] if "refine_correct" in s else None,
    }


# ---------------------------------------------------------------------------------------------
# Data loading.


class Prefetcher:
    """Builds batches (array slices of preloaded columns) and puts them on the device in a thread,
    `depth` batches ahead, so the host prepares batch i+1 while the device runs batch i.

    sharding: where each batch goes (every field [B, ...] split alike, e.g. `Placement.batch`'s
    NamedSharding over "data"); None: the default device, uncommitted (the single-device path)."""

    _END = object()

    def __init__(
        self,
        samples: Mapping[str, np.ndarray],
        batches: Iterable[tuple[np.ndarray, np.ndarray]],
        depth: int,
        sharding: jax.sharding.Sharding | None = None,
    ):
        self._queue: queue.Queue = queue.Queue(maxsize=depth)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, args=(samples, batches, sharding), daemon=True)
        self._thread.start()

    def _run(self, samples, batches, sharding):
        try:
            for index, weight in batches:
                item = jax.device_put(dataset.make_batch(samples, index, weight), sharding)
                while not self._stop.is_set():
                    try:
                        self._queue.put(item, timeout=0.1)
                        break
                    except queue.Full:
                        continue
                if self._stop.is_set():
                    return
            self._queue.put(self._END)
        except Exception as exc:  # noqa: BLE001 - re-raised in the consumer thread
            self._queue.put(exc)

    def __iter__(self):
        while True:
            item = self._queue.get()
            if item is self._END:
                return
            if isinstance(item, BaseException):
                raise item
            yield item

    def close(self):
        self._stop.set()
        self._thread.join(timeout=5)


# ---------------------------------------------------------------------------------------------
# Outputs.


METRIC_COLUMNS = ("loss", "eval_loss", "refine_loss", "accuracy", "precision", "recall")
JUDGEMENT_COLUMNS = ("auc", "ece", "collision_score", "top1_success", "random_success")


def _csv_text(history: list[dict[str, Any]]) -> str:
    header = ["epoch"]
    for split in ("train", "held_out"):
        header += [f"{split}_{m}" for m in METRIC_COLUMNS] + [f"{split}_refine_accuracy_{v}" for v in range(3)]
    for split in ("held_out", "held_out_objects"):
        header += [f"{split}_{m}" for m in JUDGEMENT_COLUMNS]
    out = io.StringIO()
    writer = csv.writer(out)
    writer.writerow(header)
    for record in history:
        row: list[Any] = [record["epoch"]]
        for split in ("train", "held_out"):
            m = record.get(split) or {}
            row += [m.get(k) for k in METRIC_COLUMNS]
            row += list(m.get("refine_accuracy") or [None] * 3)
        for split in ("held_out", "held_out_objects"):
            judged = (record.get(split) or {}).get("judgement") or {}
            row += [judged.get(k) for k in JUDGEMENT_COLUMNS]
        writer.writerow(["" if v is None else v for v in row])
    return out.getvalue()


def plot_curves(history: list[dict[str, Any]], path: str) -> None:
    """Loss, accuracy, precision/recall at the threshold and refine accuracy per epoch (PNG, Agg)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(12, 8))
    FigureCanvasAgg(fig)
    axes = fig.subplots(2, 2)
    epochs = [r["epoch"] for r in history]

    def series(split, key, index=None):
        values = []
        for r in history:
            m = r.get(split) or {}
            v = m.get(key)
            v = v[index] if (v is not None and index is not None) else v
            values.append(np.nan if v is None else v)
        return values

    panels = [
        (axes[0, 0], "loss", [("loss", None)]),
        (axes[0, 1], "evaluation accuracy", [("accuracy", None)]),
        (axes[1, 0], "precision / recall (eval score >= threshold)", [("precision", None), ("recall", None)]),
        (axes[1, 1], "refinement accuracy per variant", [("refine_accuracy", v) for v in range(3)]),
    ]
    for ax, title, keys in panels:
        for split, style in (("train", "-"), ("held_out", "--")):
            for key, index in keys:
                label = f"{split} {key}" + ("" if index is None else f" {index}")
                ax.plot(epochs, series(split, key, index), style, marker="o", markersize=3, label=label)
        ax.set_title(title)
        ax.set_xlabel("epoch")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.tight_layout()
    atomic_write(path, lambda tmp: fig.savefig(tmp, dpi=100))


def _write_outputs(run_dir: str, history: list[dict[str, Any]], config: TrainConfig) -> None:
    record = {"train_config": json.loads(json.dumps(dataclasses.asdict(config))), "history": history}
    atomic_write_text(os.path.join(run_dir, "metrics.json"), json.dumps(record, indent=1))
    atomic_write_text(os.path.join(run_dir, "metrics.csv"), _csv_text(history))
    plot_curves(history, os.path.join(run_dir, "curves.png"))
    judged = {split: ((history[-1].get(split) or {}).get("judgement")) for split in ("held_out", "held_out_objects")} if history else {}
    if any(judged.values()):
        plot_reliability(judged, os.path.join(run_dir, "reliability.png"))


def plot_reliability(judged: Mapping[str, Mapping[str, Any] | None], path: str) -> None:
    """The reliability diagram of the latest epoch: success rate against mean score per score bin, per
    split, beside the diagonal of perfect calibration (PNG)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(5, 5))
    FigureCanvasAgg(fig)
    ax = fig.subplots()
    ax.plot([0, 1], [0, 1], ":", color="grey", label="calibrated")
    for split, metrics in judged.items():
        if not metrics or not metrics.get("reliability"):
            continue
        table = np.asarray(metrics["reliability"], np.float64)
        ece = metrics.get("ece")
        ax.plot(table[:, 0], table[:, 1], marker="o", label=f"{split} (ECE {ece:.3f}, AUC {metrics.get('auc') or float('nan'):.3f})")
    ax.set_xlabel("evaluation score")
    ax.set_ylabel("success rate")
    ax.set_xlim(0, 1)
    ax.set_ylim(0, 1)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    atomic_write(path, lambda tmp: fig.savefig(tmp, dpi=100))


# ---------------------------------------------------------------------------------------------
# Training.


DATA_AXIS = "data"  # the mesh axis batches are split along


def data_mesh(devices: int) -> jax.sharding.Mesh:
    """A one-axis mesh ("data",) over the first `devices` JAX devices.

    Raises ValueError naming how many devices JAX sees (and how to get more on a CPU) when there are
    fewer than `devices`."""
    available = jax.devices()
    if devices > len(available):
        raise ValueError(
            f"devices={devices} asks for more devices than JAX sees: {len(available)} {available[0].platform} "
            f"device(s). On a CPU, split the host into N devices by starting Python with "
            f"XLA_FLAGS=--xla_force_host_platform_device_count={devices} (it must be set before JAX is imported)"
        )
    # Auto axes: jit (GSPMD) propagates the shardings through the unchanged step functions; the
    # default of jax.make_mesh, Explicit axes, would make every op's sharding part of its type.
    return jax.make_mesh((devices,), (DATA_AXIS,), (jax.sharding.AxisType.Auto,), devices=available[:devices])


@dataclasses.dataclass(frozen=True)
class Placement:
    """Where a run's arrays live: `state` for the parameters and optimiser state, `batch` for every
    batch field [B, ...] (None: the default device, uncommitted)."""

    state: jax.sharding.Sharding
    batch: jax.sharding.Sharding | None

    @classmethod
    def for_devices(cls, devices: int) -> "Placement":
        """devices == 1: the first device for the state, batches as `jax.device_put` places them (the
        single-device path, unchanged); devices > 1: state replicated over a `data_mesh`, batches split
        along their leading axis."""
        if devices == 1:
            return cls(jax.sharding.SingleDeviceSharding(jax.devices()[0]), None)
        mesh = data_mesh(devices)
        P = jax.sharding.PartitionSpec
        return cls(jax.sharding.NamedSharding(mesh, P()), jax.sharding.NamedSharding(mesh, P(DATA_AXIS)))

    def abstract(self, tree):
        """Shape-only targets of `tree`'s arrays carrying `state`: what orbax restores into, so a
        checkpoint written on any device count lands on this run's devices."""
        import orbax.checkpoint as ocp

        def target(x):
            s = ocp.utils.to_shape_dtype_struct(x)  # as orbax itself sees the leaf (scalars stay scalars)
            return jax.ShapeDtypeStruct(s.shape, s.dtype, sharding=self.state) if isinstance(s, jax.ShapeDtypeStruct) else s

        return jax.tree.map(target, tree)


@dataclasses.dataclass
class TrainResult:
    model: nnx.Module  # an ERNet (`train`), or the network given to `run_training`
    history: list[dict[str, Any]]
    run_dir: str


def _checkpoint_manager(run_dir: str):
    import orbax.checkpoint as ocp

    options = ocp.CheckpointManagerOptions(max_to_keep=3, enable_async_checkpointing=False, cleanup_tmp_directories=True)
    return ocp.CheckpointManager(os.path.abspath(os.path.join(run_dir, CHECKPOINT_DIR)), options=options)


EVAL_FIELDS = (*dataset.TRAIN_FIELDS, "source", "outcome", "scene_seed")  # what the judgement metrics need


def _load_data(data: str | os.PathLike | Sequence[str | os.PathLike] | Mapping[str, np.ndarray], config: TrainConfig):
    """-> (train set, held-out scenes, held-out objects): columns of the valid samples. Held-out objects
    are never trained on, nor mixed into the held-out scenes' metrics."""
    crop = getattr(config.model, "crop", "enlarged")
    samples = dataset.validate(data, "data") if isinstance(data, Mapping) else dataset.read_shards(data, crop)
    objects = dataset.select(samples, np.flatnonzero(samples["valid"] & samples["held_out_object"]))
    samples = dataset.select(samples, np.flatnonzero(samples["valid"] & ~samples["held_out_object"]))
    if dataset.num_samples(samples) == 0:
        raise dataset.DatasetError("no valid samples to train on")
    train_index, held_index = dataset.split_by_scene(samples["scene_seed"], config.held_out_fraction, config.seed)
    if len(train_index) == 0:
        raise dataset.DatasetError("every scene fell into the held-out split; lower held_out_fraction")
    train_set = {k: np.ascontiguousarray(samples[k][train_index]) for k in dataset.TRAIN_FIELDS}
    held_set = {k: np.ascontiguousarray(samples[k][held_index]) for k in EVAL_FIELDS}
    objects_set = {k: np.ascontiguousarray(objects[k]) for k in EVAL_FIELDS}
    return train_set, held_set, objects_set


def train(
    data: str | os.PathLike | Sequence[str | os.PathLike] | Mapping[str, np.ndarray],
    run_dir: str | os.PathLike,
    config: TrainConfig = TrainConfig(),
    *,
    progress: bool = True,
    on_step: Callable[[int, int], None] | None = None,
    init: str | os.PathLike | None = None,
    extra_meta: Mapping[str, Any] | None = None,
) -> TrainResult:
    """Train E-RNet on shards in `data` (a directory, several of disjoint scenes, or validated columns), writing to `run_dir`.

    Resumes from the last epoch checkpoint in `run_dir` if there is one (same settings required,
    `epochs` may grow). `on_step(epoch, step)` is called after every training step (e.g. logging).
    init: a `sgjax train` run directory whose latest weights (not its optimiser state) start this run,
    e.g. to go on training a checkpoint on more data; its network config must equal `config.model`.
    extra_meta: JSON entries stored in every checkpoint's meta (e.g. the recipe and commit, `train.recipe`).
    Writes run_dir/{checkpoints/, metrics.json, metrics.csv, curves.png}.
    """
    if config.model.n_refinements != config.spec.num_refinements:
        raise ValueError("model n_refinements must equal the gripper spec's refinement count")
    if init is None:
        model = ERNet(config.model, rngs=nnx.Rngs(config.seed))
    else:
        model = initial_model(init, config.model, lambda path: load_model(path)[0])
    return run_training(model, make_steps, data, run_dir, config, meta=extra_meta, progress=progress, on_step=on_step,
                        init=init)


def check_data_gripper(data, spec: GripperSpec) -> None:
    """Refuse (ValueError, one line) labelled directories made for another gripper than `spec`, the one
    the crops and the checkpoint's meta follow, or directories of different grippers
    (`train.label.data_gripper`). Columns given as a mapping carry no gripper: `spec` is theirs."""
    if isinstance(data, Mapping):
        return
    from sgjax.stage2.checkpoint import describe_gripper
    from train.label import data_gripper

    found = data_gripper(data)
    if found != spec:
        where = data if isinstance(data, (str, os.PathLike)) else ", ".join(os.fspath(d) for d in data)
        raise ValueError(f"{where} was labelled for gripper {describe_gripper(found, spec)} but the training config's "
                         f"gripper is {describe_gripper(spec, found)}: train with the data's gripper "
                         "(TrainConfig(spec=train.label.data_gripper(dirs)); `sgjax train` takes it from the data)")


def initial_model(init: str | os.PathLike, model_config, load: Callable[[str], nnx.Module]) -> nnx.Module:
    """The network of run directory `init` (latest epoch) to start a run from; ValueError when its
    config is not `model_config` (the weights would not fit) or it holds no checkpoint."""
    try:
        model = load(os.fspath(init))
    except FileNotFoundError as exc:
        raise ValueError(f"init: {exc}") from exc
    if model.config != model_config:
        raise ValueError(f"init: {init} holds a network with another config ({model.config}) than this run's "
                         f"({model_config}); pass the same --model / --hand-points")
    return model


def run_training(
    model: nnx.Module,
    steps: Callable[[nnx.GraphDef, TrainConfig], tuple],
    data: str | os.PathLike | Sequence[str | os.PathLike] | Mapping[str, np.ndarray],
    run_dir: str | os.PathLike,
    config: TrainConfig,
    *,
    meta: Mapping[str, Any] | None = None,
    progress: bool = True,
    on_step: Callable[[int, int], None] | None = None,
    init: str | os.PathLike | None = None,
) -> TrainResult:
    """The training loop of `train`, for any network trained on these shards (E-RNet, the baselines).

    model: the freshly initialised network (seeded by config.seed; `config.model` is its config, with
    `to_dict()`); steps(graphdef, config) -> (tx, train_step, eval_step) as `make_steps`, whose stats
    follow `_batch_stats` (the "refine_*" entries may be left out); meta: extra JSON entries stored
    in every checkpoint's meta (e.g. {"network": "pointnetgpd"}); init: the run directory `model` was
    loaded from (`initial_model`), part of the run's fingerprint so that a resume keeps it. Data split,
    batching, prefetch, checkpoints, exact resume and outputs are those of `train`.
    """
    import orbax.checkpoint as ocp
    from tqdm.auto import tqdm

    run_dir = os.fspath(run_dir)
    placement = Placement.for_devices(config.devices)  # before reading data: a bad device count fails fast
    check_data_gripper(data, config.spec)  # before any work: labels of one gripper, the config's
    os.makedirs(run_dir, exist_ok=True)
    train_set, held_set, objects_set = _load_data(data, config)
    n_train, n_held = len(train_set["label"]), len(held_set["label"])

    graphdef, params = nnx.split(model)
    tx, train_step, eval_step = steps(graphdef, config)
    opt_state = tx.init(params)

    manager = _checkpoint_manager(run_dir)
    history: list[dict[str, Any]] = []
    start = manager.latest_step() or 0
    fingerprint = {"config": config.resume_key(), "n_train": n_train, "n_held_out": n_held}
    if init is not None:  # only then: runs started from scratch keep the fingerprint they always had
        fingerprint["init"] = os.path.abspath(os.fspath(init))
    if config.spec != GripperSpec():  # likewise: the whole gripper (resume_key holds its geometry only)
        fingerprint["gripper"] = gripper_to_dict(config.spec)
    if start:
        saved = manager.restore(start, args=ocp.args.Composite(**{META_ITEM: ocp.args.JsonRestore()}))[META_ITEM]
        if saved["fingerprint"] != fingerprint:
            raise ValueError(
                f"{run_dir} holds a run with other settings or data ({saved['fingerprint']}); "
                "use a new --out directory or the same settings to resume"
            )
        # Targets carrying this run's sharding, not the saved one: a run written with --devices 2
        # resumes on one device and the other way round.
        abstract = placement.abstract({PARAMS_ITEM: params, OPT_STATE_ITEM: opt_state})
        restored = manager.restore(
            start,
            args=ocp.args.Composite(**{k: ocp.args.StandardRestore(v) for k, v in abstract.items()}),
        )
        params, opt_state = restored[PARAMS_ITEM], restored[OPT_STATE_ITEM]
        history = saved["history"]
        if progress:
            print(f"resuming {run_dir} after epoch {start}")
    # Restored arrays are committed to a device; commit fresh ones too, or the jitted step would
    # compile a second time for a resumed run (committedness is part of jit's cache key).
    params, opt_state = jax.device_put((params, opt_state), placement.state)

    base_key = jax.random.key(config.seed)
    eval_key = jax.random.fold_in(base_key, 1 << 30)  # apart from the epoch keys
    n_batches = math.ceil(n_train / config.batch_size)
    try:
        for epoch in range(start, config.epochs):
            epoch_key = jax.random.fold_in(base_key, epoch)
            rng = np.random.default_rng([config.seed, epoch])
            batches = dataset.batch_indices(n_train, config.batch_size, rng)
            loader = Prefetcher(train_set, batches, config.prefetch, placement.batch)
            totals = None
            bar = tqdm(total=n_batches, desc=f"epoch {epoch + 1}/{config.epochs}", disable=not progress, leave=False)
            try:
                for step, batch in enumerate(loader):
                    scale = jnp.float32(config.lr_scale(epoch, step, n_batches))
                    params, opt_state, stats = train_step(params, opt_state, batch, jax.random.fold_in(epoch_key, step), scale)
                    totals = stats if totals is None else jax.tree.map(jnp.add, totals, stats)
                    bar.update(1)
                    if step % 20 == 0:
                        bar.set_postfix(loss=f"{float(stats['loss'] / jnp.maximum(stats['n'], 1)):.4f}")
                    if on_step is not None:
                        on_step(epoch, step)
            finally:
                bar.close()
                loader.close()
            record = {"epoch": epoch + 1, "train": summarise(totals), "held_out": None, "held_out_objects": None}
            if n_held:
                record["held_out"] = evaluate_params(eval_step, params, held_set, config.batch_size, eval_key, placement.batch)
            if len(objects_set["label"]):
                record["held_out_objects"] = evaluate_params(
                    eval_step, params, objects_set, config.batch_size, eval_key, placement.batch
                )
            history.append(record)
            record_meta = {
                **(meta or {}),
                "epochs_done": epoch + 1,
                "history": history,
                "model_config": config.model.to_dict(),
                "fingerprint": fingerprint,
                # The gripper of the training data, whole (`sgjax.stage2.checkpoint.meta_gripper` reads it).
                GRIPPER_ITEM: gripper_to_dict(config.spec),
            }
            manager.save(
                epoch + 1,
                args=ocp.args.Composite(
                    **{
                        PARAMS_ITEM: ocp.args.StandardSave(params),
                        OPT_STATE_ITEM: ocp.args.StandardSave(opt_state),
                        META_ITEM: ocp.args.JsonSave(record_meta),
                    }
                ),
            )
            manager.wait_until_finished()
            _write_outputs(run_dir, history, config)
            if progress:
                print(_epoch_line(record))
    finally:
        manager.close()
    if config.devices > 1:
        # The returned model lives on one device like a devices=1 run's, so that it mixes with the
        # single-device arrays of the planner and the benchmarks.
        params = jax.device_put(params, jax.devices()[0])
    return TrainResult(nnx.merge(graphdef, params), history, run_dir)


def evaluate_params(
    eval_step,
    params,
    samples: Mapping[str, np.ndarray],
    batch_size: int,
    key,
    sharding: jax.sharding.Sharding | None = None,
    resamples: int = 0,
) -> dict[str, Any]:
    """Metrics of `params` on preloaded columns (fixed-size padded batches, no noise): the summed
    classifier metrics (`summarise`) and, when the step gives per-sample scores, the judgement metrics
    (`train.judgement.judge`: AUC overall and per source, calibration, collisions' scores, refine AUC,
    the top-scored grasp per scene) under "judgement".

    sharding: where each batch [batch_size, ...] goes, as the training batches (`Placement.batch`; with
    replicated `params` the evaluation runs data-parallel too); None: the default device.
    resamples: > 0 adds scene-resampled intervals to the judgement (`train.judgement.scene_interval`)."""
    totals, per = score_samples(eval_step, params, samples, batch_size, key, sharding)
    metrics = summarise(totals)
    if per is not None:
        metrics["judgement"] = judge_samples(per, samples, resamples)
    return metrics


def score_samples(
    eval_step,
    params,
    samples: Mapping[str, np.ndarray],
    batch_size: int,
    key,
    sharding: jax.sharding.Sharding | None = None,
) -> tuple[dict[str, Any], dict[str, np.ndarray] | None]:
    """`eval_step` over preloaded columns [N] in fixed-size padded batches (batch i downsampled with
    fold_in(key, i)) -> (the summed batch stats, the per-sample outputs [N, ...] when the step gives
    them, else None)."""
    totals, parts = None, []
    n = len(samples["label"])
    for i, (index, weight) in enumerate(dataset.batch_indices(n, batch_size, None)):
        batch = jax.device_put(dataset.make_batch(samples, index, weight), sharding)
        stats = eval_step(params, batch, jax.random.fold_in(key, i))
        per = stats.pop("per_sample", None)
        if per is not None:
            parts.append({k: np.asarray(v)[: min(batch_size, n - i * batch_size)] for k, v in per.items()})
        totals = stats if totals is None else jax.tree.map(jnp.add, totals, stats)
    return totals, ({k: np.concatenate([p[k] for p in parts]) for k in parts[0]} if parts else None)


def judge_samples(per: Mapping[str, np.ndarray], samples: Mapping[str, np.ndarray], resamples: int = 0) -> dict[str, Any]:
    """`train.judgement.judge` of per-sample scores over the samples they scored (weight > 0: those
    with an anchor feature)."""
    from train.judgement import judge
    from train.sources import SOURCES

    rows = per["weight"] > 0
    column = {k: np.asarray(samples[k])[rows] for k in ("source", "outcome", "scene_seed") if k in samples}
    refine = per.get("refine_prob")
    return judge(
        per["prob"][rows],
        np.asarray(samples["label"])[rows],
        source=column.get("source"),
        outcome=column.get("outcome"),
        scene=column.get("scene_seed"),
        refine_score=None if refine is None else refine[rows],
        refine_label=None if refine is None else np.asarray(samples["refine_labels"])[rows],
        source_names=SOURCES,
        resamples=resamples,
    )


def _epoch_line(record: Mapping[str, Any]) -> str:
    def fmt(m):
        if not m:
            return "-"
        def f(v):
            return "n/a" if v is None else f"{v:.3f}"

        line = f"loss {f(m['loss'])} acc {f(m['accuracy'])} P {f(m['precision'])} R {f(m['recall'])}"
        if m.get("refine_accuracy") is not None:
            line += " refine " + "/".join(f(v) for v in m["refine_accuracy"])
        if m.get("judgement"):
            line += f" AUC {f(m['judgement'].get('auc'))} ECE {f(m['judgement'].get('ece'))}"
        return line

    line = f"epoch {record['epoch']}: train {fmt(record['train'])} | held-out {fmt(record['held_out'])}"
    if record.get("held_out_objects"):
        line += f" | held-out objects {fmt(record['held_out_objects'])}"
    return line
