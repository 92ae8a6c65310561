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
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np

from envs import camera as camera_lib
from envs import scene as scene_lib
from envs import trial as trial_lib
from eval.declutter import NO_OBJECT, DeclutterConfig, logged_contacts, make_benchmark_scene
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
    scene = logged_scene(log, objects, config)
    other_scene = None
    out = []
    for record in log["attempts"]:
        if record["outcome"] == NO_OBJECT or record["target"] is None:
            out.append(ReplayedAttempt(int(record["attempt"]), None, record["outcome"], NO_OBJECT, {}))
            continue
        target = int(record["target"])
        if not scene.present[target]:
            raise ValueError(f"attempt {record['attempt']}: target {target} is not on the table in the replay")
        pose = np.asarray(record["pose"], np.float64)
        width = float(record["width"])
        result = trial_lib.run_trials(scene, target, pose[None], np.array([width]), backend=config.backend,
                                      config=config.trial, nthread=config.nthread)
        depth = spec.finger_length - float(result.object_in_gripper[0, trial_lib.Phase.CLOSE, 2])
        obs = camera_lib.observe(scene, config.camera, seed=int(log["scene_seed"]) + int(record["attempt"]))
        neighbour, table = _seen_in_hand(obs, target, pose, width, spec, config.trial.pregrasp_distance)
        replayed = ReplayedAttempt(int(record["attempt"]), target, record["outcome"], _outcome(result),
                                   _contacts(scene, result), depth, neighbour, table)
        if other is not None:
            other_scene = scene_lib.with_gripper(scene, other, like=other_scene)
            other_pose = fingertips_aligned(pose, spec, other)
            other_result = trial_lib.run_trials(other_scene, target, other_pose[None],
                                                np.array([min(width, other.max_opening)]), backend=config.backend,
                                                config=config.trial, nthread=config.nthread)
            replayed = dataclasses.replace(replayed, other_outcome=_outcome(other_result),
                                           other_contacts=_contacts(other_scene, other_result))
        out.append(replayed)
        if not replayed.reproduced:
            break
        if result.label[0]:
            scene = scene_lib.remove_object(scene, target)
        else:
            scene = scene_lib.after_trial(scene, result.final_qpos[0])
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
