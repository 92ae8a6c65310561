"""The decluttering episode: observe -> plan -> execute in simulation, until the table is clear.

One scene (paper Sec. V-B): `make_scene` drops n objects into the 50 x 50 cm workspace; then, at most
objects + 5 times: the fixed depth camera observes the scene, the method plans on the observation, the
grasp is simulated (`envs.trial.run_trials`, approach / close / lift / reorient / disturbance), and a
successful grasp removes its object (`envs.scene.remove_object`, which re-settles the rest). A scene
ends when the table is clear ("cleared"), the attempt cap is reached ("attempt_cap") or the method
returns no grasp ("no_grasp").

Choices, documented:
  * The task's objects are the ones on the table after the initial settle (objects that rolled out of
    the workspace while the pile settled were never part of the task); the attempt cap is their count
    + 5. Objects that leave the workspace while the pile re-settles after a removal stay in the count
    (they were not grasped) and are listed in the log's "fell_out".
  * Which object a grasp is on: the object with the most observed points in the closing region (by the
    observation's ground-truth labels). A grasp with no object point between its fingers is a failed
    attempt on "nothing" (outcome "no_object"), not simulated.
  * A failed grasp leaves the objects where the trial left them (`envs.scene.after_trial`: knocked
    over, dropped, pushed; then re-settled), as a real table would; the method re-plans on a new
    observation with a new seed. A target dropped out of the workspace counts as not grasped.
  * Memory (`DeclutterConfig.remember_failures`, on by default): every plan call gets the poses of the
    grasps that failed so far in this scene as `avoid`, and the method leaves out the same grasps
    (`eval.protocol.near_grasps`). Without it a deterministic planner repeats a grasp that collides on
    its approach until the attempt cap, as long as the scene does not change. Every method gets the
    same memory; a method whose `plan` takes no `avoid` runs without it (logged as "memory": false).
  * Scene seeds are `scene_seed(seed, index)`: the same (setting, seed, index) gives the identical
    scene for every method. Plan seeds are `plan_seed(scene_seed, attempt)`.
  * Through a sensor (`DeclutterConfig.sensor` other than "exact", or `masks` = "clusters"): the scene
    also holds what real frames hold around the table (`SceneConfig.surroundings`: floor, robot stand,
    wall; seen, never touched), the camera delivers the named sensor's depth image (`envs.sensors`), and
    the method sees what `sgjax.perception.Frame.from_depth` makes of it, the front end of a user's
    frame: world points from the depth, the table fitted, objects from the true masks ("truth",
    instance ids of the exact render, as a perfect segmenter would give) or from clustering
    ("clusters"). The method gets the table's and the objects' points (labels -1 and 1..K); what the
    front end put beyond the table is dropped. Which object a grasp is on is still decided on the exact
    render's truth. With clusters, the method plans on the frame's hypotheses in turn until one gives a
    grasp (`Frame.hypotheses`, as `sgjax plan --depth` does): the parted one (touching objects merged into
    one cluster cut apart where the finer crease test finds them), the clusters as segmented, the joined
    one (crease-cut fragments joined to their neighbour), the finer one (a pile cut into its objects);
    the attempt's "seen" says "labels": "parted", "clusters", "joined" or "finer" where it was not the
    clusters as segmented.
"""

from __future__ import annotations

import dataclasses
import inspect
import time
from collections.abc import Iterator, Sequence
from typing import NamedTuple

import numpy as np

from envs import camera as camera_lib
from envs import scene as scene_lib
from envs import sensors as sensors_lib
from envs import trial as trial_lib
from eval.numerics import numerics_label
from eval.protocol import Decision, Method
from sgjax.geometry.gripper import GripperSpec
from sgjax.perception import Frame, PerceptionError

LOG_VERSION = 1
NO_OBJECT = "no_object"
MASKS = ("truth", "clusters")


