"""The SuperGrasp planner: Stage 1 candidates -> E-RNet scores -> one grasp (paper Sec. IV-D, IV-E).

    plan = Planner(model, db).plan(scene_points, labels)     # every visible object of a scene
    plan = Planner(model, db).plan_target(scene_points, target_points)   # one given object cloud
    plan = Planner(model, db).plan_masked(scene_points, target_mask)     # one object by a bool mask
    plan = sgjax.planner.plan(scene_points, mask_or_labels_or_target)    # cached default planner

A plan, in order:

  1. Stage 1 (`sgjax.stage1.pipeline`) turns each object's single-view cloud into grasp candidates
     (superquadric fit, similarity matching, grasp transfer, coarse filtering with the rest of the scene
     as obstacles; with `fit_grasps`, top-down grasps on the fitted superquadric too).
  2. With `neighbour_fits`, candidates whose hand meets another object's fitted superquadric go
     (`sgjax.stage1.neighbours`: the sides of neighbours the camera did not see).
  3. Stage 2 scores all candidates of all objects in ONE jit-compiled E-RNet call on the whole scene cloud
     (`sgjax.stage2.ernet.score`), and the decision policy (`Planner._policy`, pure steps in
     `sgjax.policy`) picks the grasp: the paper's rule (evaluated > 0.7, else refined > 0.7, else none),
     the robust choice among the best evaluated (`robust`), refinements re-scored at their pose
     (`refine_rescore`), and refined poses checked against obstacles and the table.
  4. When that finds no grasp, a second plan with Stage 1's looser `fallback_filter`, the candidates clear
     of the neighbours' fits first (all of them when those give no grasp).

Fixed shapes, so repeated plans never recompile: Stage 2 scores the candidates in the smallest of a few
power-of-two batches that holds them (`stage2_min_slots` up to `max_stage2_candidates`, padded and
masked; the first plan compiles every size) on `scene_cloud.max_points` scene points (voxel grid + seeded
uniform subsample, padded and masked, made as the labelling pipeline makes it). Stage 1 runs objects in
batches of the sizes in `stage1_batch_sizes`. Over the plans of one scene, a `Stage1Memory` passed to
`plan` keeps each object's Stage-1 result while its cloud does not change: only filter (iv) runs again
on it (`Stage1.rescene`). When Stage 1 yields more candidates than Stage 2 takes, every object keeps its
best-matched ones (`policy.stage2_subset`).

Everything is deterministic for a seed. Bad input (wrong shapes, NaN, mismatched labels, an empty
cloud) raises ValueError naming the problem; a scene in which nothing can be grasped gives a Plan with
kind None and the reason. Named configurations: `sgjax.presets`.
"""

from __future__ import annotations

import dataclasses
import functools
import time
from typing import Any, ClassVar

import jax
import numpy as np
from flax import nnx

from sgjax import policy
from sgjax.geometry import gripper, pointcloud
from sgjax.geometry.gripper import GripperSpec
from sgjax.policy import KIND_EVALUATED, KIND_NAMES, KIND_NONE, KIND_REFINED, PERTURBATIONS
from sgjax.stage1 import neighbours
from sgjax.stage1.database import PrimitiveDB
from sgjax.stage1.filters import FilterConfig
from sgjax.stage1.fit_grasps import FitGraspConfig
from sgjax.stage1.memory import Stage1Memory
from sgjax.stage1.neighbours import NeighbourFitConfig
from sgjax.stage1.pipeline import Candidates, Stage1, Stage1Config
from sgjax.stage2 import checkpoint, ernet, pointnetgpd, scorers
from sgjax.stage2.scene_cloud import SceneCloudConfig
from sgjax.utils import exported
from sgjax.utils.cache import enable_compilation_cache

# The second plan's coarse filter (`PlannerConfig.fallback_filter`): the filters beyond the paper's off
# (camera-ray shadows, hidden contacts judged by the fitted superquadric) and the paper's (ii) and (iii)
# loosened to 25 points and 30 degrees, for the objects the default filters starve; E-RNet judges what
# it lets through.
FALLBACK_FILTER = FilterConfig(shadow_depth=0.0, hidden_contacts="accept", max_normal_angle_deg=30.0, min_points=25)


@dataclasses.dataclass(frozen=True)
class RobustChoice:
    """`PlannerConfig.robust`: execute, among the `top` best-evaluated passing candidates, the one whose
    score holds up when the hand lands a little off: E-RNet judges each at five perturbed poses
    (`gripper.perturbed_poses`: `shift` metres either way along the finger width and backed out along
    the approach, `angle_deg` either way about the approach axis), and the candidate with the highest mean
    of its own and those five scores is executed (ties: the better evaluated). The best of hundreds of
    scores is the one most likely over-estimated, and a grasp held at the object's edge loses its score
    when moved by millimetres."""

    top: int = 12
    shift: float = 0.005
    angle_deg: float = 10.0
    RETIRED_FIELDS: ClassVar[dict] = {"fits": False, "must_pass": False, "prefer_clearance": 0.0}

    def __post_init__(self):
        if self.top < 2:
            raise ValueError(f"RobustChoice.top must be >= 2 (the candidates compared), got {self.top}")
        if not (np.isfinite(self.shift) and 0.0 <= self.shift <= 0.05):
            raise ValueError(f"RobustChoice.shift must be in [0, 0.05] metres, got {self.shift}")
        if not (np.isfinite(self.angle_deg) and 0.0 <= self.angle_deg < 90.0):
            raise ValueError(f"RobustChoice.angle_deg must be in [0, 90), got {self.angle_deg}")

    @property
    def rows(self) -> int:
        """Stage-2 rows of one robustness call: `top` candidates x 5 perturbations."""
        return self.top * PERTURBATIONS


