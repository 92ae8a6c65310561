"""Replaying a benchmark scene from its log: the logged grasps again, without the method that chose them.

The harness is deterministic (`eval.declutter`: the same seed gives the same scene, the same grasp the
same trial), so executing a scene log's grasps in order from the same scene reproduces the episode
attempt by attempt, and before each attempt the objects lie as they did when the method chose it. That
makes a method's failures inspectable after the fact, at the cost of simulation only (no planner, no
other environment: Contact-GraspNet's logs replay without torch):

  * what the gripper touched in the phase that decided each failed trial (`envs.trial.what_touched`:
    the table, a neighbour, by finger or palm);
  * whether the same grasp fails with another hand (`other`, e.g. the Panda hand
    `sgjax.geometry.gripper.PANDA_HAND`), simulated from the same state with its fingertips where the
    logged gripper's were and the same opening: the logged gripper's outcome decides how the episode
    goes on, the other hand's is only recorded.

A replayed outcome that differs from the logged one (another version of the simulator or of the object
meshes) ends that scene's replay: later states would no longer be the logged ones.

`LoggedStates` is that walk over a log's states, for any study of them: with a SuperGrasp planner it
also plans each state again (which must choose the logged grasp) and lets the caller simulate other
grasps from the same state (`eval.counterfactual`); `replay_scene` is the walk without a planner.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np

from envs import camera as camera_lib
from envs import scene as scene_lib
from envs import trial as trial_lib
from eval.declutter import (NO_OBJECT, DeclutterConfig, closing_region_objects, logged_contacts, make_benchmark_scene,
                           plan_seed, rigid_pose)
from sgjax.geometry.gripper import GripperSpec, hand_boxes, in_box


@dataclasses.dataclass(frozen=True)
class ReplayedAttempt:
    """One logged attempt replayed.

    attempt, target (object index or None), logged: the log's attempt index, target and outcome;
    outcome: the replayed outcome (NO_OBJECT when the log had no object between the fingers, not
        simulated); contacts: what the gripper touched in the deciding phase of a failed trial, in the
        scene log's form (`eval.declutter.logged_contacts`; {} for a success or no trial);
    com_depth: how far the target's centre of mass lay behind the fingertips once the fingers closed (m,
        along the approach; negative: beyond the fingertips; NaN without a trial): how deep the grasp is;
    seen_neighbour / seen_table: points of the observation the method planned on (other objects than
        the target / the table) inside the open hand's fingers and palm swept over the approach: a
        collision with something the method could see, or not;
    other_outcome / other_contacts: the same for the other hand ("" / {} without one).
    """

    attempt: int
    target: int | None
    logged: str
    outcome: str
    contacts: dict
    com_depth: float = float("nan")
    seen_neighbour: int = 0
    seen_table: int = 0
    other_outcome: str = ""
    other_contacts: dict = dataclasses.field(default_factory=dict)

    @property
    def reproduced(self) -> bool:
        return self.outcome == self.logged


def fingertips_aligned(pose: np.ndarray, spec: GripperSpec, other: GripperSpec) -> np.ndarray:
    """The pose [4, 4] of the `other` gripper whose fingertips lie where `spec`'s do at `pose` [4, 4]:
    both grippers' origins are their palm faces, the fingertips `finger_length` ahead along z."""
    out = np.array(pose, np.float64)
    out[:3, 3] += (spec.finger_length - other.finger_length) * out[:3, 2]
    return out


def _outcome(result: trial_lib.TrialResult) -> str:
    return trial_lib.Outcome(int(result.outcome[0])).name.lower()


def _contacts(scene: scene_lib.Scene, result: trial_lib.TrialResult) -> dict:
    return {} if result.label[0] else logged_contacts(scene, result)


def _seen_in_hand(obs, target: int, pose: np.ndarray, width: float, spec: GripperSpec, sweep: float) -> tuple[int, int]:
    """Observed points of other objects / of the table inside the hand's boxes swept over the approach."""
    local = (np.asarray(obs.points, np.float64) - pose[:3, 3]) @ pose[:3, :3]
    inside = np.zeros(len(local), bool)
    for box in hand_boxes(spec, width, sweep=sweep):
        inside |= np.asarray(in_box(local[:, 0], local[:, 1], local[:, 2], box))
    labels = np.asarray(obs.point_labels)
    return int((inside & (labels >= 0) & (labels != target)).sum()), int((inside & (labels < 0)).sum())