@dataclasses.dataclass(frozen=True)
class Setting:
    """A benchmark setting: how many objects per scene, from which object set; a setting may also fix the
    gripper (a preset of `sgjax.geometry.gripper_files`), the sensor and the masks (`apply_setting`)."""

    name: str
    n_objects: int
    object_set: str
    gripper: str | None = None
    sensor: str | None = None
    masks: str | None = None

    @property
    def fixes_hardware(self) -> bool:
        return (self.gripper, self.sensor, self.masks) != (None, None, None)

    def label(self, objects: str, n_objects: int, view: str = "", replaced: bool = False, custom: bool = False) -> str:
        """The name of a run of this setting in logs and tables: "<objects>-<n>" (seen-10, tiny-4,
        mymeshes-10), with "@<view>" after it when the method sees the scene through a sensor
        (seen-10@realsense+clusters). A setting that fixes its hardware keeps its own name (real-similar),
        "<name>-<objects>" when `replaced` (its object set replaced by the set `objects`:
        real-novel-mymeshes), unless `custom` (other assets or another object count: not its scenes)."""
        if self.fixes_hardware and not custom:
            return f"{self.name}-{objects}" if replaced else self.name
        return f"{objects}-{n_objects}" + (f"@{view}" if view else "")


# The paper's Table I in simulation, and its real-world Table II re-created as closely as simulation
# allows: the DH-Robotics AG-105-145 gripper, stereo depth (the paper's ZED 2i) and masks the front end
# segments itself (the paper used SAM), 10 seen ("similar") or 10 unseen ("novel") objects per scene.
SETTINGS = {
    s.name: s
    for s in (
        Setting("seen-10", 10, "seen"),
        Setting("seen-20", 20, "seen"),
        Setting("unseen-10", 10, "unseen"),
        Setting("real-similar", 10, "seen", gripper="ag-105-145", sensor="stereo", masks="clusters"),
        Setting("real-novel", 10, "unseen", gripper="ag-105-145", sensor="stereo", masks="clusters"),
    )
}


def get_setting(name: str) -> Setting:
    """The setting called `name` (seen-10, seen-20, unseen-10, real-similar, real-novel); ValueError listing
    them otherwise."""
    if name not in SETTINGS:
        raise ValueError(f"unknown setting {name!r}: expected one of {', '.join(SETTINGS)}")
    return SETTINGS[name]


def apply_setting(setting: Setting, config: "DeclutterConfig") -> "DeclutterConfig":
    """`config` with the gripper, sensor and masks the setting fixes. A config value left at its default
    takes the setting's; one set to something else is a contradiction (ValueError naming both)."""
    from sgjax.geometry.gripper_files import load_gripper

    default = DeclutterConfig()
    changes = {}
    for field, wanted in (("gripper", setting.gripper and load_gripper(setting.gripper)), ("sensor", setting.sensor),
                          ("masks", setting.masks)):
        if wanted is None:
            continue
        have = getattr(config, field)
        if have != default.__getattribute__(field) and have != wanted:
            shown = setting.gripper if field == "gripper" else wanted
            raise ValueError(f"setting {setting.name!r} fixes the {field} ({shown}); the config asks for another")
        changes[field] = wanted
    return dataclasses.replace(config, **changes) if changes else config


@dataclasses.dataclass(frozen=True)
class DeclutterConfig:
    """Episode settings: attempts allowed beyond the object count, camera, scene, trial, trial backend;
    remember_failures: hand the method the poses that failed so far in the scene; sensor (`envs.sensors`:
    exact, kinect, realsense, stereo) and masks (truth, clusters): how the method sees the scene (module
    doc). sensor and masks stay out of the repr (the resume key): `view` names them in the key and the
    setting's label, so that exact runs keep theirs."""

    extra_attempts: int = 5
    camera: camera_lib.CameraConfig = dataclasses.field(default_factory=camera_lib.CameraConfig)
    scene: scene_lib.SceneConfig = dataclasses.field(default_factory=scene_lib.SceneConfig)
    trial: trial_lib.TrialConfig = dataclasses.field(default_factory=trial_lib.TrialConfig)
    gripper: GripperSpec = dataclasses.field(default_factory=GripperSpec)
    backend: str = "cpu"
    nthread: int = 0
    remember_failures: bool = True
    sensor: str = dataclasses.field(default="exact", repr=False)
    masks: str = dataclasses.field(default="truth", repr=False)

    def __post_init__(self):
        if self.extra_attempts < 0:
            raise ValueError(f"extra_attempts must be >= 0, got {self.extra_attempts}")
        trial_lib.check_backend(self.backend)
        sensors_lib.get_sensor(self.sensor)
        if self.masks not in MASKS:
            raise ValueError(f"unknown masks {self.masks!r}: expected one of {', '.join(MASKS)}")

    @property
    def through_sensor(self) -> bool:
        """Whether the method sees the scene through the sensor and the front end (module doc)."""
        return (self.sensor, self.masks) != ("exact", "truth")

    @property
    def view(self) -> str:
        """"" for the exact render with true masks, else "<sensor>+<masks>" (e.g. "realsense+clusters")."""
        return f"{self.sensor}+{self.masks}" if self.through_sensor else ""


