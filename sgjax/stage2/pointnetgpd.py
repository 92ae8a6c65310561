"""PointNetGPD: a PointNet grasp-quality classifier over the gripper's closing region (baseline).

Liang et al., "PointNetGPD: Detecting Grasp Configurations from Point Sets", ICRA 2019: the points of
the scene inside the closing region of a grasp candidate, expressed in the grasp frame, go through a
PointNet (shared per-point MLP, max-pool over the points, MLP head) that classifies the grasp as
good or bad. Here, as in the SuperGrasp paper's baseline and ablations (Table I):

  crop_closing_regions  (sgjax.stage2.crops) world scene -> each candidate's gripper frame -> the points inside its closing
                        region (|x| <= w/2, |y| <= finger_width/2, 0 <= z <= finger_length;
                        `sgjax.geometry.gripper.points_in_closing_region`), up to `n_points` (PointNetGPD: 500)
                        in scene order (shuffle the scene first: `score` does), padded, with a mask.
  prepare_inputs        the same crop from stored enlarged-region samples (`train.dataset`, grasp
                        frame; the closing region is a subset of the enlarged region), with optional
                        training noise and shuffle.
  PointNetGPD           shared MLP (PointNetGPD: 64-64-64-128-1024) -> masked max-pool -> MLP head
                        (512-256) -> 2 logits (class 1 = stable grasp). Padding rows never reach
                        the max-pool (PointNetGPD pads by repeating points, which gives the same max).
  score                 crop + network for M candidates on one scene in one jitted call: probability
                        of a stable grasp [M], valid [M] (closing region not empty, finite pose, width
                        in range), count [M] (points found in the closing region).

Differences from the original, documented: no input/feature T-Nets and no batch norm (PointNetGPD's
PointNet had both; both are dispensable for a 3-D crop already in a canonical grasp frame and batch
norm would make scores depend on the batch); the points are multiplied by `input_scale` (1/0.05 m,
so a closing region spans about [-1, 1]) before the first layer. Binary classification (PointNetGPD
also had a 3-class variant), trained on the SAME shards as E-RNet with their `label` field only
(`train/train_pointnetgpd.py`, `sgjax train --network pointnetgpd`).

Configs: `PointNetGPDConfig.paper()` has PointNetGPD's layer sizes; `light()` (the default) is a
narrower network for the 2-core CPU; `tiny()` is for tests. Checkpoints use E-RNet's run-directory
layout (`run_dir/checkpoints/<epoch>/{params,opt_state,meta}`, meta["network"] = "pointnetgpd").
"""

from __future__ import annotations

import dataclasses
import functools
import os
from typing import Any

import jax
import jax.numpy as jnp
from flax import nnx

from sgjax.geometry import gripper
from sgjax.geometry.gripper import GripperSpec
from sgjax.stage2 import checkpoint
from sgjax.stage2.checkpoint import restore_run
from sgjax.utils import configs
from sgjax.stage2.crops import crop_closing_regions, in_closing_region_local
from sgjax.stage2.ernet import (
    DEFAULT_SPEC,
    anchor_feature,
    evaluation_loss,
    first_points,
    forward_chunked,
    region_inputs,
    scene_candidates,
)
from sgjax.stage2.pointnet2 import SharedMLP

NETWORK = "pointnetgpd"  # meta["network"] of a PointNetGPD run directory
TRAIN_COMMAND = "sgjax train --network pointnetgpd --data SHARD_DIR --out RUN_DIR"


# ---------------------------------------------------------------------------------------------
# Configuration.


