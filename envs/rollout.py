"""The grasp-trial contract (paper Sec. V-A): what every simulation backend takes and returns.

A trial backend (`envs.backend_cpu`, `envs.backend_mjx`) imports this module only: it rolls a
`Schedule` out for the trials a `Judge` describes and reports a `Rollout`; `classify` turns that into
`TrialResult` outcomes. `envs.trial` chooses the backend (`run_trials`) and is what callers use.

Trials: approach, close, lift, reorient, 1 N disturbance.

A trial is an open-loop schedule over time, computed once from (pose, width, GripperSpec, TrialConfig)
by `make_schedule` and rolled out for many grasps in parallel from the same settled scene state, by
the C engine (`backend="cpu"`, mujoco.batch) or MJX (`backend="mjx"`, jit + vmap + scan; its warp
implementation on a GPU where `warp-lang` is installed, else its JAX one; "mjx-jax" / "mjx-warp" pick
one). All backends return the same per-phase summary (`Rollout`), which `classify` turns into outcomes.

Phases (defaults; 2.04 s simulated, 1020 steps at 2 ms):
  PREGRASP  0.04 s  gripper placed `pregrasp_distance` behind the grasp along -approach, fingers
                    open to the grasp width w (exactly w: the widths of Stage 1 already carry the
                    paper's contact clearance delta); any gripper contact -> COLLISION_PREGRASP.
  APPROACH  0.20 s  straight along the approach axis to the grasp pose (smooth-step profile);
  CLOSE     0.30 s  finger servos ramp to 1 cm beyond closed, force-limited at grip_force; any
                    gripper contact with the table or a non-target object during APPROACH or CLOSE
                    -> COLLISION_APPROACH (paper: "if the gripper collides with surrounding objects,
                    the label is directly set to 0"; touching the table counts, as a real arm would
                    press into it). Touching the target is allowed.
  LIFT      0.40 s  straight up by `lift_height`;                     not held -> DROPPED_LIFT
  REORIENT  0.50 s  rotate about the closing-region centre until the approach axis points straight
                    down (smallest rotation; about the closing axis if it points straight up);
  HOLD      0.10 s  still;                                            not held -> DROPPED_REORIENT
  DISTURB   0.50 s  1 N straight down on the target's centre of mass; not held, or the target
                    slid more than `max_slip` (1 cm) relative to the gripper -> DROPPED_DISTURBANCE
  otherwise SUCCESS (label 1). After the grasp closes, contacts with neighbours are not failures.
"Held": both fingers touch the target and its centre of mass is at least lift_height / 2 above where it
started. A NaN, an engine error or warning, or any object faster than `max_object_speed` makes the trial
INVALID, never a success.
"""

from __future__ import annotations

import dataclasses
import enum

import mujoco
import numpy as np
from scipy.spatial.transform import Rotation

from envs import gripper_model
from envs.outcome import Outcome
from envs import scene as scene_lib
from sgjax.geometry.gripper import GripperSpec, check_width


class Phase(enum.IntEnum):
    PREGRASP = 0
    APPROACH = 1
    CLOSE = 2
    LIFT = 3
    REORIENT = 4
    HOLD = 5
    DISTURB = 6


