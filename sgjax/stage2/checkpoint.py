"""Saved Stage-2 networks: the trainer's run-directory layout (orbax) and the one model loader.

A run directory (`sgjax train --out RUN_DIR`) holds `checkpoints/<epoch>/{params, opt_state, meta}`;
`restore_run` reads any network the trainer writes (E-RNet, PointNetGPD) from it. `load_default`
reads a checkpoint shipped in `sgjax/models/` (once per process), and `as_model` turns what a user
passes as "the model" (None for the shipped default, a model, or a run directory) into a model. Each
network module (`ernet`, `pointnetgpd`) binds these to its own class, shape-only model and directory.

A checkpoint knows its gripper: the trainer records `gripper_to_dict(spec)` of its training data as
meta["gripper"]; `checkpoint_gripper(run_dir)` / `meta_gripper(meta)` read it back (a checkpoint without
the record, as the shipped defaults, counts as the default gripper), `shipped_dir` picks the shipped
checkpoint made for a gripper (`sgjax/models/ernet_<gripper>` beside `ernet_default`), and
`gripper_mismatch` words the warning a planner gives when it plans for another gripper than its network
was trained for.
"""

from __future__ import annotations

import contextlib
import functools
import os
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import jax
from flax import nnx

from sgjax.geometry.gripper import GripperSpec
from sgjax.geometry.gripper_files import gripper_from_dict

CHECKPOINT_DIR = "checkpoints"  # inside a run directory
PARAMS_ITEM, OPT_STATE_ITEM, META_ITEM = "params", "opt_state", "meta"

# The shipped checkpoints (package data of sgjax, not packages).
MODELS_DIR = Path(__file__).resolve().parent.parent / "models"
ERNET_DEFAULT_DIR = MODELS_DIR / "ernet_default"
POINTNETGPD_DEFAULT_DIR = MODELS_DIR / "pointnetgpd_default"

LoadModel = Callable[[str | os.PathLike], tuple[nnx.Module, dict[str, Any]]]


@contextlib.contextmanager
def _checkpoint_step(run_dir: str | os.PathLike, epoch: int | None, missing_hint: str = ""):
    """(orbax CheckpointManager of the run's checkpoints, the step of `epoch`; None: the latest), closed
    after use. Raises FileNotFoundError (with `missing_hint`) when there is no such checkpoint."""
    import orbax.checkpoint as ocp

    directory = os.path.abspath(os.path.join(os.fspath(run_dir), CHECKPOINT_DIR))
    if not os.path.isdir(directory):
        raise FileNotFoundError(f"no checkpoints in {run_dir} (expected {directory}){missing_hint}")
    manager = ocp.CheckpointManager(directory, options=ocp.CheckpointManagerOptions(create=False))
    try:
        step = manager.latest_step() if epoch is None else epoch
        if step is None or step not in manager.all_steps():
            raise FileNotFoundError(f"no checkpoint for epoch {epoch} in {directory} (have {manager.all_steps()})")
        yield manager, step
    finally:
        manager.close()


def _restore_meta(manager, step: int) -> dict[str, Any]:
    import orbax.checkpoint as ocp

    return manager.restore(step, args=ocp.args.Composite(**{META_ITEM: ocp.args.JsonRestore()}))[META_ITEM]


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

    with _checkpoint_step(run_dir, epoch, missing_hint) as (manager, step):
        meta = _restore_meta(manager, step)
        graphdef, abstract = nnx.split(abstract_from_meta(meta))
        # Onto this process's first device whatever the saved sharding was: a run trained on several
        # devices (`sgjax train --devices N`) loads on a machine with fewer.
        device = jax.sharding.SingleDeviceSharding(jax.devices()[0])
        target = jax.tree.map(lambda x: _on(ocp.utils.to_shape_dtype_struct(x), device), abstract)
        restored = manager.restore(step, args=ocp.args.Composite(**{PARAMS_ITEM: ocp.args.StandardRestore(target)}))
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


# ---------------------------------------------------------------------------------------------
# The gripper a checkpoint was trained for (the trainer records `gripper_to_dict(spec)` as meta["gripper"]).

GRIPPER_ITEM = "gripper"  # the meta entry
IN_MEMORY = "an in-memory model"


def read_meta(run_dir: str | os.PathLike, epoch: int | None = None) -> dict[str, Any]:
    """The JSON meta of a run directory's checkpoint (None: the latest epoch), without its parameters.

    Raises FileNotFoundError when there is no such checkpoint."""
    with _checkpoint_step(run_dir, epoch) as (manager, step):
        return _restore_meta(manager, step)


def meta_gripper(meta: dict[str, Any], source: str = "checkpoint") -> GripperSpec:
    """The gripper a checkpoint's meta records (meta["gripper"], `gripper_to_dict`'s table); a meta
    without the record (every checkpoint written before it existed, the shipped ones included) counts
    as the default gripper, `GripperSpec()`. A record that does not read raises GripperFileError."""
    record = meta.get(GRIPPER_ITEM) if isinstance(meta, dict) else None
    if record is None:
        return GripperSpec()
    return gripper_from_dict(record, f"{source}: meta[{GRIPPER_ITEM!r}]")


@functools.lru_cache(maxsize=16)
def _run_gripper(path: str, mtime: float) -> GripperSpec:
    return meta_gripper(read_meta(path), path)


def checkpoint_gripper(run_dir: str | os.PathLike) -> GripperSpec:
    """The gripper the latest checkpoint of a run directory was trained for (`meta_gripper` of its meta):
    what the command line and `sgjax.planner.Planner` compare with the gripper they plan for. Read once
    per directory and version (cached)."""
    path = os.path.abspath(os.fspath(run_dir))
    directory = os.path.join(path, CHECKPOINT_DIR)
    mtime = os.path.getmtime(directory) if os.path.isdir(directory) else 0.0
    return _run_gripper(path, mtime)


