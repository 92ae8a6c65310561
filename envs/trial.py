"""Grasp trials (paper Sec. V-A): the entry points, which choose a simulation backend.

`run_trials` simulates grasps from a scene's settled state on the chosen backend: the C engine
(`backend="cpu"`, `envs.backend_cpu`) or MJX (`backend="mjx"`, `envs.backend_mjx`: its warp
implementation on a GPU where `warp-lang` is installed, else its JAX one; "mjx-jax" / "mjx-warp" pick
one). The backends implement one contract, `envs.rollout` (schedule in, per-phase `Rollout` out); this
module sits above them and is the only one that imports them. The trial's phases and outcomes are
described in `envs.rollout`; its public types are re-exported here for callers of `run_trials`.
"""

from __future__ import annotations

import dataclasses
import functools

import numpy as np

from envs import scene as scene_lib
from envs.rollout import (
    Judge,
    Outcome,
    Phase,
    TrialConfig,
    TrialResult,
    check_grasps,
    check_targets,
    classify,
    layout,
    make_schedule,
    touched,
)
from sgjax.geometry.gripper import GripperSpec, enlarged_region_poses

__all__ = [
    "BACKENDS",
    "Outcome",
    "Phase",
    "TrialConfig",
    "TrialResult",
    "check_backend",
    "run_grasp_with_refinements",
    "run_trials",
    "what_touched",
]

# ---------------------------------------------------------------------------------------------
# Entry points.


BACKENDS = ("cpu", "mjx", "mjx-jax", "mjx-warp")
_MJX_IMPL = {"mjx": "auto", "mjx-jax": "jax", "mjx-warp": "warp"}


def check_backend(backend: str) -> str:
    """-> backend, or ValueError naming the valid ones."""
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {', '.join(repr(b) for b in BACKENDS)}, got {backend!r}")
    return backend


def run_trials(
    scene: scene_lib.Scene,
    targets,
    poses,
    widths,
    backend: str = "cpu",
    spec: GripperSpec | None = None,
    config: TrialConfig = TrialConfig(),
    nthread: int = 0,
) -> TrialResult:
    """Simulate grasps (poses[M, 4, 4], widths[M]) on target objects targets[M] (or one int) of `scene`.

    Every trial starts from the scene's settled state. backend: "cpu" (C engine, mujoco.batch on
    `nthread` threads, 0 = all cores) or "mjx" (jit-compiled once per scene model and batch size; the
    warp implementation on a GPU where warp-lang is installed, else JAX), "mjx-jax" or "mjx-warp".
    spec defaults to the scene's GripperSpec (the one the simulated gripper was built from).
    Raises ValueError for bad poses (shape, non-finite, not rigid), widths out of [0, max_opening],
    targets out of range or removed, or an unknown backend.
    """
    spec = scene.gripper if spec is None else spec
    if spec != scene.gripper:
        raise ValueError("spec differs from the GripperSpec the scene's gripper was built from")
    poses, widths = check_grasps(poses, widths, spec)
    targets = check_targets(targets, len(poses), scene)
    if check_backend(backend) == "cpu":
        from envs.backend_cpu import rollout_cpu as rollout_fn
    else:
        from envs.backend_mjx import resolve_impl, rollout_mjx

        rollout_fn = functools.partial(rollout_mjx, impl=resolve_impl(_MJX_IMPL[backend]))

    lay = layout(scene)
    results = []
    for start in range(0, len(poses), config.batch_size):
        part = slice(start, start + config.batch_size)
        schedule = make_schedule(poses[part], widths[part], spec, config, scene.model.opt.timestep)
        judge = Judge.make(scene, targets[part], lay, config)
        rollout = rollout_fn(scene, judge, schedule, nthread=nthread)
        results.append(classify(judge, rollout))
    return TrialResult(*(np.concatenate(fields) for fields in zip(*(dataclasses.astuple(r) for r in results))))


def run_grasp_with_refinements(
    scene: scene_lib.Scene,
    targets,
    poses,
    widths,
    backend: str = "cpu",
    spec: GripperSpec | None = None,
    config: TrialConfig = TrialConfig(),
    nthread: int = 0,
) -> tuple[np.ndarray, TrialResult]:
    """Each grasp and its refinements (paper Sec. IV-C): labels [M, 1 + K] and the TrialResult [M * (1 + K)].

    Column 0 is the initial grasp, column 1 + v `sgjax.geometry.gripper.refined_pose(pose, v)` (default: deepen
    0.008 m along approach, then rotate -15, 0, +15 deg about it), all at the same width. The result's
    trials are ordered grasp-major ([M, 1 + K] flattened).
    """
    spec = scene.gripper if spec is None else spec
    poses, widths = check_grasps(poses, widths, spec)
    # Padded to a power of two: the jitted variants compile once per size class, not once per M.
    padded = np.tile(np.eye(4), (1 << max(len(poses) - 1, 0).bit_length(), 1, 1))
    padded[: len(poses)] = poses
    variants = np.asarray(enlarged_region_poses(padded, spec), np.float64)[: len(poses)]  # [M, 1 + K, 4, 4]
    k = variants.shape[1]
    # float32 JAX math leaves rotations orthonormal to ~1e-7: re-orthonormalise before the checks.
    u, _, vt = np.linalg.svd(variants[..., :3, :3])
    variants[..., :3, :3] = u @ vt
    targets = check_targets(targets, len(poses), scene)
    result = run_trials(
        scene,
        np.repeat(targets, k),
        variants.reshape(-1, 4, 4),
        np.repeat(widths, k),
        backend=backend,
        spec=spec,
        config=config,
        nthread=nthread,
    )
    return result.label.reshape(len(poses), k), result


def what_touched(scene: scene_lib.Scene, result: TrialResult, row: int, phase: Phase | None = None) -> dict:
    """What trial `row` of `result` (run on `scene`) touched during `phase`, by default the phase that
    decided its outcome: {"phase": name, "table": bool, "objects": {object index: "finger" | "palm" |
    "finger+palm"}} (`envs.rollout.touched`). For a collision outcome, the table or an object other than
    the target here is what failed the trial.
    """
    phase = Phase(int(result.decided_at[row]) if phase is None else phase)
    return {"phase": phase.name.lower(), **touched(result, layout(scene), row, phase)}