@dataclasses.dataclass(frozen=True)
class TrialConfig:
    """Timing and thresholds of a trial (seconds, metres, newtons); see the module docstring.

    close_target: finger servo goal while closing, beyond closed so that the grip force saturates.
    max_object_speed: any object on or above the table faster than this (m/s) marks the trial INVALID
        (flung away); a free fall from the lift height reaches ~2.4 m/s. Objects that fell off the
        table (centre of mass below FALLEN_BELOW) fall freely and are not counted.
    max_slip: the target may move at most this far relative to the gripper during DISTURB (m), or
        the grasp did not "remain stable" (paper) and the trial is DROPPED_DISTURBANCE.
    batch_size: trials per engine call (CPU) or per compiled MJX batch (fixed shape, padded).
    early_stop: the CPU backend stops simulating a trial as soon as its outcome is decided (a
        collision, a drop); its traces then repeat the state at the stop. Outcomes are unchanged.
    sleep: the CPU backend lets bodies at rest sleep (MuJoCo's mjENBL_SLEEP, in a persistent batch)
        until something touches them: resting neighbours cost nothing. Measured 1.65x faster with the
        same outcome for all ~640 trials of 3 labelled scenes (docs/experiments.md). MJX has no sleep.
    """

    pregrasp_distance: float = 0.05
    pregrasp_time: float = 0.04
    approach_time: float = 0.2
    close_time: float = 0.3
    close_ramp_fraction: float = 0.6
    close_target: float = -0.01
    lift_height: float = 0.2
    lift_time: float = 0.4
    reorient_time: float = 0.5
    hold_time: float = 0.1
    disturbance_force: float = 1.0
    disturbance_time: float = 0.5
    max_object_speed: float = 5.0
    max_slip: float = 0.01
    batch_size: int = 256
    early_stop: bool = True
    sleep: bool = True

    def __post_init__(self):
        for field in dataclasses.fields(self):
            value = getattr(self, field.name)
            if field.name not in ("close_target", "early_stop", "sleep") and not value >= 0:
                raise ValueError(f"TrialConfig.{field.name} must be non-negative, got {value}")
        if self.batch_size < 1:
            raise ValueError(f"TrialConfig.batch_size must be >= 1, got {self.batch_size}")
        if not 0 < self.close_ramp_fraction <= 1:
            raise ValueError(f"close_ramp_fraction must be in (0, 1], got {self.close_ramp_fraction}")

    def phase_steps(self, timestep: float) -> tuple[int, ...]:
        """Steps of each Phase at `timestep` (at least one each)."""
        times = (
            self.pregrasp_time,
            self.approach_time,
            self.close_time,
            self.lift_time,
            self.reorient_time,
            self.hold_time,
            self.disturbance_time,
        )
        return tuple(max(1, round(t / timestep)) for t in times)


@dataclasses.dataclass(frozen=True)
class Schedule:
    """Open-loop controls of M trials over T steps (the phases back to back).

    phase_steps: [P] steps per phase; T = sum.
    mocap_pos: [M, T, 3], mocap_quat: [M, T, 4] (w, x, y, z) gripper target pose per step.
    finger_ctrl: [M, T] servo goal of each finger joint (opening / 2).
    phase_force: [P] downward force on the target's centre of mass during each phase (N).
    init_qpos: [M, 7] gripper free joint at t = 0 (the pre-grasp pose); init_finger: [M] finger q.
    """

    phase_steps: tuple[int, ...]
    mocap_pos: np.ndarray
    mocap_quat: np.ndarray
    finger_ctrl: np.ndarray
    phase_force: np.ndarray
    init_qpos: np.ndarray
    init_finger: np.ndarray

    @property
    def nstep(self) -> int:
        return int(sum(self.phase_steps))

    def controls(self) -> np.ndarray:
        """[M, T, 9] per-step (ctrl left, ctrl right, mocap pos, mocap quat) in MuJoCo state order."""
        ctrl = np.repeat(self.finger_ctrl[..., None], 2, axis=-1)
        return np.concatenate([ctrl, self.mocap_pos, self.mocap_quat], axis=-1)


# Objects whose centre of mass is below this height (m) fell off the table: their (free-fall) speed does
# not count as a simulation instability.
FALLEN_BELOW = -0.05

CONTROL_SPEC = (
    mujoco.mjtState.mjSTATE_CTRL | mujoco.mjtState.mjSTATE_MOCAP_POS | mujoco.mjtState.mjSTATE_MOCAP_QUAT
)


@dataclasses.dataclass(frozen=True)
class Rollout:
    """What a backend reports per trial and phase (M trials, P phases, S contact sensors).

    contact_max: [M, P, S] the largest count of each contact sensor over the phase's steps.
    end_contacts: [M, P, S] the counts at the last step of each phase.
    end_qpos: [M, P, nq] joint positions at the end of each phase.
    max_speed: [M, P] fastest linear speed of any present object on or above the table during the phase.
    ok: [M] False where the engine failed, warned or stopped early, or (MJX warp) lost contacts; NaNs
        are found per phase from end_qpos / max_speed.
    """

    contact_max: np.ndarray
    end_contacts: np.ndarray
    end_qpos: np.ndarray
    max_speed: np.ndarray
    ok: np.ndarray