def shipped_dir(default_dir: Path, spec: GripperSpec | None) -> Path:
    """The shipped checkpoint for gripper `spec`: of `default_dir` (`sgjax/models/ernet_default`) and its
    siblings shipped for other grippers (`sgjax/models/ernet_<gripper>`), the first (default_dir, then by
    name) whose meta records `spec` (`checkpoint_gripper`); default_dir when none does (planning with it
    is then warned about, `warn_gripper`) or when spec is None."""
    if spec is None:
        return default_dir
    prefix = default_dir.name.rsplit("_", 1)[0] + "_"
    siblings = sorted(d for d in default_dir.parent.glob(prefix + "*") if d != default_dir)
    for directory in [default_dir, *siblings]:
        if (directory / CHECKPOINT_DIR).is_dir() and checkpoint_gripper(directory) == spec:
            return directory
    return default_dir


def checkpoint_name(model, default_dir: Path) -> str:
    """How to name the checkpoint behind what a user passed as "the model" (None, a run directory or a
    model): "sgjax/models/ernet_default" for the shipped one in `default_dir`, the run directory, or "an
    in-memory model"."""
    if model is None:
        return f"sgjax/models/{default_dir.name}" if default_dir.parent == MODELS_DIR else str(default_dir)
    if isinstance(model, (str, os.PathLike)):
        return os.fspath(model)
    return IN_MEMORY


def model_gripper(model, default_dir: Path) -> GripperSpec | None:
    """The gripper of the checkpoint behind `model` as `checkpoint_name` names it (None, the shipped
    checkpoint in `default_dir`; a run directory); None for a model in memory (its gripper is unknown)."""
    if model is None:
        return checkpoint_gripper(default_dir)
    if isinstance(model, (str, os.PathLike)):
        return checkpoint_gripper(model)
    return None


def describe_gripper(spec: GripperSpec, other: GripperSpec | None = None) -> str:
    """"robotiq-2f85 (max_opening 0.085 m, ...)": the preset `spec` equals (else "a custom gripper"), with
    up to three of the values that differ from `other` (max_opening, finger_length and closing_force when
    None), the stroke, the fingers and the force first."""
    from sgjax.geometry.gripper_files import gripper_to_dict, load_gripper, preset_names

    name = next((n for n in preset_names() if load_gripper(n) == spec), "a custom gripper")
    mine = gripper_to_dict(spec)
    if other is None:
        keys = ["max_opening", "finger_length", "closing_force"]
    else:
        theirs = gripper_to_dict(other)
        keys = sorted((k for k in mine if mine[k] != theirs[k]), key=lambda k: (k not in _FIRST, _FIRST.index(k) if k in _FIRST else 0))
        keys = keys or ["max_opening"]
    units = {"closing_force": " N", "finger_friction": "", "refine_angles_deg": " deg"}
    shown = ", ".join(f"{k} {_number(mine[k])}{units.get(k, ' m')}" for k in keys[:3])
    return f"{name} ({shown}{', ...' if len(keys) > 3 else ''})"


_FIRST = ["max_opening", "finger_length", "closing_force", "finger_friction"]  # shown first by describe_gripper


def _number(value) -> str:
    if isinstance(value, list):
        return "[" + ", ".join(f"{v:g}" for v in value) + "]"
    return f"{value:g}"


class GripperMismatchWarning(UserWarning):
    """A network checkpoint plans for another gripper than the one it was trained for (`gripper_mismatch`)."""


def gripper_mismatch(network: str, checkpoint: str, trained: GripperSpec | None, spec: GripperSpec) -> str | None:
    """The warning for a network checkpoint trained for gripper `trained` that plans for gripper `spec`;
    None when they agree or the checkpoint's gripper is unknown (a model in memory)."""
    if trained is None or trained == spec:
        return None
    return (f"{network} checkpoint {checkpoint} was trained for gripper {describe_gripper(trained, spec)} but plans "
            f"for gripper {describe_gripper(spec, trained)}: retrain with `sgjax label --gripper` and "
            "`sgjax train` on those labels, or plan without a network (`--model none`; measured better than "
            "another gripper's E-RNet: docs/grippers.md)")


def model_checkpoint(model, default_dir: Path, spec: GripperSpec) -> tuple[str, GripperSpec | None]:
    """(`checkpoint_name`, `model_gripper`) of the checkpoint behind `model` for a planner of gripper
    `spec`: None is the one shipped for `spec` (`shipped_dir(default_dir, spec)`), a run directory itself."""
    shipped = shipped_dir(default_dir, spec)
    return checkpoint_name(model, shipped), model_gripper(model, shipped)


def warn_mismatch(network: str, name: str, trained: GripperSpec | None, spec: GripperSpec,
                  stacklevel: int = 3) -> str | None:
    """`warnings.warn` the `gripper_mismatch` of checkpoint `name`, trained for gripper `trained` (None: a
    model in memory, never warned about), planning for `spec`; returns the message (None: no warning)."""
    message = gripper_mismatch(network, name, trained, spec)
    if message is not None:
        warnings.warn(message, GripperMismatchWarning, stacklevel=stacklevel)
    return message


def warn_gripper(network: str, model, default_dir: Path, spec: GripperSpec, stacklevel: int = 3) -> str | None:
    """`warn_mismatch` for the checkpoint behind `model` (`model_checkpoint`) planning for `spec`."""
    return warn_mismatch(network, *model_checkpoint(model, default_dir, spec), spec, stacklevel=stacklevel + 1)