def scene_seed(seed: int, index: int) -> int:
    """The seed of scene `index` of a run seeded `seed` (a uint32, independent of the method)."""
    return int(np.random.SeedSequence([int(seed), int(index)]).generate_state(1)[0])


def plan_seed(scene_seed_: int, attempt: int) -> int:
    """The seed handed to the method for attempt `attempt` of a scene."""
    return int(np.random.SeedSequence([int(scene_seed_), int(attempt), 1]).generate_state(1)[0])


def closing_region_objects(
    points: np.ndarray, labels: np.ndarray, pose: np.ndarray, width: float, spec: GripperSpec
) -> dict[int, int]:
    """Observed points of each object in the closing region of (pose [4, 4], width): {object: count}.

    points [P, 3] world, labels [P] (object index, < 0 for the table / no object).
    """
    pose = np.asarray(pose, np.float64)
    local = (np.asarray(points, np.float64) - pose[:3, 3]) @ pose[:3, :3]
    inside = (
        (np.abs(local[:, 0]) <= 0.5 * width)
        & (np.abs(local[:, 1]) <= 0.5 * spec.finger_width)
        & (local[:, 2] >= 0.0)
        & (local[:, 2] <= spec.finger_length)
        & (np.asarray(labels) >= 0)
    )
    ids, counts = np.unique(np.asarray(labels)[inside], return_counts=True)
    return {int(i): int(c) for i, c in zip(ids, counts)}


CLEAN_SHARE = 0.8  # a cluster is one object when >= this share of it is that object and it holds >= this share of it


def cluster_grade(points: np.ndarray, labels: np.ndarray, truth: np.ndarray, visible: np.ndarray, pose: np.ndarray,
                  width: float, spec: GripperSpec) -> dict | None:
    """How the cluster a grasp (pose [4, 4], width) was planned on matches the objects, against the exact
    render: the method's points [P, 3], its labels [P] (objects > 0), the true object index at each of
    those points' pixels truth [P] (-1: none), visible [n_objects]: each object's pixels in the frame.
    The cluster is the label with the most points in the closing region. -> {"cluster", "points",
    "object" (its most frequent true object, -1: none), "purity" (that object's share of it), "coverage"
    (its share of that object's pixels), "grade": "clean" (both >= CLEAN_SHARE), "merged" (purity below),
    "split" (coverage below)}; None when no cluster's point lies in the closing region."""
    inside = closing_region_objects(points, np.where(labels > 0, labels, -1), pose, width, spec)
    if not inside:
        return None
    cluster = max(inside, key=lambda k: (inside[k], -k))
    mine = truth[labels == cluster]
    ids, counts = np.unique(mine, return_counts=True)
    best = int(np.argmax(np.where(ids >= 0, counts, -1)))  # the most frequent true object
    obj = int(ids[best]) if ids[best] >= 0 else -1
    purity = float(counts[best] / len(mine)) if obj >= 0 else 0.0
    coverage = float(counts[best] / max(int(visible[obj]), 1)) if obj >= 0 else 0.0
    grade = "merged" if purity < CLEAN_SHARE else "split" if coverage < CLEAN_SHARE else "clean"
    return {"cluster": int(cluster), "points": int(len(mine)), "object": obj, "purity": round(purity, 4),
            "coverage": round(coverage, 4), "grade": grade}


