"""Grasp trials on the MuJoCo C engine: `mujoco.batch.Batch`, one simulation per trial, on a thread pool.

Each phase is one `Batch.rollout` call whose per-step controls are the schedule's finger goals and
gripper target pose (mjSTATE_CTRL | MOCAP_POS | MOCAP_QUAT); the disturbance force is constant within a
phase, so it is written into the state rows (xfrc_applied) between calls. The contact sensors and object
velocities are recorded per step and reduced per phase right away, so memory stays O(batch * phase).
With `TrialConfig.early_stop`, trials whose outcome is decided are left out of the later phases.
"""

from __future__ import annotations

import copy

import mujoco
import numpy as np
from mujoco import batch as mj_batch

from envs import scene as scene_lib
from envs.rollout import (
    CONTROL_SPEC,
    FALLEN_BELOW,
    Judge,
    Phase,
    Rollout,
    Schedule,
    initial_states,
)


def rollout_cpu(scene: scene_lib.Scene, judge: Judge, schedule: Schedule, nthread: int = 0) -> Rollout:
    """Roll out the M trials of `schedule` (targets in `judge`) from the scene's settled state.

    nthread: engine threads (0: all cores).
    """
    model = scene.model
    if judge.config.sleep:  # on a copy: the scene's own model (settling, the camera) is unchanged
        model = copy.copy(model)
        model.opt.enableflags |= int(mujoco.mjtEnableBit.mjENBL_SLEEP)
    m = len(judge.targets)
    nphase = len(schedule.phase_steps)
    # Sleep's bookkeeping lives in each simulation's MjData, so it needs a persistent batch.
    batch = mj_batch.Batch(model, nsim=m, nthread=nthread, persistent=judge.config.sleep)
    batch.state[:] = initial_states(scene, schedule, judge.lay)
    xfrc, qpos = batch.bind("xfrc_applied"), batch.bind("qpos")
    target_bodies = scene.body_ids[judge.targets]
    controls = schedule.controls()
    # Parked (removed) objects sit far below FALLEN_BELOW, so every object can be checked.
    object_dofs = (judge.lay.object_qvel[:, None] + np.arange(3)).ravel()
    object_height = judge.lay.object_qpos + 2

    out = Rollout(
        contact_max=np.zeros((m, nphase, model.nsensordata)),
        end_contacts=np.zeros((m, nphase, model.nsensordata)),
        end_qpos=np.zeros((m, nphase, model.nq)),
        max_speed=np.zeros((m, nphase)),
        ok=np.ones(m, bool),
    )
    ok = out.ok
    active = np.ones(m, bool)
    steps_run = np.zeros(m, np.int64)
    start = 0
    for phase, nstep in enumerate(schedule.phase_steps):
        xfrc[:] = 0.0
        xfrc[np.arange(m), target_bodies, 2] = -schedule.phase_force[phase]
        rows = np.flatnonzero(active & ok)
        if len(rows):
            try:
                record = _rollout(batch, nstep, controls, start, rows)
            except mj_batch.SimulationError as error:
                # The failed simulations kept their state; run the phase again without them.
                ok[error.ids] = False
                rows = np.flatnonzero(active & ok)
                record = _rollout(batch, nstep, controls, start, rows)
            steps_run[rows] += nstep
            out.contact_max[rows, phase] = record["sensordata"].max(axis=1)
            out.end_contacts[rows, phase] = record["sensordata"][:, -1]
            speed = np.linalg.norm(record["qvel"][:, :, object_dofs].reshape(len(rows), nstep, -1, 3), axis=-1)
            on_table = record["qpos"][:, :, object_height] > FALLEN_BELOW  # objects that fell off may fall fast
            out.max_speed[rows, phase] = np.where(on_table, speed, 0.0).max(axis=(1, 2), initial=0.0)
        out.end_qpos[:, phase] = qpos
        if judge.config.early_stop and len(rows):
            active[rows[judge.failed(Phase(phase), out, rows)]] = False
        start += nstep
    # A simulation whose warning counters rose stopped stepping: its clock fell behind.
    expected = steps_run * model.opt.timestep
    ok &= np.abs(batch.bind("time") - expected) < 0.5 * model.opt.timestep
    return out


def _rollout(batch: mj_batch.Batch, nstep: int, controls: np.ndarray, start: int, rows: np.ndarray) -> dict:
    return batch.rollout(
        nstep,
        controls[rows, start : start + nstep],
        control_spec=int(CONTROL_SPEC),
        record=("sensordata", "qpos", "qvel"),
        ids=rows,
    )
