"""Saved Stage-2 networks: the trainer's run-directory layout (orbax) and the one model loader.

A run directory (`sgjax train --out RUN_DIR`) holds `checkpoints/<epoch>/{params, opt_state, meta}`;
`restore_run` reads any network the trainer writes (E-RNet, PointNetGPD) from it. `load_default`
reads a checkpoint shipped in `sgjax/models/` (once per process), and `as_model` turns what a user
passes as "the model" (None for the shipped default, a model, or a run directory) into a model. Each
network module (`ernet`, `pointnetgpd`) binds these to its own class, shape-only model and directory.
"""

from __future__ import annotations

import functools
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

import jax
from flax import nnx

CHECKPOINT_DIR = "checkpoints"  # inside a run directory
PARAMS_ITEM, OPT_STATE_ITEM, META_ITEM = "params", "opt_state", "meta"

# The shipped checkpoints (package data of sgjax, not packages).
MODELS_DIR = Path(__file__).resolve().parent.parent / "models"
ERNET_DEFAULT_DIR = MODELS_DIR / "ernet_default"
POINTNETGPD_DEFAULT_DIR = MODELS_DIR / "pointnetgpd_default"

LoadModel = Callable[[str | os.PathLike], tuple[nnx.Module, dict[str, Any]]]


def restore_run(
    run_dir: str | os.PathLike,
    epoch: int | None,
    abstract_from_meta: Callable[[dict[str, Any]], nnx.Module],
    missing_hint: str = "",
) -> tuple[nnx.Module, dict[str, Any]]:
    """Restore a network from a run directory's orbax checkpoints -> (model, meta).

    Shared by every network the trainer writes (E-RNet, PointNetGPD). epoch: which epoch (None: the
    latest). `abstract_from_meta(meta)` builds the shape-only model to restore into; it may raise
    ValueError when meta describes another network. Raises FileNotFoundError (with `missing_hint`)
    when there is no such checkpoint.
    """
    import orbax.checkpoint as ocp

    directory = os.path.abspath(os.path.join(os.fspath(run_dir), CHECKPOINT_DIR))
    if not os.path.isdir(directory):
        raise FileNotFoundError(f"no checkpoints in {run_dir} (expected {directory}){missing_hint}")
    manager = ocp.CheckpointManager(directory, options=ocp.CheckpointManagerOptions(create=False))
    try:
        step = manager.latest_step() if epoch is None else epoch
        if step is None or step not in manager.all_steps():
            raise FileNotFoundError(f"no checkpoint for epoch {epoch} in {directory} (have {manager.all_steps()})")
        meta = manager.restore(step, args=ocp.args.Composite(**{META_ITEM: ocp.args.JsonRestore()}))[META_ITEM]
        graphdef, abstract = nnx.split(abstract_from_meta(meta))
        # Onto this process's first device whatever the saved sharding was: a run trained on several
        # devices (`sgjax train --devices N`) loads on a machine with fewer.
        device = jax.sharding.SingleDeviceSharding(jax.devices()[0])
        target = jax.tree.map(lambda x: _on(ocp.utils.to_shape_dtype_struct(x), device), abstract)
        restored = manager.restore(step, args=ocp.args.Composite(**{PARAMS_ITEM: ocp.args.StandardRestore(target)}))
    finally:
        manager.close()
    return nnx.merge(graphdef, restored[PARAMS_ITEM]), meta


def _on(leaf, sharding: jax.sharding.Sharding):
    """A restore target (jax.ShapeDtypeStruct) placed by `sharding`; other leaves as they are."""
    return jax.ShapeDtypeStruct(leaf.shape, leaf.dtype, sharding=sharding) if isinstance(leaf, jax.ShapeDtypeStruct) else leaf


# One entry per shipped network: a process that plans loads each default once.
@functools.lru_cache(maxsize=4)
def _load_once(path: str, load_model: LoadModel) -> nnx.Module:
    return load_model(path)[0]


def load_default(directory: Path, load_model: LoadModel, missing: str) -> nnx.Module:
    """The network shipped in `directory` (a run directory), loaded with `load_model` once per process.

    Raises FileNotFoundError(missing) when the directory holds no checkpoint; `missing` should name the
    path and the command that makes one."""
    if not (directory / CHECKPOINT_DIR).is_dir():
        raise FileNotFoundError(missing)
    return _load_once(str(directory), load_model)


def as_model(model, model_type: type, load_model: LoadModel, default: Callable[[], nnx.Module], what: str) -> nnx.Module:
    """`model` as a `model_type`: None -> `default()`, a model -> itself, a run directory -> `load_model`.

    Raises TypeError otherwise; `what` names the accepted model and run directory in the message."""
    if model is None:
        return default()
    if isinstance(model, model_type):
        return model
    if isinstance(model, (str, os.PathLike)):
        return load_model(model)[0]
    raise TypeError(f"model must be {what} or None, got {type(model).__name__}")