def rigid_pose(pose, method_name: str) -> np.ndarray:
    """The method's pose as float64 [4, 4] with its rotation re-orthonormalised; ValueError if unusable."""
    pose = np.asarray(pose, np.float64)
    if pose.shape != (4, 4) or not np.isfinite(pose).all():
        raise ValueError(f"method {method_name!r} returned a pose of shape {pose.shape} that is not finite [4, 4]")
    u, s, vt = np.linalg.svd(pose[:3, :3])
    if np.linalg.det(u @ vt) < 0 or np.abs(s - 1.0).max() > 1e-3:
        raise ValueError(f"method {method_name!r} returned a pose whose rotation is not a rotation (singular values {s})")
    out = np.eye(4)
    out[:3, :3] = u @ vt
    out[:3, 3] = pose[:3, 3]
    return out


def takes_avoid(method: Method) -> bool:
    """Whether method.plan accepts the harness's memory (an `avoid` argument)."""
    try:
        parameters = inspect.signature(method.plan).parameters
    except (TypeError, ValueError):
        return False
    return "avoid" in parameters or any(p.kind == p.VAR_KEYWORD for p in parameters.values())


def _json_info(info: dict) -> dict:
    """Method extras made JSON-able (numpy scalars and arrays to Python)."""
    out = {}
    for key, value in (info or {}).items():
        if isinstance(value, np.ndarray):
            value = value.tolist()
        elif isinstance(value, np.generic):
            value = value.item()
        out[str(key)] = value
    return out


def logged_contacts(scene, result: trial_lib.TrialResult, row: int = 0) -> dict:
    """What trial `row` touched in the phase that decided it (`envs.trial.what_touched`), as the scene
    log keeps it: {"phase", "table", "objects" {object index as a string: "finger" | "palm" | "finger+palm"}}."""
    touched = trial_lib.what_touched(scene, result, row)
    return {**touched, "objects": {str(k): v for k, v in touched["objects"].items()}}


@dataclasses.dataclass
class SceneRun:
    """One finished scene: its JSON-able log and the first observation (for pictures)."""

    log: dict
    first_observation: camera_lib.Observation


def make_benchmark_scene(objects: Sequence, n_objects: int, seed: int, index: int, config: DeclutterConfig):
    """Scene `index` of a run seeded `seed`: identical for every method (through a sensor, with the
    table's surroundings, which only the camera sees)."""
    scene_config = dataclasses.replace(config.scene, surroundings=True) if config.through_sensor else config.scene
    return scene_lib.make_scene(objects, n_objects, scene_seed(seed, index), scene_config, config.gripper)


class View(NamedTuple):
    """What a method sees of a scene (`observe`): obs (the exact observation, which decides the
    outcome), points [P, 3], labels [P], info (the front end's {"objects_found", "table" plane}, else
    {}); through a sensor, visible int [n]: each object's points in the whole frame (`cluster_grade`),
    frame: the front end's `Frame` and frame_truth [N]: the exact render's object index at each of its
    points' pixels (-1: none); else None. truth [P]: frame_truth at the points handed to the method."""

    obs: camera_lib.Observation
    points: np.ndarray
    labels: np.ndarray
    info: dict
    visible: np.ndarray | None = None
    frame: Frame | None = None
    frame_truth: np.ndarray | None = None

    @property
    def truth(self) -> np.ndarray | None:
        return None if self.frame is None else self.frame_truth[self.frame.planned]


def observe(scene, config: DeclutterConfig, seed: int) -> View:
    """What the method sees of `scene`: the exact render's own cloud and labels, or through a sensor the
    front end's (module doc). A frame the front end cannot use (PerceptionError) leaves the method no
    points."""
    if not config.through_sensor:
        obs = camera_lib.observe(scene, config.camera, seed=seed)
        return View(obs, obs.points, obs.point_labels, {})
    sensed = sensors_lib.sense(scene, config.camera, config.sensor, seed=seed)
    obs = sensed.truth
    try:
        frame = sensors_lib.front_end(sensed, config.camera, config.masks)
    except PerceptionError as exc:
        return View(obs, np.zeros((0, 3), np.float32), np.zeros(0, np.int32), {"front_end": str(exc)})
    first = next(frame.hypotheses())  # with clusters, the parted one where it differs (`hypotheses`)
    points, labels = first.table_and_objects()
    info = {"objects_found": len(first.object_ids), "table": [round(v, 5) for v in frame.table.plane]}
    if first is not frame:
        info["labels"] = first.segmentation.split()[0]
    truth = obs.labels[frame.pixels[:, 0], frame.pixels[:, 1]]  # of every point of the frame
    visible = np.bincount(truth[truth >= 0], minlength=len(scene.present))
    return View(obs, points.astype(np.float32), labels, info, visible, frame, truth)