@dataclasses.dataclass(frozen=True)
class PointNetGPDConfig:
    """PointNetGPD sizes and loss settings; hashable (static under jit) and JSON round-trippable.

    n_points: closing-region points fed to the network (PointNetGPD: 500), padded and masked.
    mlp: widths of the shared per-point MLP before the max-pool (PointNetGPD: 64, 64, 64, 128, 1024).
    head: hidden widths of the classifier after the max-pool (PointNetGPD: 512, 256); then 2 classes.
    input_scale: points (m) are multiplied by this before the first layer.
    noise_std: Gaussian noise (m) added to the points during training.
    label_smoothing: epsilon of the cross-entropy (0: PointNetGPD's plain NLL loss).
    """

    n_points: int = 500
    mlp: tuple[int, ...] = (64, 128, 256)
    head: tuple[int, ...] = (128, 64)
    input_scale: float = 20.0
    noise_std: float = 0.001
    label_smoothing: float = 0.0

    def __post_init__(self):
        object.__setattr__(self, "mlp", tuple(int(c) for c in self.mlp))
        object.__setattr__(self, "head", tuple(int(c) for c in self.head))
        if self.n_points < 1 or not self.mlp or min(self.mlp + self.head, default=1) < 1:
            raise ValueError(f"need n_points >= 1 and positive layer widths, got {self}")
        if not 0.0 <= self.label_smoothing < 1.0 or self.noise_std < 0 or not self.input_scale > 0:
            raise ValueError("label_smoothing must be in [0, 1), noise_std >= 0 and input_scale > 0")

    @classmethod
    def light(cls, **overrides) -> PointNetGPDConfig:
        """The CPU default: 500 points, shared MLP 64-128-256, head 128-64."""
        return cls(**overrides)

    @classmethod
    def paper(cls, **overrides) -> PointNetGPDConfig:
        """PointNetGPD's sizes: 500 points, shared MLP 64-64-64-128-1024, head 512-256."""
        return cls(**{"mlp": (64, 64, 64, 128, 1024), "head": (512, 256), **overrides})

    @classmethod
    def tiny(cls, **overrides) -> PointNetGPDConfig:
        """A minimal network (64 points, 16/32-wide layers) for tests and quick experiments."""
        return cls(**{"n_points": 64, "mlp": (16, 32), "head": (16,), **overrides})

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> PointNetGPDConfig:
        """The config back from `to_dict` (e.g. a checkpoint's JSON meta); ValueError names an unknown field."""
        return configs.from_dict(cls, data)


# ---------------------------------------------------------------------------------------------
# Network inputs.


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class PointNetGPDInputs:
    """points [M, n_points, 3] in the closing region, gripper frame (padding rows 0); mask bool [M, n_points]."""

    points: jax.Array
    mask: jax.Array

    @property
    def valid(self) -> jax.Array:
        """bool [M]: at least one point in the closing region."""
        return jnp.any(self.mask, axis=-1)


def prepare_inputs(
    points: jax.Array,
    mask: jax.Array | None,
    widths: jax.Array,
    spec: GripperSpec,
    config: PointNetGPDConfig,
    *,
    key: jax.Array | None = None,
    noise_std: float = 0.0,
) -> PointNetGPDInputs:
    """Grasp-frame points (e.g. a stored enlarged region) -> the closing-region crop the network sees.

    points [M, P, 3], mask [M, P] (None: all finite points), widths [M] -> PointNetGPDInputs. With
    `key`: Gaussian noise of `noise_std` m, then a random shuffle; then the first `n_points` points
    inside the closing region of each width are kept (fewer: masked padding).
    """
    points, mask, widths = region_inputs(points, mask, widths, key, noise_std)
    crop, keep = first_points(points, in_closing_region_local(points, widths, spec) & mask, config.n_points)
    return PointNetGPDInputs(crop, keep)


# ---------------------------------------------------------------------------------------------
# The network.


class PointNetGPD(nnx.Module):
    """Shared MLP over the closing-region points -> masked max-pool -> MLP head -> logits [M, 2]."""

    def __init__(self, config: PointNetGPDConfig | None = None, *, rngs: nnx.Rngs):
        config = PointNetGPDConfig() if config is None else config
        self.config = config
        self.point_mlp = SharedMLP(3, config.mlp, rngs=rngs)
        self.head = SharedMLP(config.mlp[-1], (*config.head, 2), rngs=rngs, final_relu=False)

    def __call__(self, inputs: PointNetGPDInputs) -> jax.Array:
        features = self.point_mlp(inputs.points * self.config.input_scale)
        return self.head(anchor_feature(features, inputs.mask))  # an empty region pools to 0


def probability(logits: jax.Array) -> jax.Array:
    """logits [..., 2] -> probability of a stable grasp [...]."""
    return jax.nn.softmax(logits, axis=-1)[..., 1]


def loss(logits: jax.Array, labels: jax.Array, config: PointNetGPDConfig, weights: jax.Array | None = None) -> jax.Array:
    """Cross-entropy of the 2-class logits [B, 2] against labels int [B] (weighted mean; optional smoothing)."""
    return evaluation_loss(logits, labels, config.label_smoothing, weights)


# ---------------------------------------------------------------------------------------------
# Inference.


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class PointNetGPDScores:
    """prob [M] (0 where not valid), valid bool [M], count int32 [M] (points in the closing region)."""

    prob: jax.Array
    valid: jax.Array
    count: jax.Array