def logged_scene(log: dict, objects: Sequence, config: DeclutterConfig) -> scene_lib.Scene:
    """The scene of log `log` as the run began (settled), from `objects`; ValueError when it holds
    other objects than the log names (not the log's object set or meshes)."""
    scene = make_benchmark_scene(objects, int(log["n_objects"]), int(log["seed"]), int(log["scene_index"]), config)
    names = [scene.assets[i].name for i in np.flatnonzero(scene.present)]
    if names != list(log["object_names"]):
        raise ValueError(f"scene {log['scene_index']} holds other objects than its log: not the log's object set or meshes")
    return scene


class LoggedStates:
    """The states of a scene log, replayed: iterate to get each attempt's `LoggedState` (the observation,
    and with a `method` its plan of it, which must be the logged grasp); the caller may simulate other
    grasps from it (`LoggedState.simulate`), and the episode then goes on as logged. `reproduced` turns
    False, and the iteration stops, when a plan chose another grasp than the log's or a replayed outcome
    differed (another planner, checkpoint or machine's numerics). method None: no plans (`plan` None),
    the logged grasps alone, so any method's log replays (Contact-GraspNet's without torch)."""

    def __init__(self, log: dict, objects: Sequence, method=None, config: DeclutterConfig | None = None):
        if method is not None and not hasattr(method, "full_plan"):
            raise ValueError("a replay of logged states with a planner needs a SuperGrasp planner method (its full_plan)")
        self.log, self.objects, self.method = log, objects, method
        self.config = config or DeclutterConfig()
        self.reproduced = True

    def __iter__(self):
        config = self.config
        scene = logged_scene(self.log, self.objects, config)
        if self.method is not None:
            self.method.begin_scene()
        s_seed = int(self.log["scene_seed"])
        viewpoint = np.asarray(config.camera.position, np.float64)
        failed: list[np.ndarray] = []
        for record in self.log["attempts"]:
            k = int(record["attempt"])
            obs = camera_lib.observe(scene, config.camera, seed=s_seed + k)
            avoid = np.asarray(failed, np.float64).reshape(-1, 4, 4)
            logged_pose = np.asarray(record["pose"], np.float64)
            plan = None
            if self.method is not None:
                plan = self.method.full_plan(obs.points, obs.point_labels, viewpoint, plan_seed(s_seed, k), avoid)
                if plan.pose is None or not np.allclose(rigid_pose(plan.pose, "supergrasp"), logged_pose, atol=1e-9):
                    self.reproduced = False
                    return
            state = LoggedState(k, record, obs, plan, scene, avoid, viewpoint, plan_seed(s_seed, k), config)
            yield state
            if state.target is None:
                failed.append(logged_pose)
                continue
            if state.result is None:
                state.simulate([])
            if not state.reproduced:
                self.reproduced = False
                return
            if state.result.label[state.row]:
                scene = scene_lib.remove_object(scene, state.target)
            else:
                failed.append(logged_pose)
                scene = scene_lib.after_trial(scene, state.result.final_qpos[state.row])