@dataclasses.dataclass(frozen=True)
class PlannerConfig:
    """Planner settings (hashable). `sgjax.presets` names the configurations the benchmark reports.

    stage1: Stage-1 settings (fit, matching, coarse filter, gripper spec; the spec is also Stage 2's).
    eval_threshold, refine_threshold: the paper's 0.7 (a score must exceed it).
    use_refinement: False = the paper's "w/o RNet" ablation (evaluated grasps only).
    refine_rescore: when no candidate's evaluation passes, the refine head's best `refine_rescore`
        proposals (candidate, variant) are judged by the evaluation head at their refined pose, and a
        refinement scores the geometric mean of both heads (one more Stage-2 call). 0: the paper's rule,
        the refine head alone.
    max_stage2_candidates: the largest Stage-2 batch; more candidates -> each object's best-matched first
        (round-robin over objects in match order).
    stage2_min_slots: Stage 2 scores the candidates in the smallest power-of-two batch of at least this
        many slots that holds them (up to max_stage2_candidates); a candidate's scores do not depend on the
        batch size. The first plan compiles every size not yet in the cache, so later plans never stall.
    min_object_points: objects with fewer visible points are skipped (the reason is recorded).
    scene_cloud: the Stage-2 scene cloud (`SceneCloudConfig`: optional crop, voxel grid, seeded uniform
        subsample to a fixed size, padded and masked), made as in labelling so that E-RNet sees the
        point density it was trained on (`envs.scene.stage2_scene_cloud` gives the benchmark's).
    support_plane: the table as (nx, ny, nz, d), free space n . x + d > 0, for Stage 1's filter (v)
        (grippers reaching below the table); None: no such filter (e.g. camera-frame clouds).
    stage1_batch_sizes: Stage-1 batch sizes (objects per call): objects run in chunks of the largest size
        that fits those left, the smallest size padded when none fits; each size compiles once.
    avoid_distance, avoid_angle_deg: a Stage-1 candidate this close to a pose passed as `avoid` (e.g. a
        grasp that already failed) is left out before Stage 2 (`gripper.near_grasps`).
    fallback_filter: when a plan finds no grasp, plan once more with Stage 1's coarse filter set to this
        (and the fit's grasps), and let E-RNet judge what it lets through; `Plan.fallback` says when that
        plan's grasp was chosen. None: one plan (the paper's planner).
    fit_grasps: Stage 1 also offers top-down grasps on each object's fitted superquadric
        (`sgjax.stage1.fit_grasps`), ahead of the transferred ones, filtered and judged by E-RNet like
        them, in both plans. None: the paper's candidates only.
    neighbour_fits: remove every candidate (and refined pose) whose hand, swept back over the approach,
        meets another object's fitted superquadric grown by its margin (`sgjax.stage1.neighbours`); in the
        second plan the candidates clear of them are tried first, all of them when those give no grasp.
        None: the paper's filters only.
    robust: among the best-evaluated passing candidates, execute the one whose E-RNet score holds up at
        small perturbations of its pose (`RobustChoice`). None: the paper's choice, the highest evaluation.
    reuse_tolerance: with a `Stage1Memory` passed to `plan`, an object whose cloud is within this many
        metres of the one Stage 1 last ran on (`pointcloud.same_cloud`) keeps those candidates, tested
        against the obstacles of now (`Stage1.rescene`). 0: only identical clouds. Set it to the depth
        noise of a real camera.
    """

    stage1: Stage1Config = dataclasses.field(default_factory=Stage1Config)
    eval_threshold: float = 0.7
    refine_threshold: float = 0.7
    use_refinement: bool = True
    refine_rescore: int = 64
    max_stage2_candidates: int = 512
    stage2_min_slots: int = 64
    min_object_points: int = 50
    scene_cloud: SceneCloudConfig = SceneCloudConfig()
    support_plane: tuple[float, float, float, float] | None = None
    stage1_batch_sizes: tuple[int, ...] = (1, 2, 4)
    avoid_distance: float = gripper.AVOID_DISTANCE
    avoid_angle_deg: float = gripper.AVOID_ANGLE_DEG
    fallback_filter: FilterConfig | None = FALLBACK_FILTER
    fit_grasps: FitGraspConfig | None = FitGraspConfig()
    reuse_tolerance: float = 0.0005
    neighbour_fits: NeighbourFitConfig | None = NeighbourFitConfig()
    robust: RobustChoice | None = RobustChoice()
    # Options measured and not adopted (docs/experiments.md): saved configs
    # holding their old defaults still load.
    RETIRED_FIELDS: ClassVar[dict] = {"fallback_match": None, "fallback_for": (), "lever_weight": 0.0, "failed_last": None,
                                      "prefer_fit_grasps": False}

    @property
    def first_stage1(self) -> Stage1Config:
        """The first plan's Stage-1 config: `stage1` with `fit_grasps`."""
        if self.fit_grasps is None:
            return self.stage1
        return dataclasses.replace(self.stage1, fit_grasps=self.fit_grasps)

    def __post_init__(self):
        object.__setattr__(self, "stage1_batch_sizes", tuple(sorted({int(b) for b in self.stage1_batch_sizes})))
        if not self.stage1_batch_sizes or self.stage1_batch_sizes[0] < 1:
            raise ValueError(f"stage1_batch_sizes must be positive integers, got {self.stage1_batch_sizes}")
        if self.max_stage2_candidates < 1:
            raise ValueError("max_stage2_candidates must be >= 1")
        if not 0 <= self.refine_rescore <= self.max_stage2_candidates:
            raise ValueError(f"refine_rescore must be in [0, max_stage2_candidates={self.max_stage2_candidates}], "
                             f"got {self.refine_rescore}")
        if self.stage2_min_slots < 1:
            raise ValueError(f"stage2_min_slots must be >= 1, got {self.stage2_min_slots}")
        if self.min_object_points < pointcloud.MIN_POINTS:
            raise ValueError(f"min_object_points must be >= {pointcloud.MIN_POINTS} (a superquadric fit needs that many)")
        if self.support_plane is not None:
            plane = tuple(float(v) for v in self.support_plane)
            if len(plane) != 4 or not np.all(np.isfinite(plane)) or not any(plane[:3]):
                raise ValueError(f"support_plane must be 4 finite numbers (nx, ny, nz, d), got {self.support_plane}")
            object.__setattr__(self, "support_plane", plane)
        if not (np.isfinite(self.reuse_tolerance) and self.reuse_tolerance >= 0):
            raise ValueError(f"reuse_tolerance must be a finite number >= 0 (metres), got {self.reuse_tolerance}")
        if self.avoid_distance < 0 or not 0 <= self.avoid_angle_deg <= 180:
            raise ValueError(f"avoid_distance must be >= 0 and avoid_angle_deg in [0, 180], got "
                             f"{self.avoid_distance} and {self.avoid_angle_deg}")
        if self.robust is not None and self.robust.rows > self.max_stage2_candidates:
            raise ValueError(f"robust.top x {PERTURBATIONS} = {self.robust.rows} perturbed poses exceed "
                             f"max_stage2_candidates={self.max_stage2_candidates}")
        policy.check_thresholds(self)

    @property
    def spec(self) -> GripperSpec:
        return self.stage1.spec

    @property
    def stage2_sizes(self) -> tuple[int, ...]:
        """The Stage-2 batch sizes: powers of two from stage2_min_slots, capped by max_stage2_candidates."""
        sizes, size = [], 1 << max(self.stage2_min_slots - 1, 0).bit_length()
        while size < self.max_stage2_candidates:
            sizes.append(size)
            size *= 2
        return (*sizes, self.max_stage2_candidates)

    def stage2_slots(self, m: int) -> int:
        """The Stage-2 batch size for m candidates (m <= max_stage2_candidates)."""
        return next(size for size in self.stage2_sizes if size >= m)