def hypotheses(view: View) -> Iterator[tuple[str, np.ndarray, np.ndarray, np.ndarray]]:
    """The front end's other labellings of a clustered view, in the order a method that finds no grasp is
    shown them (`Frame.hypotheses` after the view's own; each made only when asked for): (its
    `Frame.segmentation`: "clusters" | "joined clusters" | "finer clusters", points [Q, 3] float32, labels [Q],
    truth [Q]). None with true masks or the exact render."""
    if view.frame is None or view.frame.segmentation != "clusters":
        return
    others = view.frame.hypotheses()
    next(others)  # the view's own labels
    for other in others:
        points, labels = other.table_and_objects()
        yield other.segmentation, points.astype(np.float32), labels, view.frame_truth[other.planned]


def _decide(method: Method, points, labels, viewpoint, seed: int, avoid) -> Decision:
    """The method's plan, with the scene's memory when it has one (avoid not None)."""
    if avoid is None:
        return method.plan(points, labels, viewpoint, seed)
    return method.plan(points, labels, viewpoint, seed, avoid=avoid)


def run_scene(
    method: Method,
    objects: Sequence,
    n_objects: int,
    seed: int,
    index: int,
    config: DeclutterConfig | None = None,
    setting: str = "",
) -> SceneRun:
    """Run one decluttering scene with `method` and return its log (see module doc for the rules).

    log: {"version", "method", "setting", "seed", "scene_index", "scene_seed", "n_objects",
    "objects" (on the table after settling), "object_names", "at_rest", "attempts" [...], "end",
    "final_reason", "final_timing", "fell_out", "remaining", "memory", "wall_s", "numerics"}; each attempt:
    {"attempt", "target", "target_name", "outcome", "success", "score", "width", "pose" [4][4],
    "points_in_gripper" {object: count}, "timing" {stage1_s, stage2_s, total_s}, "plan_seed",
    "avoided" (failed poses handed to the method), "observe_s", "trial_s", "settle_s" (the scene's update
    after the trial: the object removed or the scene left as the trial left it, re-settled), "info"}; a simulated attempt
    that failed also has "contacts": what the gripper touched in the phase that decided it
    (`envs.trial.what_touched`: {"phase", "table", "objects" {object: "finger" | "palm" | "finger+palm"}});
    with clustered masks, "segment": how the cluster planned on matches the objects (`cluster_grade`).
    """
    start = time.perf_counter()
    config = config or DeclutterConfig()
    spec = config.gripper
    s_seed = scene_seed(seed, index)
    scene = make_benchmark_scene(objects, n_objects, seed, index, config)
    present0 = np.flatnonzero(scene.present)
    at_rest = bool(scene.at_rest)
    cap = len(present0) + config.extra_attempts
    viewpoint = np.asarray(config.camera.position, np.float64)
    ground_truth = getattr(method, "uses_ground_truth", False)
    memory = config.remember_failures and takes_avoid(method)
    if hasattr(method, "begin_scene"):  # a method that keeps state over a scene's plans starts afresh
        method.begin_scene()
    failed: list[np.ndarray] = []  # poses of this scene's failed attempts (the memory)
    attempts: list[dict] = []
    fell_out: list[int] = []
    end, final_reason, final_timing, first = "cleared", "", None, None
    while True:
        if not scene.present.any():
            end = "cleared"
            break
        if len(attempts) >= cap:
            end = "attempt_cap"
            break
        t0 = time.perf_counter()
        view = observe(scene, config, s_seed + len(attempts))
        obs, points, labels, seen, truth = view.obs, view.points, view.labels, view.info, view.truth
        observe_s = time.perf_counter() - t0
        first = obs if first is None else first
        if ground_truth:
            method.set_scene(scene)
        p_seed = plan_seed(s_seed, len(attempts))
        if not len(points):  # the front end found no table in the frame: nothing to plan on
            end, final_reason, final_timing = "no_grasp", f"front end: {seen['front_end']}", {}
            break
        avoid = np.asarray(failed, np.float64).reshape(-1, 4, 4) if memory else None
        decision: Decision = _decide(method, points, labels, viewpoint, p_seed, avoid)
        if decision.pose is None:  # the frame's other hypotheses in turn (module doc)
            for where, *other in hypotheses(view):
                second = _decide(method, *other[:2], viewpoint, p_seed, avoid)
                # Every plan's time counts: the earlier ones ran before this one.
                timing = {k: v + decision.timing.get(k, 0.0) if isinstance(v, float) else v for k, v in second.timing.items()}
                if second.pose is not None:
                    decision, seen = dataclasses.replace(second, timing=timing), {**seen, "labels": where.split()[0]}
                    points, labels, truth = other
                    break
                decision = dataclasses.replace(decision, timing=timing, reason=f"{decision.reason or 'no grasp'}; on "
                                               f"the {where}: {second.reason or 'no grasp'}")
        if decision.pose is None:
            end, final_reason, final_timing = "no_grasp", decision.reason or "no grasp", dict(decision.timing)
            break
        pose = rigid_pose(decision.pose, method.name)
        width = float(np.clip(decision.width, 0.0, spec.max_opening))
        counts = closing_region_objects(obs.points, obs.point_labels, pose, width, spec)
        record = {
            "attempt": len(attempts),
            "target": None,
            "target_name": None,
            "outcome": NO_OBJECT,
            "success": False,
            "score": float(decision.score),
            "width": width,
            "pose": pose.tolist(),
            "points_in_gripper": {str(k): v for k, v in counts.items()},
            "timing": {k: float(v) for k, v in decision.timing.items()},
            "plan_seed": p_seed,
            "avoided": len(failed) if memory else 0,
            "observe_s": observe_s,
            "trial_s": 0.0,
            "info": _json_info(decision.info),
        }
        if seen:
            record["seen"] = seen
        if config.masks == "clusters":  # through a sensor: the front end gave truth, or the scene ended above
            record["segment"] = cluster_grade(points, labels, truth, view.visible, pose, width, spec)
        attempts.append(record)
        candidates = {k: v for k, v in counts.items() if scene.present[k]}
        if not candidates:
            failed.append(pose)
            continue
        target = max(candidates, key=lambda k: (candidates[k], -k))
        t0 = time.perf_counter()
        result = trial_lib.run_trials(scene, target, pose[None], np.array([width]), backend=config.backend,
                                      config=config.trial, nthread=config.nthread)
        record["trial_s"] = time.perf_counter() - t0
        outcome = trial_lib.Outcome(int(result.outcome[0]))
        record.update(target=int(target), target_name=scene.assets[target].name, outcome=outcome.name.lower(),
                      success=outcome == trial_lib.Outcome.SUCCESS)
        before = scene.present.copy()
        t0 = time.perf_counter()
        if record["success"]:
            scene = scene_lib.remove_object(scene, target)
        else:  # the objects stay where the failed grasp left them (knocked over, dropped)
            record["contacts"] = logged_contacts(scene, result)
            failed.append(pose)
            scene = scene_lib.after_trial(scene, result.final_qpos[0])
        record["settle_s"] = time.perf_counter() - t0
        fell_out += [int(i) for i in np.flatnonzero(before & ~scene.present) if i != target or not record["success"]]
    if first is None:  # nothing on the table after settling: still keep a picture of the empty scene
        first = camera_lib.observe(scene, config.camera, seed=s_seed)
    log = {
        "version": LOG_VERSION,
        "method": method.name,
        "setting": setting,
        "seed": int(seed),
        "scene_index": int(index),
        "scene_seed": s_seed,
        "n_objects": int(n_objects),
        "objects": len(present0),
        "object_names": [scene.assets[i].name for i in present0],
        "at_rest": at_rest,
        "attempts": attempts,
        "end": end,
        "final_reason": final_reason,
        "final_timing": final_timing,
        "fell_out": fell_out,
        "remaining": int(scene.present.sum()),
        "memory": memory,
        "wall_s": time.perf_counter() - start,
        "numerics": numerics_label(),
    }
    if config.through_sensor:
        log["view"] = config.view
    return SceneRun(log, first)