@dataclasses.dataclass
class LoggedState:
    """One logged attempt's state: attempt index, its log record, the observation, the replaying method's
    plan (the logged grasp; None without a method), the scene, the failed poses so far avoid [F, 4, 4],
    the camera's position viewpoint [3] and the plan's seed. target: the logged object (None: no object
    between the fingers, no trial)."""

    attempt: int
    record: dict
    obs: object
    plan: object
    scene: scene_lib.Scene
    avoid: np.ndarray
    viewpoint: np.ndarray
    seed: int
    config: DeclutterConfig
    # Set by `simulate`: the batched trial, the logged grasp's row in it, and whether it gave the logged outcome.
    result: trial_lib.TrialResult | None = None
    row: int = -1
    reproduced: bool = False

    @property
    def target(self) -> int | None:
        record = self.record
        return None if record["outcome"] == NO_OBJECT or record["target"] is None else int(record["target"])

    def lifted(self, pose: np.ndarray, width: float) -> int | None:
        """The object the harness would lift with `pose` [4, 4] (float64, `rigid_pose`): the present one
        with the most observed points in the closing region; None: none (no trial)."""
        counts = {k: v for k, v in closing_region_objects(self.obs.points, self.obs.point_labels, pose, width,
                                                          self.config.gripper).items() if self.scene.present[k]}
        return max(counts, key=lambda k: (counts[k], -k)) if counts else None

    def simulate(self, rows: list[dict]) -> list[str]:
        """Execute rows [{"pose", "width", "target"}] (target not None) and the logged grasp from this state in
        one batched trial -> the rows' outcomes (`envs.trial.Outcome` names, lower case). A row marked
        "chosen" is the logged grasp itself (else it is added). Once per state."""
        if self.result is not None or self.target is None:
            raise ValueError("simulate runs once per state, and only where the logged grasp had a trial")
        record = self.record
        rows = list(rows)
        given = len(rows)
        executed = next((i for i, r in enumerate(rows) if r.get("chosen")), None)
        if executed is None:
            rows.append({"pose": np.asarray(record["pose"], np.float64), "width": float(record["width"]),
                         "target": self.target})
            executed = given
        config = self.config
        result = trial_lib.run_trials(self.scene, np.asarray([r["target"] for r in rows]), np.stack([r["pose"] for r in rows]),
                                      np.asarray([r["width"] for r in rows]), backend=config.backend, config=config.trial,
                                      nthread=config.nthread)
        outcomes = [trial_lib.Outcome(int(o)).name.lower() for o in result.outcome]
        self.result, self.row = result, executed
        self.reproduced = outcomes[executed] == record["outcome"] and rows[executed]["target"] == self.target
        return outcomes[:given]


def replay_scene(
    log: dict,
    objects: Sequence,
    config: DeclutterConfig | None = None,
    other: GripperSpec | None = None,
) -> list[ReplayedAttempt]:
    """Replay scene log `log` (`eval.declutter.run_scene`'s) on its objects `objects` (the set the run
    used); `other`: also simulate each grasp with this gripper. Returns the attempts replayed, in order,
    up to and including the first one whose outcome differs from the log (see the module doc).
    Raises ValueError for a log without attempts' poses or with a target that is not on the table.
    """
    config = config or DeclutterConfig()
    spec = config.gripper
    other_scene = None
    out = []
    for state in LoggedStates(log, objects, None, config):
        record = state.record
        target = state.target
        if target is None:
            out.append(ReplayedAttempt(state.attempt, None, record["outcome"], NO_OBJECT, {}))
            continue
        if not state.scene.present[target]:
            raise ValueError(f"attempt {record['attempt']}: target {target} is not on the table in the replay")
        pose = np.asarray(record["pose"], np.float64)
        width = float(record["width"])
        state.simulate([])
        result = state.result  # the logged grasp alone: its row 0
        depth = spec.finger_length - float(result.object_in_gripper[0, trial_lib.Phase.CLOSE, 2])
        neighbour, table = _seen_in_hand(state.obs, target, pose, width, spec, config.trial.pregrasp_distance)
        replayed = ReplayedAttempt(state.attempt, target, record["outcome"], _outcome(result),
                                   _contacts(state.scene, result), depth, neighbour, table)
        if other is not None:
            other_scene = scene_lib.with_gripper(state.scene, other, like=other_scene)
            other_pose = fingertips_aligned(pose, spec, other)
            other_result = trial_lib.run_trials(other_scene, target, other_pose[None],
                                                np.array([min(width, other.max_opening)]), backend=config.backend,
                                                config=config.trial, nthread=config.nthread)
            replayed = dataclasses.replace(replayed, other_outcome=_outcome(other_result),
                                           other_contacts=_contacts(other_scene, other_result))
        out.append(replayed)
    return out


def collision_cause(attempt: ReplayedAttempt, other: bool = False) -> str:
    """What failed a collision trial, in words: "table", "neighbour (finger)", "neighbour (palm)",
    "table + neighbour", or "" when the trial was not a collision (or no trial)."""
    outcome, contacts = (attempt.other_outcome, attempt.other_contacts) if other else (attempt.outcome, attempt.contacts)
    if not outcome.startswith("collision") or not contacts:
        return ""
    neighbours = {k: v for k, v in contacts["objects"].items() if k != str(attempt.target)}
    parts = sorted({part for v in neighbours.values() for part in v.split("+")})
    if contacts["table"] and neighbours:
        return "table + neighbour"
    if contacts["table"]:
        return "table"
    if neighbours:
        return f"neighbour ({' + '.join(parts)})"
    return "target only"  # a pre-grasp contact with the target itself