@functools.partial(jax.jit, static_argnames=("graphdef", "spec"))
def score_regions(graphdef: nnx.GraphDef, state: nnx.State, points, mask, widths, *, spec: GripperSpec = DEFAULT_SPEC,
                 key: jax.Array | None = None) -> PointNetGPDScores:
    """Score pre-cropped grasp-frame samples (e.g. dataset regions): points [M, P, 3], mask [M, P],
    widths [M] -> PointNetGPDScores. `key` shuffles before keeping n_points (None: keep the order)."""
    model = nnx.merge(graphdef, state)
    widths = jnp.asarray(widths, jnp.float32)
    inputs = prepare_inputs(points, mask, widths, spec, model.config, key=key)
    valid = inputs.valid & jnp.isfinite(widths) & gripper.width_in_range(widths, spec)
    prob = probability(forward_chunked(model, inputs))
    return PointNetGPDScores(jnp.where(valid, prob, 0.0), valid, jnp.sum(inputs.mask, -1).astype(jnp.int32))


@functools.partial(jax.jit, static_argnames=("graphdef", "spec"))
def score(
    graphdef: nnx.GraphDef,
    state: nnx.State,
    scene: jax.Array,
    poses: jax.Array,
    widths: jax.Array,
    scene_mask: jax.Array | None = None,
    *,
    spec: GripperSpec = DEFAULT_SPEC,
    key: jax.Array | None = None,
) -> PointNetGPDScores:
    """PointNetGPD for M candidates on one scene: crop the closing regions and classify, one jitted call.

    graphdef, state = nnx.split(model); scene [N, 3] world, poses [M, 4, 4], widths [M], scene_mask
    [N] (None: all) -> PointNetGPDScores. The scene is shuffled with `key` (default a fixed key:
    deterministic) so each crop is a uniform sample of its region. Candidates with a non-finite pose
    or width, a width outside [0, max_opening] or an empty closing region are valid=False, prob 0.
    Static shapes: the same (N, M) never recompiles.
    """
    model = nnx.merge(graphdef, state)
    config: PointNetGPDConfig = model.config
    c = scene_candidates(scene, poses, widths, scene_mask, spec, key)
    region = crop_closing_regions(c.scene, c.poses, c.widths, spec, config.n_points, c.scene_mask)
    inputs = PointNetGPDInputs(region.points, region.mask)
    valid = c.ok & inputs.valid
    prob = probability(forward_chunked(model, inputs))
    return PointNetGPDScores(jnp.where(valid, prob, 0.0), valid, region.count)


# ---------------------------------------------------------------------------------------------
# Saved models (the trainer's run-directory layout, orbax).


def abstract_model(config: PointNetGPDConfig) -> PointNetGPD:
    """A PointNetGPD with shape-only parameters, for restoring checkpoints."""
    return nnx.eval_shape(lambda: PointNetGPD(config, rngs=nnx.Rngs(0)))


def load_model(run_dir: str | os.PathLike, epoch: int | None = None) -> tuple[PointNetGPD, dict[str, Any]]:
    """Load a trained PointNetGPD from a run directory (`sgjax train --network pointnetgpd`) -> (model, meta).

    epoch: which epoch (None: the latest). Raises FileNotFoundError when there is no checkpoint and
    ValueError when the run directory holds another network (e.g. an E-RNet run).
    """

    def abstract_from_meta(meta: dict[str, Any]) -> PointNetGPD:
        if meta.get("network") != NETWORK:
            raise ValueError(
                f"{run_dir} holds a {meta.get('network') or 'E-RNet'} run, not a PointNetGPD run (train one with `{TRAIN_COMMAND}`)"
            )
        return abstract_model(PointNetGPDConfig.from_dict(meta["model_config"]))

    return restore_run(run_dir, epoch, abstract_from_meta, missing_hint=f"; train one with `{TRAIN_COMMAND}`")


def load_default_model(spec: GripperSpec | None = None) -> PointNetGPD:
    """The shipped PointNetGPD checkpoint for gripper `spec` (`checkpoint.shipped_dir`:
    `sgjax/models/pointnetgpd_default/`, a run directory, unless one was shipped for `spec`; None: that one).

    Raises FileNotFoundError naming the path and the training command when it is missing."""
    path = checkpoint.shipped_dir(checkpoint.POINTNETGPD_DEFAULT_DIR, spec)
    return checkpoint.load_default(
        path,
        load_model,
        f"no default PointNetGPD checkpoint at {path}: train one on the E-RNet shards with "
        f"`{TRAIN_COMMAND}` and pass it as the method's model (`--model RUN_DIR`), or copy the run directory "
        f"to {path}",
    )


def as_model(model, spec: GripperSpec | None = None) -> PointNetGPD:
    """A PointNetGPD from None (the shipped one for gripper `spec`, `load_default_model`), a model, or a run
    directory."""
    return checkpoint.as_model(model, PointNetGPD, load_model, lambda: load_default_model(spec),
                               "a PointNetGPD, a run directory")