@dataclasses.dataclass(frozen=True)
class TrialResult:
    """Outcomes of M trials and the traces their tests need.

    outcome: [M] int8 Outcome codes; label: [M] bool (outcome == SUCCESS).
    object_pose: [M, P, 7] target pose (position, quaternion wxyz) at the end of each phase.
    gripper_pose: [M, P, 7] gripper pose at the end of each phase.
    object_in_gripper: [M, P, 3] target centre of mass in the gripper frame at the end of each phase.
    opening: [M, P] finger opening (m) at the end of each phase.
    held: [M, P] the "held" test at the end of each phase.
    slip: [M] how far the target moved in the gripper frame during DISTURB (m).
    max_speed: [M] fastest object speed over the trial (m/s).
    final_qpos: [M, nq] joint positions where each trial ended (or stopped early): what a failed grasp
        did to the scene (`envs.scene.after_trial`).
    decided_at: [M] the Phase that decided the outcome (the first failing one; the last for a success).
    contacts: [M, P, S] the largest count of each contact sensor over each phase (`Rollout.contact_max`;
        sensor order `envs.gripper_model.contact_sensor_names`): what the gripper touched, read by
        `touched`.
    """

    outcome: np.ndarray
    object_pose: np.ndarray
    gripper_pose: np.ndarray
    object_in_gripper: np.ndarray
    opening: np.ndarray
    held: np.ndarray
    slip: np.ndarray
    max_speed: np.ndarray
    final_qpos: np.ndarray
    decided_at: np.ndarray
    contacts: np.ndarray

    @property
    def label(self) -> np.ndarray:
        return self.outcome == Outcome.SUCCESS

    def counts(self) -> dict[str, int]:
        """Number of trials per outcome name."""
        return {o.name.lower(): int((self.outcome == o).sum()) for o in Outcome}


# ---------------------------------------------------------------------------------------------
# Inputs.


def check_grasps(poses, widths, spec: GripperSpec) -> tuple[np.ndarray, np.ndarray]:
    """Validate grasps: poses[M, 4, 4] rigid transforms, widths[M] in [0, max_opening].

    Returns them as float64 arrays; raises ValueError naming the problem.
    """
    poses = np.asarray(poses, np.float64)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4):
        raise ValueError(f"poses must have shape [M, 4, 4], got {poses.shape}")
    if len(poses) == 0:
        raise ValueError("poses must hold at least one grasp")
    widths = np.asarray(widths, np.float64)
    if widths.shape != (len(poses),):
        raise ValueError(f"widths must have shape [{len(poses)}] (one per pose), got {widths.shape}")
    if not np.isfinite(poses).all():
        bad = int(np.flatnonzero(~np.isfinite(poses).all(axis=(1, 2)))[0])
        raise ValueError(f"pose {bad} has non-finite entries")
    rotation = poses[:, :3, :3]
    orth = np.abs(np.einsum("mji,mjk->mik", rotation, rotation) - np.eye(3)).max(axis=(1, 2))
    det = np.linalg.det(rotation)
    bottom = np.abs(poses[:, 3] - [0.0, 0.0, 0.0, 1.0]).max(axis=1)
    bad = (orth > 1e-4) | (det < 0) | (bottom > 1e-9)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise ValueError(
            f"pose {i} is not a rigid transform (|R^T R - I| = {orth[i]:.2e}, det R = {det[i]:.3f}, "
            f"last row {poses[i, 3].tolist()}); {int(bad.sum())} of {len(poses)} bad"
        )
    return poses, check_width(widths, spec)


def check_targets(targets, n: int, scene: scene_lib.Scene) -> np.ndarray:
    targets = np.asarray(targets)
    if targets.shape not in ((), (n,)):
        raise ValueError(f"targets must be one object index or one per grasp [{n}], got shape {targets.shape}")
    targets = np.broadcast_to(targets, (n,))
    if not np.issubdtype(targets.dtype, np.integer):
        raise ValueError(f"targets must be object indices (integers), got dtype {targets.dtype}")
    if ((targets < 0) | (targets >= scene.n_objects)).any():
        raise ValueError(f"targets must be in [0, {scene.n_objects}), got {np.unique(targets).tolist()}")
    removed = ~scene.present[targets]
    if removed.any():
        raise ValueError(f"target object {int(targets[removed][0])} was removed from the scene")
    return targets.astype(np.int64)