@dataclasses.dataclass
class Plan:
    """The planner's decision.

    pose [4, 4] (gripper frame -> world; the refined pose when kind == "refined"), width (m), target
    (object label the grasp is for; 0 for `plan_target`), score (eval prob, or the chosen refinement's
    score: its refine prob, or with `refine_rescore` the geometric mean of that and its pose's eval prob),
    kind "evaluated" | "refined" | None (no grasp), refine_variant 0..K-1 when refined,
    candidate_index (row of the `scores` arrays), reason (why no grasp, else None), n_candidates
    (Stage-1 candidates over all objects), timing {"stage1_s", "stage2_s", "total_s", "compiled"}
    (wall seconds of this call; "compiled" says whether it included a compilation), candidates (per
    planned object: stage1.Candidates), scores (NumPy over the M scored candidates: eval_prob [M],
    refine_prob [M, K], valid [M], target [M] label, object [M] index into `candidates`,
    object_candidate [M] row in that Candidates; with `refine_rescore`, when it ran: refine_score [M, K],
    the refinements' scores the policy used, 0 where not re-scored; with `robust`, when it ran:
    robust_score [M] and perturbed_score [M, 5], NaN where not judged), initial_pose [4, 4] (the chosen Stage-1 candidate,
    before refinement), objects (per object label: points, candidates, reason when skipped/empty),
    refinements_rejected (refined poses the policy chose that collided, each left out before deciding again),
    fallback (whether the grasp comes from the second plan with `PlannerConfig.fallback_filter`).
    """

    pose: np.ndarray | None
    width: float | None
    target: int | None
    score: float
    kind: str | None
    refine_variant: int | None
    candidate_index: int | None
    reason: str | None
    n_candidates: int
    timing: dict
    candidates: list
    scores: dict
    initial_pose: np.ndarray | None = None
    objects: list = dataclasses.field(default_factory=list)
    refinements_rejected: int = 0  # refined poses the policy chose that failed the collision tests
    fallback: bool = False  # planned with `PlannerConfig.fallback_filter` (the default filters found nothing)
    reused: int = 0  # objects whose Stage-1 candidates came from the memory (`plan(memory=...)`)

    @property
    def ok(self) -> bool:
        """Whether there is a grasp to execute."""
        return self.kind is not None

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready summary (no per-candidate arrays; see `scores` and `candidates` for those)."""
        as_list = lambda a: None if a is None else np.round(np.asarray(a, np.float64), 6).tolist()
        return {
            "kind": self.kind,
            "pose": as_list(self.pose),
            "width": None if self.width is None else round(float(self.width), 6),
            "target": self.target,
            "score": round(float(self.score), 6),
            "refine_variant": self.refine_variant,
            "candidate_index": self.candidate_index,
            "initial_pose": as_list(self.initial_pose),
            "reason": self.reason,
            "n_candidates": int(self.n_candidates),
            "n_scored": len(self.scores.get("eval_prob", ())),
            "timing": {k: (round(v, 6) if isinstance(v, float) else v) for k, v in self.timing.items()},
            "objects": self.objects,
            "refinements_rejected": int(self.refinements_rejected),
            "fallback": bool(self.fallback),
            "reused": int(self.reused),
        }


def _stage2(graphdef, state, scene, scene_mask, poses, widths, slots, key, thresholds, use_refinement, *, spec,
            scorer=ernet.score):
    """One compiled Stage 2: the network's scores of the candidate slots (scene [S, 3] + mask, poses
    [C, 4, 4], widths [C], slots bool[C]; `scorer` from `scorers.scorer_for`) and the decision."""
    scores = scorer(graphdef, state, scene, poses, widths, scene_mask, spec=spec, key=key)
    valid = scores.valid & slots
    choice = policy.select_grasp(
        poses, widths, scores.eval_prob, scores.refine_prob, valid, thresholds[0], thresholds[1], use_refinement, spec
    )
    return {"eval_prob": scores.eval_prob, "refine_prob": scores.refine_prob, "valid": valid}, choice


# ---------------------------------------------------------------------------------------------
# Input checks (host side, clear errors).


def _cloud(points, name: str) -> np.ndarray:
    try:
        arr = np.asarray(points, np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name}: not a numeric array ({exc})") from None
    if arr.ndim != 2 or arr.shape[-1] != 3:
        raise ValueError(f"{name} must have shape [N, 3], got {arr.shape}")
    if len(arr) == 0:
        raise ValueError(f"{name} is empty")
    bad = ~np.all(np.isfinite(arr), axis=1)
    if bad.any():
        raise ValueError(f"{name} holds NaN or inf coordinates ({int(bad.sum())} of {len(arr)} points)")
    return arr


def _labels(labels, n: int) -> np.ndarray:
    arr = np.asarray(labels)
    if arr.dtype == bool:
        raise ValueError("labels must be integer object ids; for a bool target mask use plan_target or sgjax.planner.plan")
    if arr.ndim != 1 or len(arr) != n:
        raise ValueError(f"labels must have shape [N] = ({n},) (one per scene point), got {arr.shape}")
    if arr.dtype.kind == "f":
        if not np.all(np.isfinite(arr)) or np.any(arr != np.round(arr)):
            raise ValueError("labels must be integer object ids (< 0 = table/background)")
        arr = arr.astype(np.int64)
    elif arr.dtype.kind not in "iu":
        raise ValueError(f"labels must be integer object ids, got dtype {arr.dtype}")
    return arr.astype(np.int64)


def _avoid(avoid) -> np.ndarray:
    """Poses to avoid as float64 [F, 4, 4] (None: none)."""
    if avoid is None:
        return np.zeros((0, 4, 4))
    try:
        arr = np.asarray(avoid, np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"avoid: not a numeric array ({exc})") from None
    if arr.ndim == 2 and arr.shape == (4, 4):
        arr = arr[None]
    if arr.ndim != 3 or arr.shape[1:] != (4, 4):
        raise ValueError(f"avoid must be gripper poses [F, 4, 4], got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError("avoid holds NaN or inf entries")
    return arr


def _viewpoint(viewpoint) -> np.ndarray:
    v = np.asarray(viewpoint if viewpoint is not None else (0.0, 0.0, 0.0), np.float64)
    if v.shape != (3,) or not np.all(np.isfinite(v)):
        raise ValueError(f"viewpoint must be 3 finite numbers (the camera position), got {np.asarray(viewpoint).tolist()}")
    return v


@dataclasses.dataclass
class _Scored:
    """What the decision policy's steps read: one plan's objects and Stage-1 candidates, the M scored
    candidates (scores as in `Plan.scores`, their poses [M, 4, 4] and widths [M]) and the Stage-2 inputs
    (scene_pad [S, 3], scene_mask [S], seed, thresholds) for the calls that judge them again."""

    stage1: Stage1
    objects: list
    candidates: list
    view: np.ndarray
    seed: int
    fitted: tuple | None
    scores: dict
    poses: np.ndarray
    widths: np.ndarray
    scene_pad: np.ndarray
    scene_mask: np.ndarray
    thresholds: np.ndarray


@functools.partial(jax.jit, static_argnums=(1, 2))
def _perturbed_jit(poses, shift: float, angle_deg: float):
    return gripper.perturbed_poses(poses, shift, angle_deg)


def _perturbed_poses(poses: np.ndarray, robust: RobustChoice) -> np.ndarray:
    """`gripper.perturbed_poses` of t <= robust.top poses [t, 4, 4] -> [t, 5, 4, 4], as one jitted program
    of robust.top rows (padded); eagerly, its fifteen small operations were each compiled or loaded per t."""
    t = len(poses)
    rows = np.tile(np.eye(4, dtype=np.float32), (robust.top, 1, 1))
    rows[:t] = poses
    return np.asarray(_perturbed_jit(rows, robust.shift, robust.angle_deg), np.float32)[:t]


class Planner:
    """Stage 1 + Stage 2 with the database and the E-RNet weights on the device.

    model: an ERNet, a `sgjax train` run directory, or None (the shipped one for the gripper, `config.spec`:
        `ernet.load_default_model`);
        a PointNetGPD instead: the network ablation (`sgjax.stage2.scorers`; needs use_refinement=False);
    db: a PrimitiveDB, or None (the default database from the cache, built on first use);
    config: a `PlannerConfig` (named ones: `sgjax.presets`).

    `checkpoint` names the network's checkpoint ("sgjax/models/ernet_default", the run directory, "an
    in-memory model", or for `scorers.Stage1Order` "none (Stage 1's order)") and `checkpoint_gripper` the
    gripper it was trained for (its meta's record; None for a model in memory or no network). When that differs from the gripper the planner plans for (`config.spec`), the
    planner warns once, when it is built (`checkpoint.gripper_mismatch`).
    """

    def __init__(self, model=None, db: PrimitiveDB | None = None, config: PlannerConfig = PlannerConfig()):
        enable_compilation_cache()  # a new process loads what an earlier one compiled
        # PointNetGPD in E-RNet's place is the network ablation (`scorers`): it has no refinement head.
        other_scorer = isinstance(model, (pointnetgpd.PointNetGPD, scorers.Stage1Order))
        self.model = model if other_scorer else ernet.as_model(model, config.spec)
        self.config = config
        if isinstance(self.model, scorers.Stage1Order):  # no network, so no checkpoint and no gripper to check
            self.checkpoint, self.checkpoint_gripper = scorers.STAGE1_ORDER, None
        else:
            self.checkpoint, self.checkpoint_gripper = checkpoint.model_checkpoint(
                model, checkpoint.ERNET_DEFAULT_DIR, config.spec)
            network = "E-RNet" if isinstance(self.model, ernet.ERNet) else type(self.model).__name__
            checkpoint.warn_mismatch(network, self.checkpoint, self.checkpoint_gripper, config.spec)
        self._scorer = scorers.scorer_for(self.model)
        if not scorers.has_refinement(self.model):
            if config.use_refinement:
                raise ValueError(f"{type(self.model).__name__} has no refinement head: plan with use_refinement=False")
        elif self.model.config.n_refinements != config.spec.num_refinements:
            raise ValueError(
                f"the E-RNet predicts {self.model.config.n_refinements} refinements but the gripper spec has "
                f"{config.spec.num_refinements}"
            )
        self.stage1 = Stage1(db, config.first_stage1)
        self._fallback_stages: dict[Stage1Config, Stage1] = {}  # by config: `config` may be replaced later
        self.graphdef, state = nnx.split(self.model)
        # Restored checkpoints are committed to a device and fresh models are not; committedness is part
        # of jit's cache key, so commit both: every Planner with this network shares one compiled Stage 2.
        self.state = jax.device_put(state, jax.devices()[0])
        self._stage2_ready = False  # whether every Stage-2 batch size has been compiled
        self._fits_ready = False  # likewise the neighbour-fit test (`PlannerConfig.neighbour_fits`)

    # -- public entry points ------------------------------------------------------------------

    def plan(self, scene_points, labels, viewpoint=(0.0, 0.0, 0.0), seed: int = 0, avoid=None,
             memory: Stage1Memory | None = None) -> Plan:
        """Plan over every visible object of a scene.

        scene_points [N, 3] (metres, world frame); labels int [N]: the object id of each point, < 0 for
        the table/background; viewpoint [3]: camera position (orients normals). Objects with fewer
        than `min_object_points` points are skipped. Stage 1 sees each object with the rest of the
        scene as obstacles; all candidates are scored in one Stage-2 call on the whole scene.
        avoid [F, 4, 4] (or None): gripper poses not to plan again, e.g. grasps that failed on this
        scene; candidates within `avoid_distance` / `avoid_angle_deg` of one are left out.
        memory: a `Stage1Memory` kept by the caller over the plans of one scene: objects whose cloud has
        not changed since Stage 1 last ran on them keep their candidates (`PlannerConfig.reuse_tolerance`),
        tested against the obstacles of now; `Plan.reused` counts them. None: Stage 1 on every object.
        """
        start = time.perf_counter()
        scene = _cloud(scene_points, "scene_points")
        labels = _labels(labels, len(scene))
        view, avoid = _viewpoint(viewpoint), _avoid(avoid)
        ids, counts = np.unique(labels[labels >= 0], return_counts=True)
        # Each object's points in scene order, from one stable sort rather than a pass per object.
        by_label = np.argsort(labels, kind="stable")[int(np.sum(labels < 0)):]
        rows = dict(zip(ids.tolist(), np.split(by_label, np.cumsum(counts)[:-1])))
        # The table is filter (v)'s: dropping its points once here saves each object's crop a pass over them.
        free = self.stage1.off_table(scene, self.config.support_plane)
        obstacles, obstacle_labels = scene[free], labels[free]
        margin = self.stage1.config.scene_margin
        objects, skipped = [], []
        for label, count in zip(ids.tolist(), counts.tolist()):
            if count < self.config.min_object_points:
                skipped.append({"label": label, "points": count, "candidates": 0,
                                "reason": f"{count} visible points < min_object_points {self.config.min_object_points}"})
            else:
                cloud = scene[rows[label]]
                # The rest of the scene within Stage 1's crop box (`Stage1._crop_scene` keeps no other points,
                # in the same order): one pass here instead of a copy of the whole scene per object.
                near = np.all((obstacles >= cloud.min(0) - margin) & (obstacles <= cloud.max(0) + margin), axis=1)
                objects.append((label, cloud, obstacles[near & (obstacle_labels != label)]))
        if not objects:
            if len(ids) == 0:
                reason = "no object points: every label is < 0 (table/background)"
            else:
                listed = ", ".join(f"object {s['label']}: {s['points']}" for s in skipped[:8])
                reason = f"no object with at least {self.config.min_object_points} visible points ({listed})"
            return self._empty(reason, skipped, start)
        return self._run(scene, objects, skipped, view, seed, start, avoid, memory)

    def plan_target(self, scene_points, target_points, viewpoint=(0.0, 0.0, 0.0), seed: int = 0, avoid=None) -> Plan:
        """Plan for one given object cloud target_points [K, 3] in the scene scene_points [N, 3] (which
        should contain the target's points: Stage 2 crops from it; None: the target alone). Target label 0.
        avoid: as in `plan`."""
        start = time.perf_counter()
        target = _cloud(target_points, "target_points")
        scene = target if scene_points is None else _cloud(scene_points, "scene_points")
        return self._plan_one(scene, target, scene, _viewpoint(viewpoint), seed, start, _avoid(avoid))

    def plan_masked(self, scene_points, target_mask, viewpoint=(0.0, 0.0, 0.0), seed: int = 0, avoid=None) -> Plan:
        """Plan for the object marked by target_mask bool [N] in scene_points [N, 3] (the other points are
        Stage 1's obstacles; Stage 2 sees the whole scene). Target label 0. avoid: as in `plan`."""
        start = time.perf_counter()
        scene = _cloud(scene_points, "scene_points")
        mask = np.asarray(target_mask)
        if mask.dtype != bool or mask.shape != (len(scene),):
            raise ValueError(f"the target mask must be bool with shape [N] = ({len(scene)},), got {mask.dtype} {mask.shape}")
        free = self.stage1.off_table(scene, self.config.support_plane)
        return self._plan_one(scene, scene[mask], scene[~mask & free], _viewpoint(viewpoint), seed, start, _avoid(avoid))

    # -- internals ------------------------------------------------------------------------------

    def _plan_one(self, scene, target, obstacles, view, seed, start, avoid) -> Plan:
        if len(target) < self.config.min_object_points:
            info = {"label": 0, "points": len(target), "candidates": 0,
                    "reason": f"{len(target)} visible points < min_object_points {self.config.min_object_points}"}
            return self._empty(f"target: {info['reason']}", [info], start)
        return self._run(scene, [(0, target, obstacles)], [], view, seed, start, avoid)

    def _empty(self, reason: str, objects: list, start: float, candidates=(), timing=None) -> Plan:
        timing = timing or {"stage1_s": 0.0, "stage2_s": 0.0, "total_s": time.perf_counter() - start, "compiled": False}
        spec_k = self.config.spec.num_refinements
        scores = {"eval_prob": np.zeros(0, np.float32), "refine_prob": np.zeros((0, spec_k), np.float32),
                  "valid": np.zeros(0, bool), "target": np.zeros(0, np.int64), "object": np.zeros(0, np.int64),
                  "object_candidate": np.zeros(0, np.int64)}
        n = sum(len(c) for c in candidates)
        return Plan(None, None, None, 0.0, None, None, None, reason, n, timing, list(candidates), scores, None, objects)

    def judge(self, scene_points, poses, widths, seed: int = 0) -> dict[str, np.ndarray]:
        """E-RNet's judgement of given grasps as a plan's Stage 2 makes it (the same Stage-2 scene cloud of
        `scene_points` [N, 3] and `seed`, the same compiled calls): poses [M, 4, 4], widths [M] ->
        {"eval_prob" [M], "refine_prob" [M, K], "valid" bool [M]} (NumPy; valid False where the closing
        region holds no scene point, with probabilities 0). For scoring another sampler's grasps."""
        cfg = self.config
        poses = np.asarray(poses, np.float32).reshape(-1, 4, 4)
        widths = np.asarray(widths, np.float32).reshape(-1)
        if len(poses) != len(widths):
            raise ValueError(f"got {len(poses)} poses but {len(widths)} widths")
        scene_pad, scene_mask = self._scene(_cloud(scene_points, "scene_points"), seed)
        thresholds = np.array([cfg.eval_threshold, cfg.refine_threshold], np.float32)
        size = cfg.stage2_sizes[-1]
        parts = [self._score_rows(scene_pad, scene_mask, poses[begin:begin + size], widths[begin:begin + size], seed,
                                  thresholds) for begin in range(0, len(poses), size)]
        if not parts:
            k = self.model.config.n_refinements if scorers.has_refinement(self.model) else 0
            return {"eval_prob": np.zeros(0, np.float32), "refine_prob": np.zeros((0, k), np.float32),
                    "valid": np.zeros(0, bool)}
        return {k: np.concatenate([part[k] for part in parts]) for k in ("eval_prob", "refine_prob", "valid")}

    def _score_rows(self, scene_pad, scene_mask, poses, widths, seed: int, thresholds) -> dict[str, np.ndarray]:
        """Stage 2 on n <= the largest batch size of grasps (poses [n, 4, 4], widths [n]), padded to the
        Stage-2 batch size that holds them so that nothing compiles anew -> E-RNet's outputs for the n rows
        (`_score`'s, NumPy)."""
        n = len(poses)
        slots = self.config.stage2_slots(n)
        pad_poses, pad_widths = policy.padded_batch(poses, widths, slots)
        out, _ = self._score(scene_pad, scene_mask, pad_poses, pad_widths, np.arange(slots) < n, seed, thresholds)
        return {k: np.asarray(v)[:n] for k, v in out.items()}

    def stage2_cloud(self, scene_points, seed: int = 0) -> np.ndarray:
        """The Stage-2 scene cloud a plan of `scene_points` [N, 3] with `seed` crops from: its real points
        [C, 3] float32 in the order the crops read them (C <= scene_cloud.max_points). Stored with a
        grasp, a crop of it (`sgjax.stage2.crops`) is that plan's own crop (training data from plans)."""
        points, mask = self._scene(_cloud(scene_points, "scene_points"), seed)
        order = np.asarray(ernet.scene_order(len(points), jax.random.key(seed)))  # as `_stage2_call` shuffles it
        return np.asarray(points)[order][np.asarray(mask)[order]]

    def _scene(self, scene: np.ndarray, seed: int) -> tuple[np.ndarray, np.ndarray]:
        """The fixed-size Stage-2 scene cloud: points [scene_cloud.max_points, 3] float32 and mask."""
        points, mask, _ = self.config.scene_cloud.make(scene, None, seed)
        return points, mask

    def _kept(self, candidates: list[Candidates], avoid: np.ndarray) -> list[np.ndarray]:
        """Per object, the candidate rows not near a pose in avoid [F, 4, 4] (all rows when F = 0)."""
        cfg = self.config
        if not len(avoid):
            return [np.arange(len(c)) for c in candidates]
        return [np.flatnonzero(~gripper.near_grasps(np.asarray(c.poses, np.float64), avoid, cfg.spec, cfg.avoid_distance,
                                                    cfg.avoid_angle_deg, xp=np)) for c in candidates]

    def _run(self, scene, objects, skipped, view, seed, start, avoid, memory=None) -> Plan:
        """The first plan, and the second (`fallback_filter`) when the first finds no grasp."""
        plan = self._run_with(self.stage1, scene, objects, skipped, view, seed, start, avoid, memory)
        fallback = None if plan.ok else self._fallback_stage()
        if fallback is None:
            return plan
        second = self._run_with(fallback, scene, objects, skipped, view, seed, start, avoid, memory, second=True)
        second.reused += plan.reused
        if second.ok:
            second.fallback = True
            return second
        plan.reason = f"{plan.reason}; with the fallback filter: {second.reason}"
        plan.timing = second.timing  # from the same start: both plans
        return plan

    def _fallback_stage(self) -> Stage1 | None:
        """Stage 1 with `config.fallback_filter` and the fit's grasps (built once per Stage-1 config), or
        None without a fallback filter."""
        cfg = self.config
        if cfg.fallback_filter is None:
            return None
        stage_cfg = dataclasses.replace(cfg.stage1, filter=cfg.fallback_filter, fit_grasps=cfg.fit_grasps)
        if stage_cfg not in self._fallback_stages:
            self._fallback_stages[stage_cfg] = Stage1(self.stage1.db, stage_cfg, share=self.stage1)
        return self._fallback_stages[stage_cfg]

    def _stage1(self, stage1: Stage1, objects: list, view, seed: int, memory: Stage1Memory | None) -> tuple[list, int]:
        """Stage 1 on objects [(label, cloud, obstacles)] -> (Candidates per object, how many came from memory)."""
        cfg = self.config
        clouds, obstacles = [o for _, o, _ in objects], [s for _, _, s in objects]
        if memory is None:
            return stage1.chunked(clouds, obstacles, view, seed, cfg.support_plane, cfg.stage1_batch_sizes), 0
        setup = (stage1.config, cfg.support_plane)  # a result holds only under the filters and table it had
        previous = [memory.recall(setup, label, cloud, cfg.reuse_tolerance) for label, cloud, _ in objects]
        out: list = list(previous)
        fresh = [i for i, p in enumerate(previous) if p is None]
        if fresh:
            results = stage1.chunked([clouds[i] for i in fresh], [obstacles[i] for i in fresh], view, seed,
                                     cfg.support_plane, cfg.stage1_batch_sizes)
            for i, result in zip(fresh, results):
                out[i] = result
                memory.remember(setup, objects[i][0], clouds[i], result)
        kept = [i for i, p in enumerate(previous) if p is not None]
        if kept:  # the neighbours may have changed: filter (iv) again
            results = stage1.rescene([previous[i] for i in kept], [clouds[i] for i in kept], [obstacles[i] for i in kept],
                                     view, seed, cfg.support_plane, cfg.stage1_batch_sizes)
            for i, result in zip(kept, results):
                out[i] = result
        return out, len(kept)

    def _run_with(self, stage1: Stage1, scene, objects, skipped, view, seed, start, avoid, memory=None,
                  second: bool = False) -> Plan:
        """One plan with this Stage 1. With `neighbour_fits`, the candidates that meet a neighbour's fit are
        left out; in the second plan only while the others give a grasp (what the test removed may be all
        there is)."""
        compiled = _compile_count()
        candidates, reused = self._stage1(stage1, objects, view, seed, memory)
        args = (stage1, scene, objects, skipped, view, seed, start, avoid)
        if self.config.neighbour_fits is None:
            plan = self._choose(*args, candidates, compiled)
        else:
            clear, fitted = self._without_fit_collisions(stage1, candidates, objects, seed)
            plan = self._choose(*args, clear, compiled, fitted)
            if second and not plan.ok and sum(map(len, clear)) < sum(map(len, candidates)):
                plan = self._choose(*args, candidates, compiled)
        plan.reused = reused
        return plan

    def _without_fit_collisions(self, stage1: Stage1, candidates: list[Candidates], objects: list,
                                seed: int) -> tuple[list[Candidates], tuple]:
        """Candidates whose hand meets another object's fitted superquadric removed
        (`sgjax.stage1.neighbours`), and the fits tested (`neighbours.obstacle_fits`: the refined poses
        are tested against them too). Compiled for every Stage-2 batch size at the first plan."""
        cfg = self.config
        sweep = stage1.config.filter.approach_clearance
        if not self._fits_ready:
            neighbours.warm(candidates, cfg.spec, cfg.neighbour_fits, sweep, cfg.stage2_sizes)
            self._fits_ready = True
        fitted = neighbours.obstacle_fits(candidates, [cloud for _, cloud, _ in objects], cfg.neighbour_fits, seed)
        return neighbours.without_fit_collisions(candidates, fitted, cfg.spec, cfg.neighbour_fits, sweep,
                                                 cfg.stage2_sizes), fitted

    def _choose(self, stage1: Stage1, scene, objects, skipped, view, seed, start, avoid, candidates, compiled,
                fitted: tuple | None = None) -> Plan:
        """Stage 2 and the decision policy on Stage 1's candidates (one Candidates per object); fitted: the
        neighbours' fits the refined poses are tested against (None: not tested)."""
        cfg = self.config
        labels = [label for label, _, _ in objects]
        t1 = time.perf_counter()
        infos = sorted(
            skipped + [{"label": lab, "points": len(o), "candidates": len(c), "reason": c.reason}
                       for (lab, o, _), c in zip(objects, candidates)],
            key=lambda d: d["label"],
        )
        n_candidates = sum(len(c) for c in candidates)
        timing = {"stage1_s": t1 - start, "stage2_s": 0.0, "total_s": t1 - start, "compiled": _compile_count() != compiled}
        if n_candidates == 0:
            detail = "; ".join(f"object {lab}: {c.reason}" for lab, c in zip(labels, candidates))
            return self._empty(f"no candidates: {detail}", infos, start, candidates, timing)
        kept = self._kept(candidates, avoid)
        if not sum(len(k) for k in kept):
            reason = (f"all {n_candidates} candidates are within {cfg.avoid_distance:g} m and {cfg.avoid_angle_deg:g} deg "
                      f"of the {len(avoid)} pose(s) to avoid")
            return self._empty(reason, infos, start, candidates, timing)

        scored, choice = self._stage2_scores(stage1, scene, objects, candidates, kept, view, seed, fitted)
        choice, rejected = self._policy(choice, scored)
        t2 = time.perf_counter()
        timing.update(stage2_s=t2 - t1, total_s=t2 - start, compiled=_compile_count() != compiled)

        scores, kind = scored.scores, int(choice["kind"])
        if kind == KIND_NONE:
            plan = self._empty(self._why_not(scores, len(scores["eval_prob"]), rejected), infos, start, candidates, timing)
            plan.scores, plan.score, plan.refinements_rejected = scores, float(choice["score"]), rejected
            return plan
        index = int(choice["index"])
        o, r = int(scores["object"][index]), int(scores["object_candidate"][index])
        initial = candidates[o].poses[r]
        refined = kind == KIND_REFINED
        return Plan(
            pose=np.asarray(choice["pose"], np.float64) if refined else initial.copy(),
            width=float(candidates[o].widths[r]),
            target=int(labels[o]),
            score=float(choice["score"]),
            kind=KIND_NAMES[kind],
            refine_variant=int(choice["variant"]) if refined else None,
            candidate_index=index,
            reason=None,
            n_candidates=n_candidates,
            timing=timing,
            candidates=candidates,
            scores=scores,
            initial_pose=initial.copy(),
            objects=infos,
            refinements_rejected=rejected,
        )

    def _stage2_scores(self, stage1: Stage1, scene, objects, candidates, kept, view, seed, fitted) -> tuple[_Scored, dict]:
        """The kept candidates (rows `kept[b]` of each object's Candidates) scored by E-RNet in one
        Stage-2 call on the padded batch that holds them -> (_Scored, the paper's choice from that call)."""
        cfg = self.config
        obj, rank = policy.stage2_subset([len(k) for k in kept], cfg.max_stage2_candidates)
        row = np.asarray([kept[o][r] for o, r in zip(obj, rank)], np.int64).reshape(-1)
        m = len(obj)
        slots = cfg.stage2_slots(m)
        offsets = np.cumsum([0] + [len(c) for c in candidates])[:-1]
        poses, widths = policy.padded_batch(np.concatenate([c.poses for c in candidates])[offsets[obj] + row],
                                            np.concatenate([c.widths for c in candidates])[offsets[obj] + row], slots)
        scene_pad, scene_mask = self._scene(scene, seed)
        thresholds = np.array([cfg.eval_threshold, cfg.refine_threshold], np.float32)
        if not self._stage2_ready:
            self._warm_stage2(scene_pad, scene_mask, seed, thresholds, skip=slots)
        out, choice = self._score(scene_pad, scene_mask, poses, widths, np.arange(slots) < m, seed, thresholds)
        labels = np.asarray([label for label, _, _ in objects], np.int64)
        scores = {"eval_prob": out["eval_prob"][:m], "refine_prob": out["refine_prob"][:m], "valid": out["valid"][:m],
                  "target": labels[obj], "object": obj, "object_candidate": row}
        return _Scored(stage1, objects, candidates, view, seed, fitted, scores, poses[:m], widths[:m], scene_pad,
                       scene_mask, thresholds), choice

    def _warm_stage2(self, scene_pad, scene_mask, seed: int, thresholds, skip: int) -> None:
        """Compile (or load from the cache) every Stage-2 batch size but `skip` (the one about to run), so
        that no later plan stalls on a compile."""
        cfg = self.config
        for size in cfg.stage2_sizes:
            empty = policy.padded_batch(np.zeros((0, 4, 4), np.float32), np.zeros(0, np.float32), size)
            args = (scene_pad, scene_mask, *empty, np.zeros(size, bool), seed, thresholds)
            # A size already exported to the cache is only loaded (~0.3 s) when first used: a warm
            # process's first plan then loads one Stage-2 program, not all of them.
            if size != skip and not exported.ready("stage2", *self._stage2_call(*args)[1:]):
                self._score(*args)
            if cfg.use_refinement:  # the host-side decision of re-scored or rejected refinements, per size
                self._decide(np.zeros(size, np.float32), np.zeros((size, cfg.spec.num_refinements), np.float32),
                             np.zeros(size, bool))
        self._stage2_ready = True

    # -- the decision policy ----------------------------------------------------------------------

    def _policy(self, choice: dict, s: _Scored) -> tuple[dict, int]:
        """The decision after Stage 2's scores, one step after another (the pure pieces: `sgjax.policy`)
        -> (choice {"index", "kind", "variant", "score", "pose"}, refined poses left out for collisions)."""
        cfg = self.config
        # 1. The paper's rule, already made inside the Stage-2 call (`policy.select_grasp`): `choice`.
        # 2. Among the best evaluated, the one whose score holds up at perturbed poses.
        if cfg.robust is not None and int(choice["kind"]) == KIND_EVALUATED:
            choice = self._robust(choice, s)
        # 3. No evaluation passes: the refine head's best proposals judged again at their refined pose.
        if cfg.use_refinement and cfg.refine_rescore and int(choice["kind"]) != KIND_EVALUATED:
            choice = self._rescore(s)
        # 4. A refined pose that meets an obstacle, a neighbour's fit or the table is left out; decide again.
        if int(choice["kind"]) == KIND_REFINED:
            return self._collision_free(choice, s)
        return choice, 0

    def _robust(self, choice: dict, s: _Scored) -> dict:
        """Step 2 (`PlannerConfig.robust`): the best-evaluated passing candidates judged at perturbed poses
        in one Stage-2 call (`policy.robust_scores`), the highest mean executed (`policy.robust_choice`).
        Adds scores["robust_score"] [M] and scores["perturbed_score"] [M, 5] (NaN where not judged)."""
        cfg, scores = self.config, s.scores

        def judge(index):
            perturbed = _perturbed_poses(s.poses[index], cfg.robust)
            n = perturbed.shape[0] * PERTURBATIONS
            out = self._score_rows(s.scene_pad, s.scene_mask, perturbed.reshape(n, 4, 4),
                                   np.repeat(s.widths[index], PERTURBATIONS), s.seed, s.thresholds)
            judged = np.where(out["valid"], out["eval_prob"], 0.0).reshape(-1, PERTURBATIONS)
            scores["perturbed_score"][index] = judged  # kept for whoever studies the choice (eval.counterfactual)
            return judged

        scores["perturbed_score"] = np.full((len(scores["valid"]), PERTURBATIONS), np.nan, np.float32)
        scores["robust_score"] = policy.robust_scores(scores["eval_prob"], scores["valid"], cfg.eval_threshold,
                                                      cfg.robust.top, judge)
        return policy.robust_choice(choice, scores)

    def _rescore(self, s: _Scored) -> dict:
        """Step 3 (`PlannerConfig.refine_rescore`, `policy.rescored_refinements`): each of the refine head's
        best proposals scored by the evaluation head at its refined pose, in one Stage-2 call on the
        smallest batch that holds them. Adds scores["refine_score"] [M, K] (0 where not re-scored) and
        decides again on it -> choice."""
        cfg, scores = self.config, s.scores

        def judge(index, variant):
            n = len(index)
            slots = cfg.stage2_slots(n)  # a Stage-2 batch size, so that no plan compiles
            refined, refined_widths = policy.padded_refinements(s.poses, s.widths, index, variant, slots, cfg.spec)
            out, _ = self._score(s.scene_pad, s.scene_mask, refined, refined_widths, np.arange(slots) < n, s.seed,
                                 s.thresholds)
            return np.where(out["valid"][:n], out["eval_prob"][:n], 0.0)

        scores["refine_score"] = policy.rescored_refinements(scores["refine_prob"], scores["valid"], cfg.refine_rescore, judge)
        return self._decide(scores["eval_prob"], scores["refine_score"], scores["valid"])

    def _collision_free(self, choice: dict, s: _Scored) -> tuple[dict, int]:
        """Step 4 (`policy.collision_free`): every refined pose the policy would execute checked by Stage 1's
        obstacle and table tests ((iv), (v) of `Stage1.collisions`) and the neighbours' fits where the
        plan tests them: a refinement deepens and turns the hand, and E-RNet's crop does not show all the
        obstacles or the table. -> (choice, refined poses left out)."""
        cfg, scores = self.config, s.scores
        sweep = s.stage1.config.filter.approach_clearance

        def collides(index):
            o, r = int(scores["object"][index]), int(scores["object_candidate"][index])
            _, cloud, obstacles = s.objects[o]
            # Every variant of this candidate in one call: the policy may turn to another of them next.
            variants = np.asarray(gripper.refined_poses(s.candidates[o].poses[r].astype(np.float32), cfg.spec))
            widths = np.full(len(variants), s.candidates[o].widths[r], np.float32)
            # Object o's Stage-1 call cropped its obstacles with seed + o (`Stage1.chunked`): the same crop.
            # A deepened pose that reaches into the table is backed off it first, as Stage 1 backs its
            # candidates off (`lift_to_plane`): on objects lying on the table that undoes some deepening.
            found = s.stage1.collisions(cloud, obstacles, variants, widths, s.view, s.seed + o, cfg.support_plane, lift=True)
            # The obstacles and the table, not the target: the target lies in E-RNet's crop, and its refine
            # head was trained on how these very refinements fared against it in simulation.
            hits = found["collision_scene"] | found["below_support"]
            if s.fitted is not None:  # and the other objects' hidden sides, as the candidates were
                fits, mask, pairs = s.fitted
                hits = hits | neighbours.fit_hits(found["poses"], widths, np.full(len(widths), o, np.int32), fits, mask,
                                                  cfg.spec, cfg.neighbour_fits, sweep, cfg.stage2_sizes, pairs)
            moved = np.any(found["poses"] != variants, axis=(1, 2))
            return hits, found["poses"], moved

        # The refinements' scores the policy decided on: the re-scored ones when step 3 ran.
        refine_score = scores.get("refine_score", scores["refine_prob"])
        return policy.collision_free(choice, scores["eval_prob"], refine_score, scores["valid"], collides, self._decide)

    def _decide(self, eval_prob: np.ndarray, refine_score: np.ndarray, valid: np.ndarray) -> dict:
        """`policy.decide` on the host's scores [M], [M, K], [M], padded to the Stage-2 batch size that holds
        M so that it compiles once per batch size, not once per candidate count -> choice (pose None)."""
        cfg = self.config
        m = len(eval_prob)
        slots = cfg.stage2_slots(m)
        pad = lambda a, fill: np.concatenate([a, np.full((slots - m, *a.shape[1:]), fill, a.dtype)])
        index, kind, variant, best = (np.asarray(v) for v in policy.decide_jit(
            pad(np.asarray(eval_prob, np.float32), 0.0), pad(np.asarray(refine_score, np.float32), 0.0),
            pad(np.asarray(valid, bool), False), np.float32(cfg.eval_threshold), np.float32(cfg.refine_threshold),
            np.bool_(cfg.use_refinement)))
        return {"index": index, "kind": kind, "variant": variant, "score": best, "pose": None}

    # -- Stage 2 ----------------------------------------------------------------------------------

    def _stage2_call(self, scene_pad, scene_mask, poses, widths, slots, seed: int, thresholds):
        """(function, arguments, static key) of one Stage-2 call, for `exported.call` / `exported.ready`."""
        cfg = self.config
        return (
            functools.partial(_stage2, self.graphdef, spec=cfg.spec, scorer=self._scorer),
            (self.state, scene_pad, scene_mask, poses, widths, slots, jax.random.key(seed), thresholds,
             np.bool_(cfg.use_refinement)),
            (type(self.model).__qualname__, repr(self.model.config), cfg.spec),
        )

    def _score(self, scene_pad, scene_mask, poses, widths, slots, seed: int, thresholds):
        """One Stage-2 call (`_stage2`) -> (scores, choice) as NumPy. Exported once to the cache, keyed by
        the network's class and config (which fix its graphdef)."""
        fn, args, static = self._stage2_call(scene_pad, scene_mask, poses, widths, slots, seed, thresholds)
        return jax.tree.map(np.asarray, exported.call("stage2", fn, args, static))

    def _why_not(self, scores: dict, m: int, rejected: int = 0) -> str:
        """Why the policy chose nothing among m scored candidates; rejected: refined poses it chose that
        failed the collision tests (`_collision_free`)."""
        cfg = self.config
        valid = scores["valid"]
        if not valid.any():
            return f"none of the {m} scored candidates has a scene point in its closing region (E-RNet valid = False)"
        best_eval = float(scores["eval_prob"][valid].max())
        text = f"best eval {best_eval:.2f} <= {cfg.eval_threshold:g}"
        if not cfg.use_refinement:
            return text + " (refinement disabled)"
        if rejected:
            return (text + f", and the {rejected} refined pose(s) scored above {cfg.refine_threshold:g} meet an "
                    "obstacle or the table")
        if "refine_score" in scores:
            best = float(scores["refine_score"][valid].max())
            return text + f" and best re-scored refinement {best:.2f} <= {cfg.refine_threshold:g}"
        best_refine = float(scores["refine_prob"][valid].max())
        return text + f" and best refine {best_refine:.2f} <= {cfg.refine_threshold:g}"


def stage1_order_planner(db: PrimitiveDB | None = None, config: PlannerConfig = PlannerConfig()) -> Planner:
    """The planner without a Stage-2 network: Stage 1's candidates in Stage 1's order
    (`scorers.Stage1Order`), no refinement (`sgjax plan --model none`; measured better than another
    gripper's E-RNet, docs/grippers.md). db and config as `Planner`'s."""
    return Planner(scorers.Stage1Order(), db, dataclasses.replace(config, use_refinement=False))


def _compile_count() -> int:
    return exported.compiled_programs()


# ---------------------------------------------------------------------------------------------
# Convenience.


@functools.lru_cache(maxsize=2)
def _default_planner(config: PlannerConfig) -> Planner:
    return Planner(None, None, config)


def plan(
    scene_points,
    object_masks_or_target_points,
    viewpoint=(0.0, 0.0, 0.0),
    model=None,
    db: PrimitiveDB | None = None,
    config: PlannerConfig = PlannerConfig(),
    seed: int = 0,
    avoid=None,
) -> Plan:
    """Plan a grasp in scene_points [N, 3]; the second argument says what to grasp:

    int [N] labels (object id per point, < 0 background) -> `Planner.plan` over every object;
    bool [N] target mask -> `Planner.plan_masked` (the unmasked points are Stage 1's obstacles);
    bool [B, N] object masks (disjoint) -> labels 0..B-1; float [K, 3] target points -> `plan_target`.
    With model and db None, a cached default Planner is used (built once per config); otherwise a new
    Planner is built per call (build one yourself for repeated calls). avoid [F, 4, 4]: poses not to
    plan again (see `Planner.plan`).
    """
    planner = _default_planner(config) if model is None and db is None else Planner(model, db, config)
    scene = _cloud(scene_points, "scene_points")
    what = np.asarray(object_masks_or_target_points)
    if what.dtype == bool and what.ndim == 1:
        return planner.plan_masked(scene, what, viewpoint, seed, avoid)
    if what.dtype == bool and what.ndim == 2:
        if what.shape[1] != len(scene):
            raise ValueError(f"object masks must have shape [B, N] with N = {len(scene)}, got {what.shape}")
        if np.any(what.sum(0) > 1):
            raise ValueError("object masks overlap: a point belongs to more than one object")
        labels = np.where(what.any(0), np.argmax(what, 0), -1)
        return planner.plan(scene, labels, viewpoint, seed, avoid)
    if what.ndim == 2:
        return planner.plan_target(scene, what, viewpoint, seed, avoid)
    return planner.plan(scene, what, viewpoint, seed, avoid)