# ---------------------------------------------------------------------------------------------
# The schedule.


def _quat_wxyz(rotation: Rotation) -> np.ndarray:
    return np.roll(rotation.as_quat(), 1, axis=-1)


def _smoothstep(n: int) -> np.ndarray:
    """[n] progress 0 -> 1 with zero velocity at both ends, reaching 1 at the last step."""
    s = np.arange(1, n + 1) / n
    return s * s * (3.0 - 2.0 * s)


def _turn_down(rotation: np.ndarray) -> np.ndarray:
    """[M, 3] rotation vectors (world frame) of the smallest turn taking each approach axis to -z.

    An approach axis pointing straight up turns about the gripper's closing axis.
    """
    z = rotation[:, :, 2]
    down = np.array([0.0, 0.0, -1.0])
    axis = np.cross(z, down)
    sin = np.linalg.norm(axis, axis=1)
    cos = z @ down
    angle = np.arctan2(sin, cos)
    unit = np.where(sin[:, None] > 1e-9, axis / np.maximum(sin, 1e-12)[:, None], rotation[:, :, 0])
    return unit * angle[:, None]


def make_schedule(
    poses: np.ndarray,
    widths: np.ndarray,
    spec: GripperSpec,
    config: TrialConfig = TrialConfig(),
    timestep: float = 0.002,
) -> Schedule:
    """The open-loop trial of grasps poses[M, 4, 4] (gripper frame -> world), widths[M]; pure function."""
    poses, widths = check_grasps(poses, widths, spec)
    m = len(poses)
    steps = config.phase_steps(timestep)
    rotation, grasp = poses[:, :3, :3], poses[:, :3, 3]
    approach = rotation[:, :, 2]
    pre = grasp - config.pregrasp_distance * approach
    quat0 = _quat_wxyz(Rotation.from_matrix(rotation))
    half = 0.5 * widths

    pos_parts, quat_parts, ctrl_parts = [], [], []

    def hold(pos: np.ndarray, quat: np.ndarray, ctrl: np.ndarray, n: int) -> None:
        pos_parts.append(np.repeat(pos[:, None], n, axis=1))
        quat_parts.append(np.repeat(quat[:, None], n, axis=1))
        ctrl_parts.append(np.repeat(ctrl[:, None], n, axis=1))

    closed = np.full(m, config.close_target)
    hold(pre, quat0, half, steps[Phase.PREGRASP])
    # Approach: straight along +z of the gripper.
    s = _smoothstep(steps[Phase.APPROACH])
    pos_parts.append(pre[:, None] + s[None, :, None] * (grasp - pre)[:, None])
    quat_parts.append(np.repeat(quat0[:, None], len(s), axis=1))
    ctrl_parts.append(np.repeat(half[:, None], len(s), axis=1))
    # Close: linear ramp of the servo goal, then hold it.
    n = steps[Phase.CLOSE]
    ramp = np.clip(np.arange(1, n + 1) / max(1, round(config.close_ramp_fraction * n)), 0.0, 1.0)
    pos_parts.append(np.repeat(grasp[:, None], n, axis=1))
    quat_parts.append(np.repeat(quat0[:, None], n, axis=1))
    ctrl_parts.append(half[:, None] + ramp[None] * (closed - half)[:, None])
    # Lift: straight up.
    s = _smoothstep(steps[Phase.LIFT])
    lifted = grasp + [0.0, 0.0, config.lift_height]
    pos_parts.append(grasp[:, None] + s[None, :, None] * (lifted - grasp)[:, None])
    quat_parts.append(np.repeat(quat0[:, None], len(s), axis=1))
    ctrl_parts.append(np.repeat(closed[:, None], len(s), axis=1))
    # Reorient: turn about the closing-region centre until the approach axis points down.
    s = _smoothstep(steps[Phase.REORIENT])
    turn = _turn_down(rotation)
    offset = np.array([0.0, 0.0, 0.5 * spec.finger_length])  # closing-region centre, gripper frame
    centre = lifted + rotation @ offset
    partial = Rotation.from_rotvec((s[None, :, None] * turn[:, None]).reshape(-1, 3))
    turned = (partial * Rotation.from_matrix(np.repeat(rotation, len(s), axis=0))).as_matrix()
    turned = turned.reshape(m, len(s), 3, 3)
    pos_parts.append(centre[:, None] - turned @ offset)
    quat_parts.append(_quat_wxyz(Rotation.from_matrix(turned.reshape(-1, 3, 3))).reshape(m, len(s), 4))
    ctrl_parts.append(np.repeat(closed[:, None], len(s), axis=1))
    final_pos, final_quat = pos_parts[-1][:, -1], quat_parts[-1][:, -1]
    hold(final_pos, final_quat, closed, steps[Phase.HOLD])
    hold(final_pos, final_quat, closed, steps[Phase.DISTURB])

    force = np.zeros(len(Phase))
    force[Phase.DISTURB] = config.disturbance_force
    return Schedule(
        phase_steps=steps,
        mocap_pos=np.concatenate(pos_parts, axis=1),
        mocap_quat=np.concatenate(quat_parts, axis=1),
        finger_ctrl=np.concatenate(ctrl_parts, axis=1),
        phase_force=force,
        init_qpos=np.concatenate([pre, quat0], axis=1),
        init_finger=half,
    )


# ---------------------------------------------------------------------------------------------
# Model addresses shared by the backends.


@dataclasses.dataclass(frozen=True)
class Layout:
    """Where the trial's quantities live in a scene model."""

    gripper_qpos: int  # adr of the gripper free joint's 7 qpos
    gripper_qvel: int
    finger_qpos: tuple[int, int]
    finger_qvel: tuple[int, int]
    object_qpos: np.ndarray  # [N] adr of each object's free joint
    object_qvel: np.ndarray
    mocap: int  # mocap index of the gripper target
    sensor_table: int  # sensordata index of gripper-table
    sensor_object: np.ndarray  # [N, 3] (gripper, left finger, right finger) per object


def layout(scene: scene_lib.Scene) -> Layout:
    model = scene.model

    def joint(name: str) -> int:
        return mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, name)

    gripper = model.body_jntadr[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, gripper_model.GRIPPER_BODY)]
    fingers = [joint(n) for n in gripper_model.FINGER_JOINTS]
    object_joints = model.body_jntadr[scene.body_ids]
    names = gripper_model.contact_sensor_names(list(scene.names))
    adr = np.array([model.sensor_adr[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SENSOR, n)] for n in names])
    target = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, gripper_model.TARGET_BODY)
    return Layout(
        gripper_qpos=int(model.jnt_qposadr[gripper]),
        gripper_qvel=int(model.jnt_dofadr[gripper]),
        finger_qpos=tuple(int(model.jnt_qposadr[j]) for j in fingers),
        finger_qvel=tuple(int(model.jnt_dofadr[j]) for j in fingers),
        object_qpos=model.jnt_qposadr[object_joints].astype(np.int64),
        object_qvel=model.jnt_dofadr[object_joints].astype(np.int64),
        mocap=int(model.body_mocapid[target]),
        sensor_table=int(adr[0]),
        sensor_object=adr[1:].reshape(-1, 3),
    )


def initial_states(scene: scene_lib.Scene, schedule: Schedule, lay: Layout) -> np.ndarray:
    """[M, nstate] the settled scene with each trial's gripper placed at its pre-grasp pose."""
    model = scene.model
    m = len(schedule.init_qpos)
    state = np.repeat(scene.state[None], m, axis=0)

    def view(part: mujoco.mjtState) -> np.ndarray:
        return state[:, scene_lib.state_slice(model, part)]

    qpos, qvel = view(mujoco.mjtState.mjSTATE_QPOS), view(mujoco.mjtState.mjSTATE_QVEL)
    qpos[:, lay.gripper_qpos : lay.gripper_qpos + 7] = schedule.init_qpos
    qvel[:, lay.gripper_qvel : lay.gripper_qvel + 6] = 0.0
    for adr, dof in zip(lay.finger_qpos, lay.finger_qvel):
        qpos[:, adr] = schedule.init_finger
        qvel[:, dof] = 0.0
    view(mujoco.mjtState.mjSTATE_CTRL)[:] = schedule.init_finger[:, None]
    mocap_pos = view(mujoco.mjtState.mjSTATE_MOCAP_POS).reshape(m, -1, 3)
    mocap_quat = view(mujoco.mjtState.mjSTATE_MOCAP_QUAT).reshape(m, -1, 4)
    mocap_pos[:, lay.mocap] = schedule.init_qpos[:, :3]
    mocap_quat[:, lay.mocap] = schedule.init_qpos[:, 3:]
    view(mujoco.mjtState.mjSTATE_WARMSTART)[:] = 0.0
    return state


# ---------------------------------------------------------------------------------------------
# Outcomes.


def _quat_rotate_inverse(quat: np.ndarray, vec: np.ndarray) -> np.ndarray:
    """Rotate vec[..., 3] by the inverse of quat[..., 4] (wxyz)."""
    return Rotation.from_quat(np.roll(quat, -1, axis=-1).reshape(-1, 4)).inv().apply(vec.reshape(-1, 3)).reshape(
        vec.shape
    )


# Which failure each phase can reveal (REORIENT is judged after HOLD, once the object has settled).
PHASE_FAILURE = {
    Phase.PREGRASP: Outcome.COLLISION_PREGRASP,
    Phase.APPROACH: Outcome.COLLISION_APPROACH,
    Phase.CLOSE: Outcome.COLLISION_APPROACH,
    Phase.LIFT: Outcome.DROPPED_LIFT,
    Phase.HOLD: Outcome.DROPPED_REORIENT,
    Phase.DISTURB: Outcome.DROPPED_DISTURBANCE,
}


@dataclasses.dataclass(frozen=True)
class Judge:
    """The outcome rules of the module docstring, applied one phase at a time.

    Backends call `failed` after each phase to stop trials whose outcome is already decided.
    """

    targets: np.ndarray  # [M] object indices
    start_z: np.ndarray  # [M] the targets' settled heights
    lay: Layout
    config: TrialConfig

    @classmethod
    def make(cls, scene: scene_lib.Scene, targets: np.ndarray, lay: Layout, config: TrialConfig) -> Judge:
        return cls(targets, scene.qpos[lay.object_qpos[targets] + 2], lay, config)

    def held(self, rollout: Rollout, phase: Phase, rows: np.ndarray) -> np.ndarray:
        """Both fingers touch the target, lifted by >= lift_height / 2 at the end of `phase` -> bool[R]."""
        targets = self.targets[rows]
        sensors = self.lay.sensor_object[targets]
        contacts = rollout.end_contacts[rows, phase]
        both = (contacts[np.arange(len(rows)), sensors[:, 1]] > 0) & (contacts[np.arange(len(rows)), sensors[:, 2]] > 0)
        z = rollout.end_qpos[rows, phase, self.lay.object_qpos[targets] + 2]
        return both & (z > self.start_z[rows] + 0.5 * self.config.lift_height)

    def slip(self, rollout: Rollout, rows: np.ndarray) -> np.ndarray:
        """How far the target moved in the gripper frame during DISTURB (m) -> [R]."""
        inside = object_in_gripper(rollout.end_qpos[rows][:, [Phase.HOLD, Phase.DISTURB]], self.targets[rows], self.lay)
        return np.linalg.norm(inside[:, 1] - inside[:, 0], axis=-1)

    def failed(self, phase: Phase, rollout: Rollout, rows: np.ndarray) -> np.ndarray:
        """Whether trials `rows` [R] failed in `phase` or became invalid -> bool[R].

        Reads the rollout's arrays of `phase` (and earlier phases) for those rows.
        """
        qpos = rollout.end_qpos[rows, phase]
        speed = rollout.max_speed[rows, phase]
        invalid = ~np.isfinite(qpos).all(axis=1) | ~(speed <= self.config.max_object_speed)
        failure = PHASE_FAILURE.get(Phase(phase))
        if failure is None:
            return invalid
        if failure == Outcome.DROPPED_DISTURBANCE:
            slipped = ~(self.slip(rollout, rows) <= self.config.max_slip)
            return invalid | ~self.held(rollout, phase, rows) | slipped
        if failure in (Outcome.DROPPED_LIFT, Outcome.DROPPED_REORIENT):
            return invalid | ~self.held(rollout, phase, rows)
        touching = rollout.contact_max[rows, phase] > 0
        table = touching[:, self.lay.sensor_table]
        objects = touching[:, self.lay.sensor_object[:, 0]]  # [R, N] gripper touches object n
        if failure == Outcome.COLLISION_APPROACH:
            objects[np.arange(len(rows)), self.targets[rows]] = False  # the target may be touched
        return invalid | table | objects.any(axis=1)


def object_in_gripper(end_qpos: np.ndarray, targets: np.ndarray, lay: Layout) -> np.ndarray:
    """Target centre of mass in the gripper frame: end_qpos[M, P, nq], targets[M] -> [M, P, 3]."""
    adr = lay.object_qpos[targets]
    position = np.take_along_axis(end_qpos, (adr[:, None] + np.arange(3))[:, None], axis=2)
    g = lay.gripper_qpos
    gripper = end_qpos[:, :, g : g + 7]
    return _quat_rotate_inverse(gripper[..., 3:], position - gripper[..., :3])


def classify(judge: Judge, rollout: Rollout) -> TrialResult:
    """Turn per-phase summaries into Outcomes: the first failing phase decides, INVALID overrides.

    Instability (NaN, an object faster than max_object_speed) counts up to the deciding phase only (the
    first failing phase, else the last): what the simulator does after a decided failure cannot change
    it, and the C engine with early_stop does not even simulate it while MJX always does."""
    lay, targets = judge.lay, judge.targets
    m = len(targets)
    rows = np.arange(m)
    adr = lay.object_qpos[targets]
    object_pose = np.take_along_axis(rollout.end_qpos, (adr[:, None] + np.arange(7))[:, None], axis=2)
    g = lay.gripper_qpos
    outcome = np.full(m, Outcome.SUCCESS, np.int8)
    undecided = np.ones(m, bool)
    decided_at = np.full(m, len(Phase) - 1)
    for phase in Phase:
        failed = judge.failed(phase, rollout, rows)
        outcome[undecided & failed] = PHASE_FAILURE.get(phase, Outcome.INVALID)
        decided_at[undecided & failed] = phase
        undecided &= ~failed
    max_speed = rollout.max_speed.max(axis=1)
    counted = np.arange(len(Phase))[None] <= decided_at[:, None]  # [M, P] phases up to the decision
    finite = np.where(counted, np.isfinite(rollout.end_qpos).all(axis=2), True).all(axis=1)
    fast = ~(np.where(counted, rollout.max_speed, 0.0).max(axis=1) <= judge.config.max_object_speed)
    outcome[~rollout.ok | ~finite | fast] = Outcome.INVALID
    return TrialResult(
        outcome=outcome,
        object_pose=object_pose,
        gripper_pose=rollout.end_qpos[:, :, g : g + 7],
        object_in_gripper=object_in_gripper(rollout.end_qpos, targets, lay),
        opening=sum(rollout.end_qpos[:, :, a] for a in lay.finger_qpos),
        held=np.stack([judge.held(rollout, phase, rows) for phase in Phase], axis=1),
        slip=judge.slip(rollout, rows),
        max_speed=max_speed,
        final_qpos=rollout.end_qpos[:, -1],
        decided_at=decided_at,
        contacts=rollout.contact_max,
    )


def touched(result: TrialResult, lay: Layout, row: int, phase: Phase) -> dict:
    """What the gripper of trial `row` touched during `phase`: {"table": bool, "objects": {n: part}}.

    part is "finger" where a finger touched object n, "palm" where only the palm did, "finger+palm" where
    both did. The sensors report the largest contact count per phase, so the palm is named only when the
    gripper's count exceeds both fingers' together (the palm surely touched at that step); a palm contact
    hidden behind finger contacts is reported as "finger".
    """
    counts = result.contacts[row, phase]
    objects = {}
    for n, (gripper, left, right) in enumerate(counts[lay.sensor_object]):
        if gripper <= 0:
            continue
        finger, palm = left > 0 or right > 0, gripper > left + right
        objects[n] = "finger+palm" if finger and palm else "finger" if finger else "palm"
    return {"table": bool(counts[lay.sensor_table] > 0), "objects": objects}
