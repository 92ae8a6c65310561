"""The SuperGrasp planner: Stage 1 candidates -> E-RNet scores -> one grasp (paper Sec. IV-D, IV-E).

    plan = Planner(model, db).plan(scene_points, labels)     # every visible object of a scene
    plan = Planner(model, db).plan_target(scene_points, target_points)   # one given object cloud
    plan = Planner(model, db).plan_masked(scene_points, target_mask)     # one object by a bool mask
    plan = sgjax.planner.plan(scene_points, mask_or_labels_or_target)    # cached default planner

Stage 1 (`sgjax.stage1.pipeline`) turns each object's single-view cloud into grasp candidates (superquadric
fit, similarity matching, grasp transfer, coarse filtering, the rest of the scene as obstacles). Then,
with every object's fit at hand, the candidates whose hand meets another object's fitted superquadric
go (`PlannerConfig.neighbour_fits`, `sgjax.stage1.neighbours`: the neighbours' unseen sides).
Stage 2 scores all candidates of all objects in ONE jit-compiled E-RNet call on the whole scene
cloud (`sgjax.stage2.ernet.score`), and the decision policy of the paper (Sec. IV-E, "During inference")
picks the grasp (`decide`):

  1. the candidate with the highest evaluation score is executed when that score exceeds
     `eval_threshold` (0.7); by default, among the 12 best that pass, the one whose score holds up best
     when E-RNet judges it again at five slightly perturbed poses (`PlannerConfig.robust`, `RobustChoice`;
     None: the paper's, the highest);
  2. otherwise, when the highest refinement score over all candidates and variants exceeds
     `refine_threshold` (0.7), that candidate is refined by that variant (deepen 0.008 m, rotate
     -15 / 0 / +15 deg about the approach axis, `sgjax.geometry.gripper.refined_pose`) and executed,
     where a refinement's score is, by default, not the refine head's alone: the `refine_rescore` best
     proposals of the refine head are cropped again at their refined pose and judged by the evaluation
     head, and a refinement scores the geometric mean of the two (`PlannerConfig.refine_rescore`; 0: the
     paper's rule, the refine head alone),
     once the refined pose, backed off the table where it reaches into it, has passed Stage 1's obstacle
     and table tests ((iv), (v): `Stage1.collisions`) and the neighbours' fits; one that fails is left out
     and the policy decides again;
  3. otherwise there is no grasp, and `Plan.reason` says why.

`use_refinement=False` skips step 2 (the paper's "without the refinement branch" ablation).

Fixed shapes, so repeated plans never recompile: Stage 2 scores the candidates in the smallest of a few
power-of-two batches that holds them (`stage2_min_slots` up to `max_stage2_candidates`, padded and
masked; the first plan compiles every size) on `scene_cloud.max_points` scene points (voxel grid + seeded uniform subsample,
padded and masked, made as the labelling pipeline makes it: `pointcloud.scene_cloud`). Stage 1 runs
objects in batches of the sizes in `stage1_batch_sizes` (default 1, 2, 4: 10 objects = 4 + 4 + 2), so
at most that many Stage-1 shapes are ever compiled. Over the plans of one scene, a `Stage1Memory`
passed to `plan` keeps each object's Stage-1 result while its cloud does not change: only filter (iv)
runs again on it (`Stage1.rescene`), and Stage 1 proper runs on the objects that did change, often one
or two. When Stage 1 yields more candidates than Stage 2 takes, every object keeps its best-matched
ones: candidates are taken round-robin over objects in match order (rank 0 of every object, then
rank 1, ...) up to the budget (`stage2_subset`).

Everything is deterministic for a seed. Bad input (wrong shapes, NaN, mismatched labels, an empty
cloud) raises ValueError naming the problem; a scene in which nothing can be grasped (no object with
`min_object_points` points, no candidate, no score above the thresholds) gives a Plan with
kind None and the reason.
"""

from __future__ import annotations

import dataclasses
import functools
import time
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx

from sgjax.stage2 import ernet
from sgjax.geometry import gripper, pointcloud
from sgjax.geometry.gripper import GripperSpec
from sgjax.stage1.database import PrimitiveDB
from sgjax.utils import exported
from sgjax.utils.cache import enable_compilation_cache
from sgjax.stage1.filters import FilterConfig
from sgjax.stage1.fit_grasps import FitGraspConfig
from sgjax.stage1.matching import MatchConfig
from sgjax.stage1.memory import Stage1Memory
from sgjax.stage1 import neighbours
from sgjax.stage1.neighbours import NeighbourFitConfig
from sgjax.stage1.pipeline import Candidates, Stage1, Stage1Config
from sgjax.stage2.scene_cloud import SceneCloudConfig


KIND_NONE, KIND_EVALUATED, KIND_REFINED = 0, 1, 2
KIND_NAMES = {KIND_NONE: None, KIND_EVALUATED: "evaluated", KIND_REFINED: "refined"}


def check_thresholds(config) -> None:
    """Raise ValueError unless config.eval_threshold and config.refine_threshold lie in [0, 1)."""
    for name in ("eval_threshold", "refine_threshold"):
        if not 0.0 <= getattr(config, name) < 1.0:
            raise ValueError(f"{name} must be in [0, 1), got {getattr(config, name)}")


# The second plan's coarse filter (`PlannerConfig.fallback_filter`): the filters beyond the paper's off
# (camera-ray shadows, hidden contacts judged by the fitted superquadric) and the paper's (ii) and (iii)
# loosened to 25 points and 30 degrees, for the objects the default filters starve; E-RNet judges what it
# lets through. On the benchmark (docs/benchmark.md, "Refined poses checked, and a second plan ...") it
# raised TSR on every setting (seen-10 93.3 -> 98.7, seen-20 86.9 -> 93.5, unseen-10 90.5 -> 93.5, held-out
# seen-10 seed 1 93.0 -> 96.0) for 0.3-1.2 GSR points on seen objects and 4.7 on unseen ones.
FALLBACK_FILTER = FilterConfig(shadow_depth=0.0, hidden_contacts="accept", max_normal_angle_deg=30.0, min_points=25)


@dataclasses.dataclass(frozen=True)
class RobustChoice:
    """`PlannerConfig.robust`: execute, among the `top` best-evaluated passing candidates, the one whose
    score holds up when the hand lands a little off: E-RNet judges each at five perturbed poses
    (`gripper.perturbed_poses`: `shift` metres either way along the finger width and backed out along
    the approach, `angle_deg` either way about the approach axis), and the candidate with the highest mean
    of its own and those five scores is executed (ties: the better evaluated). Why: the best of hundreds of
    scores is the one most likely over-estimated, and a grasp at the edge of the object (held by a tip,
    far off its middle) loses its score when moved by millimetres."""

    top: int = 12
    shift: float = 0.005
    angle_deg: float = 10.0
    # Also a pose's collisions: a perturbed pose whose hand meets another object's fitted superquadric
    # (`PlannerConfig.neighbour_fits`, where the plan tests them) counts 0, as E-RNet's crop shows only
    # the neighbours' observed sides. False (default): E-RNet's scores alone; the test measured worse in
    # dense clutter (more collisions, not fewer: docs/benchmark.md).
    fits: bool = False
    # Also a bar: a judged candidate's mean must pass the evaluation threshold too, and a lone passing
    # candidate is judged as well. A candidate that fails takes its mean as its evaluation (it no
    # longer passes; refinement and the second plan see it so), and the choice is made again. Why: on
    # identical dense states (`eval.counterfactual`), grasps executed when only one candidate passed
    # succeeded 61 % of the time against 92 % when several were compared. False (default): measured, it
    # trades TSR for GSR in dense clutter (89.6 / 86.7 % against 87.7 / 91.1 %, docs/benchmark.md), as
    # the grasps it refuses were the only ones offered on the objects left.
    must_pass: bool = False
    # Also a preference (metres; 0: off): the judged candidates whose hand clears the observed obstacles
    # (filter (iv), its shadows included, with the hand boxes grown by this margin) and the neighbours'
    # fitted superquadrics (where the plan tests them, grown by this margin) are chosen from first; the
    # robust mean decides among them, and among all when none or all are clear. Why: as a filter, a 5 mm
    # obstacle margin removed most approach collisions but starved objects whose every grasp passes
    # closer (TSR -6 to -10 points, docs/benchmark.md); among candidates that passed anyway it removes
    # no object's last grasp. Off: on identical dense states 5 mm turned 8 of 11 approach collisions into
    # successes and 21 successes into drops (the clear grasps lie away from the object's middle).
    prefer_clearance: float = 0.0

    def __post_init__(self):
        if self.top < 2:
            raise ValueError(f"RobustChoice.top must be >= 2 (the candidates compared), got {self.top}")
        if not (np.isfinite(self.shift) and 0.0 <= self.shift <= 0.05):
            raise ValueError(f"RobustChoice.shift must be in [0, 0.05] metres, got {self.shift}")
        if not (np.isfinite(self.angle_deg) and 0.0 <= self.angle_deg < 90.0):
            raise ValueError(f"RobustChoice.angle_deg must be in [0, 90), got {self.angle_deg}")
        if not (np.isfinite(self.prefer_clearance) and 0.0 <= self.prefer_clearance <= 0.05):
            raise ValueError(f"RobustChoice.prefer_clearance must be in [0, 0.05] metres, got {self.prefer_clearance}")

    @property
    def rows(self) -> int:
        """Stage-2 rows of one robustness call: `top` candidates x 5 perturbations."""
        return self.top * PERTURBATIONS


PERTURBATIONS = 5  # poses per candidate from `gripper.perturbed_poses`
UNCOMPARED = ("lone", "refined")  # `PlannerConfig.fallback_for`: choices made without a comparison


@dataclasses.dataclass(frozen=True)
class PlannerConfig:
    """Planner settings (hashable).

    stage1: Stage-1 settings (fit, matching, coarse filter, gripper spec; the spec is also Stage 2's).
    eval_threshold, refine_threshold: the paper's 0.7 (a score must exceed it).
    use_refinement: False = the paper's "w/o RNet" ablation (evaluated grasps only).
    refine_rescore: when no candidate's evaluation passes, the refine head's best `refine_rescore`
        proposals (candidate, variant) are scored again: E-RNet evaluates the enlarged region at each
        refined pose, and a refinement's score becomes the geometric mean of its refine-head score and
        that evaluation (one more Stage-2 call, on the smallest Stage-2 batch that holds them). Why: the
        planner refines only the leftovers no evaluation passes, best of many, where the refine head alone
        is over-confident (on the benchmark 64 % of its refinements succeeded, against 93 % of evaluated
        grasps); on labelled scenes no model was trained on (mix-v5, evaluation <= 0.7) the geometric mean
        ranks refinements better (AUC 0.935 vs 0.917) and those above 0.7 succeed 90 % vs 85 % at about
        the same count (docs/stage2.md). 0: the paper's rule, the refine head alone. Default 64.
    max_stage2_candidates: the largest Stage-2 batch; more candidates -> each object's best-matched first
        (round-robin over objects in match order).
    stage2_min_slots: Stage 2 scores the candidates in the smallest power-of-two batch of at least this
        many slots that holds them (up to max_stage2_candidates): a scene with 60 candidates costs a
        64-slot E-RNet call, not a 512-slot one. Each candidate's scores do not depend on the batch size.
        The first plan compiles every size not yet in the cache, so later plans never stall on a compile
        (a cached size is loaded, ~0.3 s, when first used). max_stage2_candidates: one size.
    min_object_points: objects with fewer visible points are skipped (the reason is recorded).
    scene_cloud: the Stage-2 scene cloud (`SceneCloudConfig`: optional crop, voxel grid, seeded
        uniform subsample to a fixed size, padded and masked), made as in labelling so that E-RNet
        sees the point density it was trained on (`envs.scene.stage2_scene_cloud` gives the
        benchmark's, with its workspace crop).
    support_plane: the table as (nx, ny, nz, d), free space n . x + d > 0, for Stage 1's filter (v)
        (grippers reaching below the table); None: no such filter (e.g. camera-frame clouds).
    stage1_batch_sizes: Stage-1 batch sizes (objects per call): objects run in chunks of the largest
        size that fits those left, the smallest size padded when none fits, so at most one compile per
        size is ever made. Default (1, 2, 4): with a memory, most plans run Stage 1 on one to three
        changed objects, which a single size 4 would pad to four (docs/stage1.md: with the memory, Stage 1
        per plan in the harness took 0.38x the time of the code before it). Each size compiles when
        first used (then cached on disk).
    avoid_distance, avoid_angle_deg: a Stage-1 candidate this close to a pose passed as `avoid` (e.g. a
        grasp that already failed) is left out before Stage 2 (`gripper.near_grasps`).
    fallback_filter: when a plan finds no grasp (Stage 1 keeps no candidate, or E-RNet passes none),
        plan once more with Stage 1's coarse filter set to this, and let E-RNet judge what it lets
        through; `Plan.fallback` says when that plan was executed. Default `FALLBACK_FILTER` (looser);
        None: no second plan (the paper's planner).
    fallback_for: the first plan's uncompared choices for which the second plan runs as well: "lone" (an
        evaluated choice with a single passing candidate, nothing to compare it with) and "refined" (no
        evaluation passes; a refinement). The second plan's choice replaces the first's when it is an
        evaluated one among two or more passing candidates (its candidates include the first's, as its
        filters are looser, so it compares the first plan's grasp with others); otherwise the first
        plan's stands. Why: in dense clutter of unseen objects the grasps executed without a comparison
        succeeded 61 % (lone) and 71 % (refined) of the time against 92 % when several were compared
        (`eval.counterfactual`, docs/benchmark.md). Measured on identical dense states it did worse (the
        second plan's extra candidates are the ones the first plan's filters removed: 5 failures became
        successes and 9 successes failures; docs/benchmark.md, "A planner's change on identical states").
        () (default): the second plan only when the first finds nothing. Needs a fallback_filter.
    fallback_match: the second plan's matching (`MatchConfig`), None: the first plan's (`stage1.match`).
        E.g. `MatchConfig(relabel_extra=5)`: when nothing was found, also match the fitted
        superquadric's other axis labellings, for flat objects whose single-view fit names its axes so
        that the database's matching shape ranks low (docs/benchmark.md). Used only with a fallback_filter.
    fit_grasps: Stage 1 also offers top-down grasps on each object's fitted superquadric
        (`sgjax.stage1.fit_grasps`: across its two horizontal axes, centred on it, fingertips halfway
        between the table and its centre), ahead of the transferred ones, filtered (all but the normal
        test) and judged by E-RNet like them; in both plans, or only in the second
        (`FitGraspConfig.first_plan=False`). Why: single views of flat objects lying on the table whose
        fit names its axes so that no matched primitive's template closes low enough got no working
        grasp (a lens-like object was most of unseen-10's unfinished objects), and where E-RNet judges
        both, taking the better of the two kinds raised GSR on every setting (docs/benchmark.md, "Grasps
        on the fit itself"). None: the paper's candidates only. Default `FitGraspConfig()`.
    neighbour_fits: after Stage 1, remove every candidate whose hand (fingers and palm, swept back over
        the approach) meets another object's fitted superquadric grown by its margin
        (`sgjax.stage1.neighbours`: the sides of neighbours the camera did not see, which filter (iv)
        cannot test); refined poses are checked against them too. In the second plan as a preference
        (`NeighbourFitConfig.in_fallback`, default "prefer": the candidates clear of the fits first, all
        of them when those give no grasp). None: off (the paper's filters). Default
        `NeighbourFitConfig()` (2 mm): see docs/benchmark.md, "Neighbours' hidden sides".
    lever_weight: on the object of the best-evaluated candidate, execute the passing candidate (eval_prob
        above `eval_threshold`) with the highest eval_prob - lever_weight * lever arm
        (`gripper.lever_arm`: metres from the closing line to the object's visible centroid along the
        finger width), not simply the highest eval_prob. E-RNet sees a crop around the fingers, not
        where the rest of the object's weight lies; grasps held far off it drop more often under the
        disturbance (docs/benchmark.md, "The lever arm"). Which object is grasped, and refinements, are
        chosen as without it. 0 (default): the paper's choice.
    robust: among the best-evaluated passing candidates, execute the one whose E-RNet score holds up at
        small perturbations of its pose (`RobustChoice`: the 12 best, each judged at 5 poses moved by 5 mm
        or turned by 10 deg, in one more Stage-2 call on the smallest batch). Why: the highest of hundreds
        of scores is the one most likely over-estimated; in dense clutter of unseen objects this choice
        dropped 43 objects where the highest score dropped 65 (40 scenes: GSR 90.7 % against 88.6 %, TSR
        92.6 % against 90.2 %) and on every other setting it moved GSR and TSR by less than a scene's worth
        (docs/benchmark.md, "A choice that holds up"). None: the paper's choice, the highest evaluation.
        Default `RobustChoice()`.
    failed_last: after a failed grasp, the other objects first. Each pose in `avoid` (the grasps that
        failed so far) counts against the object it was on: the object with an observed point nearest its
        closing region's centre, if within `failed_last` metres. The evaluated choice (and the robust
        choice's candidates) is made among the objects with the fewest such failures that have a passing
        candidate; an object that failed is grasped again once no other object has a passing grasp. Why
        it was tried: in dense clutter of unseen objects the planner went straight back to the object it
        had just failed on in 48 of 107 failures, and those retries failed 29 % of the time against 13 %
        for all grasps. Measured over 70 dense-clutter scenes it did not help (GSR 88.6 % against 88.8 %,
        TSR up a little; docs/benchmark.md, "The other objects first after a failed grasp"), so it is off.
        Refinements (no evaluated candidate passes) are chosen as without it. None (default): the paper's
        choice over all objects.
    prefer_fit_grasps: the evaluated choice (and the robust choice's candidates) is made among the passing
        grasps on the objects' fits (`fit_grasps`) when any passes, and among all candidates otherwise.
        Why: where E-RNet passed both kinds, the fit's grasps it executed succeeded far more often than
        the transferred ones (dense clutter of unseen objects, 70 scenes: 98.4 % of 191 against 88.1 % of
        1,218; unseen-10 98.4 % against 93.1 %; seen-20 99.1 % against 94.1 %): centred on the object,
        straight down, below its widest section, they hold where a template at an end twists out under the
        disturbance, and E-RNet's scores do not tell the two apart. False (default): E-RNet's order alone;
        measured, the preference moved the failures rather than removing them (dense unseen 70 scenes
        GSR 90.6 / TSR 89.5 % against 89.5 / 91.4 %, seen-20 -5 GSR points on 12 scenes; docs/benchmark.md).
        "second": only in the second plan (`fallback_filter`), whose transferred grasps are the marginal
        ones (dense unseen, 70 scenes: the second plan's transferred grasps succeeded 69 % of 112, its
        fit's grasps 7 of 7), while the first plan's choice stays E-RNet's; measured, it lost a little (dense
        unseen 70 scenes GSR 89.2 / TSR 91.1 % against 89.5 / 91.4 %; docs/benchmark.md, "The second
        plan's grasps and the neighbours' fits").
    reuse_tolerance: with a `Stage1Memory` passed to `plan`, an object whose cloud is the same as when
        Stage 1 last ran on it, within this many metres (`pointcloud.same_cloud`), keeps those candidates
        and is only tested against the obstacles of now (`Stage1.rescene`). 0: only identical clouds.
        Without a memory, Stage 1 runs afresh on every object. Default 0.5 mm: between two attempts of a
        decluttering scene an untouched object's cloud moves by a median 0.14 mm (re-settling), a nudged
        one by millimetres; on seen-10 (N = 30) 0.5 mm kept GSR / TSR at those of no memory (97.0 / 98.3
        against 97.4 / 99.0) with 3.8 objects per plan from memory, while 2 mm let stale grasps of nudged
        objects through (94.2 / 97.7). A real camera's noise is larger: set it to the noise level there.
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
    fallback_match: MatchConfig | None = None
    fallback_for: tuple[str, ...] = ()
    fit_grasps: FitGraspConfig | None = FitGraspConfig()
    reuse_tolerance: float = 0.0005
    neighbour_fits: NeighbourFitConfig | None = NeighbourFitConfig()
    lever_weight: float = 0.0
    robust: RobustChoice | None = RobustChoice()
    failed_last: float | None = None
    prefer_fit_grasps: bool | str = False

    @property
    def first_stage1(self) -> Stage1Config:
        """The first plan's Stage-1 config: `stage1`, with `fit_grasps` when they are in the first plan."""
        if self.fit_grasps is None or not self.fit_grasps.first_plan:
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
        if not (np.isfinite(self.lever_weight) and self.lever_weight >= 0):
            raise ValueError(f"lever_weight must be a finite number >= 0 (per metre), got {self.lever_weight}")
        if self.failed_last is not None and not (np.isfinite(self.failed_last) and self.failed_last > 0):
            raise ValueError(f"failed_last must be None or a finite distance > 0 (metres), got {self.failed_last}")
        if self.robust is not None and self.robust.rows > self.max_stage2_candidates:
            raise ValueError(f"robust.top x {PERTURBATIONS} = {self.robust.rows} perturbed poses exceed "
                             f"max_stage2_candidates={self.max_stage2_candidates}")
        if self.prefer_fit_grasps not in (False, True, "second"):
            raise ValueError(f"prefer_fit_grasps must be False, True or 'second', got {self.prefer_fit_grasps!r}")
        if self.prefer_fit_grasps != "second":
            object.__setattr__(self, "prefer_fit_grasps", bool(self.prefer_fit_grasps))
        object.__setattr__(self, "fallback_for", tuple(self.fallback_for))
        unknown = set(self.fallback_for) - set(UNCOMPARED)
        if unknown:
            raise ValueError(f"fallback_for takes {', '.join(map(repr, UNCOMPARED))}, got {sorted(unknown)}")
        if self.fallback_for and self.fallback_filter is None:
            raise ValueError("fallback_for says when the second plan also runs: it needs a fallback_filter (the second plan)")
        if self.fallback_match is not None and self.fallback_filter is None:
            raise ValueError("fallback_match is the second plan's matching: it needs a fallback_filter (the second plan)")
        check_thresholds(self)

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
    score: its refine prob, or with `refine_rescore` the geometric mean of that and its pose's eval prob), kind "evaluated" | "refined" | None (no grasp), refine_variant 0..K-1 when refined,
    candidate_index (row of the `scores` arrays), reason (why no grasp, else None), n_candidates
    (Stage-1 candidates over all objects), timing {"stage1_s", "stage2_s", "total_s", "compiled"}
    (wall seconds of this call; "compiled" says whether it included a compilation), candidates (per
    planned object: stage1.Candidates), scores (NumPy over the M scored candidates: eval_prob [M],
    refine_prob [M, K], valid [M], target [M] label, object [M] index into `candidates`,
    object_candidate [M] row in that Candidates; with `refine_rescore`, when it ran: refine_score [M, K],
    the refinements' scores the policy used, 0 where not re-scored; with `robust`, when it ran: robust_score [M] and
    perturbed_score [M, 5], NaN where not judged), initial_pose [4, 4] (the chosen Stage-1 candidate,
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


# ---------------------------------------------------------------------------------------------
# The decision policy (paper Sec. IV-E).


def decide(eval_prob, refine_prob, valid, eval_threshold=0.7, refine_threshold=0.7, use_refinement=True):
    """The paper's decision over M scored candidates; pure jnp and jittable (thresholds may be traced).

    eval_prob [M], refine_prob [M, K], valid bool[M] (invalid candidates are never chosen; NaN scores
    count as invalid) -> (index int32, kind int32 (0 none, 1 evaluated, 2 refined), variant int32,
    score float32), each a scalar. Execute the best-evaluated candidate when its score exceeds
    `eval_threshold`; else, if `use_refinement` and the best refinement score over all candidates and
    variants exceeds `refine_threshold`, refine that candidate with that variant; else none. Index and
    variant are -1 where they do not apply; for "none" the score is the best valid eval prob (0 if none).
    Ties go to the lowest index.
    """
    eval_prob = jnp.asarray(eval_prob, jnp.float32)
    refine_prob = jnp.asarray(refine_prob, jnp.float32)
    valid = jnp.asarray(valid, bool)
    if eval_prob.ndim != 1 or refine_prob.ndim != 2 or refine_prob.shape[0] != eval_prob.shape[0]:
        raise ValueError(f"need eval_prob [M] and refine_prob [M, K], got {eval_prob.shape} and {refine_prob.shape}")
    if valid.shape != eval_prob.shape:
        raise ValueError(f"valid must have shape {eval_prob.shape}, got {valid.shape}")
    m, k = refine_prob.shape
    minus_one = jnp.int32(-1)
    if m == 0:
        return minus_one, jnp.int32(KIND_NONE), minus_one, jnp.float32(0.0)
    valid = valid & jnp.isfinite(eval_prob) & jnp.all(jnp.isfinite(refine_prob), -1)
    e = jnp.where(valid, eval_prob, -jnp.inf)
    best = jnp.argmax(e).astype(jnp.int32)
    best_eval = e[best]
    take_eval = best_eval > eval_threshold
    if k:
        r = jnp.where(valid[:, None], refine_prob, -jnp.inf).reshape(-1)
        flat = jnp.argmax(r).astype(jnp.int32)
        take_refine = ~take_eval & jnp.asarray(use_refinement, bool) & (r[flat] > refine_threshold)
        refine_index, refine_variant, refine_score = flat // k, flat % k, r[flat]
    else:
        take_refine, refine_index, refine_variant, refine_score = jnp.bool_(False), minus_one, minus_one, jnp.float32(0)
    kind = jnp.where(take_eval, KIND_EVALUATED, jnp.where(take_refine, KIND_REFINED, KIND_NONE)).astype(jnp.int32)
    index = jnp.where(take_eval, best, jnp.where(take_refine, refine_index, minus_one))
    variant = jnp.where(take_refine, refine_variant, minus_one)
    score = jnp.where(take_refine, refine_score, jnp.where(jnp.isfinite(best_eval), best_eval, 0.0))
    return index, kind, variant, score.astype(jnp.float32)


def rescored_refinement(refine_prob, judged):
    """A refinement's score under `PlannerConfig.refine_rescore`: the geometric mean of the refine head's
    score and the evaluation head's score of the refined pose (each in [0, 1], any equal shapes): high
    only when both heads agree."""
    return np.sqrt(np.asarray(refine_prob, np.float32) * np.asarray(judged, np.float32))


_jitted_decide = jax.jit(decide)


def refine_proposals(refine_prob, valid, count: int) -> tuple[np.ndarray, np.ndarray]:
    """The refine head's best `count` proposals: refine_prob [M, K], valid [M] -> (index [n], variant [n]),
    n <= count, best first (ties: lowest candidate, then variant), only valid candidates and scores > 0."""
    head = np.where(np.asarray(valid, bool)[:, None], np.asarray(refine_prob, np.float32), -1.0)
    k = head.shape[1]
    flat = np.argsort(-head.reshape(-1), kind="stable")[:count]
    flat = flat[head.reshape(-1)[flat] > 0]
    return flat // k, flat % k


def padded_batch(poses, widths, slots: int) -> tuple[np.ndarray, np.ndarray]:
    """Candidates poses [n, 4, 4], widths [n] padded to a Stage-2 batch of `slots` rows (identity poses,
    NaN widths: invalid for E-RNet, and masked) -> (poses [slots, 4, 4] f32, widths [slots] f32)."""
    n = len(widths)
    padded_poses = np.tile(np.eye(4, dtype=np.float32), (slots, 1, 1))
    padded_widths = np.full(slots, np.nan, np.float32)
    padded_poses[:n], padded_widths[:n] = poses, widths
    return padded_poses, padded_widths


def padded_refinements(poses, widths, index, variant, slots: int, spec: GripperSpec) -> tuple[np.ndarray, np.ndarray]:
    """The refined poses of proposals (index [n], variant [n]) of candidates poses [M, 4, 4], widths [M],
    padded to `slots` rows so that the Stage-2 call that judges them has a shape it already compiled
    (row 0 fills the padding, its width NaN: invalid for E-RNet) -> (poses [slots, 4, 4] f32, widths [slots] f32)."""
    n = len(index)
    pad_index, pad_variant = np.zeros(slots, np.int64), np.zeros(slots, np.int64)
    pad_index[:n], pad_variant[:n] = index, variant
    refined = np.asarray(gripper.refined_pose(np.asarray(poses)[pad_index], pad_variant, spec), np.float32)
    return refined, np.where(np.arange(slots) < n, np.asarray(widths)[pad_index], np.nan).astype(np.float32)


def rescored_refinements(refine_prob, valid, count: int, judge) -> np.ndarray:
    """The refinements' scores under `PlannerConfig.refine_rescore`: the refine head's best `count`
    proposals each judged at its refined pose, `judge(index [n], variant [n])` -> the evaluation head's
    score there [n] (0 where it cannot judge), combined by `rescored_refinement` -> [M, K] (0 where not
    re-scored). Shared by the planner and the `gpd+s2` baseline: one Stage-2 policy for any candidates."""
    refine_prob = np.asarray(refine_prob, np.float32)
    index, variant = refine_proposals(refine_prob, valid, count)
    score = np.zeros_like(refine_prob)
    if len(index):
        score[index, variant] = rescored_refinement(refine_prob[index, variant], judge(index, variant))
    return score


def collision_free(choice: dict, eval_prob, refine_score, valid, collides, decide_again) -> tuple[dict, int]:
    """The policy's choice with every refined pose it would execute checked first: while the choice is a
    refinement, `collides(index)` -> (hits bool [K], poses [K, 4, 4], moved bool [K]) tests all the
    variants of candidate `index` (poses: as they would be executed; moved: those that differ from the
    plain refined pose, e.g. backed off the table); a chosen variant that hits is left out (its score
    set to 0, which no threshold in [0, 1) passes) and `decide_again(eval_prob, refine_score, valid)`
    decides once more. -> (choice with "pose" the refined pose to execute: the tested one where moved
    or where the choice has none, else the choice's own; refined poses left out)."""
    refine_score = np.array(refine_score, np.float32)
    rejected = 0
    while int(choice["kind"]) == KIND_REFINED:
        index, variant = int(choice["index"]), int(choice["variant"])
        hits, poses, moved = collides(index)
        if not hits[variant]:
            keep = choice.get("pose") is not None and not moved[variant]
            return {**choice, "pose": choice["pose"] if keep else poses[variant]}, rejected
        rejected += 1
        refine_score[index, hits] = 0.0
        choice = decide_again(eval_prob, refine_score, valid)
    return choice, rejected


def select_grasp(
    poses,
    widths,
    eval_prob,
    refine_prob,
    valid,
    eval_threshold=0.7,
    refine_threshold=0.7,
    use_refinement=True,
    spec: GripperSpec = ernet.DEFAULT_SPEC,
) -> dict[str, jax.Array]:
    """`decide`, then the pose to execute: poses [M, 4, 4], widths [M] and the scores of `decide` ->
    {"index", "kind", "variant", "score", "pose" [4, 4], "initial_pose" [4, 4], "width"}. "pose" is
    `gripper.refined_pose(poses[index], variant, spec)` when refined, poses[index] when evaluated
    (meaningless when kind is 0). Pure jnp, jittable."""
    index, kind, variant, score = decide(eval_prob, refine_prob, valid, eval_threshold, refine_threshold, use_refinement)
    poses = jnp.asarray(poses, jnp.float32)
    safe = jnp.maximum(index, 0)
    initial = poses[safe]
    refined = gripper.refined_pose(initial, jnp.maximum(variant, 0), spec)
    pose = jnp.where(kind == KIND_REFINED, refined, initial)
    return {
        "index": index,
        "kind": kind,
        "variant": variant,
        "score": score,
        "pose": pose,
        "initial_pose": initial,
        "width": jnp.asarray(widths, jnp.float32)[safe],
    }


def _stage2(graphdef, state, scene, scene_mask, poses, widths, slots, key, thresholds, use_refinement, *, spec):
    """One compiled Stage 2: E-RNet scores of the candidate slots (scene [S, 3] + mask, poses [C, 4, 4],
    widths [C], slots bool[C]) and the decision."""
    scores = ernet.score(graphdef, state, scene, poses, widths, scene_mask, spec=spec, key=key)
    valid = scores.valid & slots
    choice = select_grasp(
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


# ---------------------------------------------------------------------------------------------
# The planner.


class Planner:
    """Stage 1 + Stage 2 with the database and the E-RNet weights on the device.

    model: an ERNet, a `sgjax train` run directory, or None (the shipped default, `ernet.load_default_model`);
    db: a PrimitiveDB, or None (the default database from the cache, built on first use).
    judge: None, "paper" (the shipped paper-size E-RNet, `ernet.load_paper_model`), or a second ERNet or
        run directory, that makes the robust choice (`PlannerConfig.robust`, required): `model` scores
        every candidate, and among its `robust.top` best the judge's mean score at the candidate's own
        pose and its perturbed ones picks the grasp. Why: a network too slow to score hundreds of
        candidates on a CPU (the paper-size E-RNet: seconds per 512) judges a dozen finalists in one
        call of 72 rows. Measured in dense clutter of unseen objects: more objects removed, GSR no
        better (docs/benchmark.md, "The paper-size E-RNet as a judge"), so None is the default.
    """

    def __init__(self, model=None, db: PrimitiveDB | None = None, config: PlannerConfig = PlannerConfig(), judge=None):
        enable_compilation_cache()  # a new process loads what an earlier one compiled
        self.model = ernet.as_model(model)
        self.config = config
        self.judge = None
        if judge is not None:
            if config.robust is None:
                raise ValueError("a judge network makes the robust choice: PlannerConfig.robust must not be None")
            if config.robust.top * (PERTURBATIONS + 1) > config.max_stage2_candidates:
                raise ValueError(f"robust.top x {PERTURBATIONS + 1} judged poses exceed max_stage2_candidates "
                                 f"{config.max_stage2_candidates}")
            self.judge = ernet.as_judge(judge)
            graphdef, state = nnx.split(self.judge)
            self._judge_network = (graphdef, jax.device_put(state, jax.devices()[0]))
        if self.model.config.n_refinements != config.spec.num_refinements:
            raise ValueError(
                f"the E-RNet predicts {self.model.config.n_refinements} refinements but the gripper spec has "
                f"{config.spec.num_refinements}"
            )
        self.stage1 = Stage1(db, config.first_stage1)
        self._fallback_stages: dict[Stage1Config, Stage1] = {}  # by config: `config` may be replaced later
        self._margin_stages: dict[Stage1Config, Stage1] = {}  # `RobustChoice.prefer_clearance`: by config
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
        cfg = self.config
        plan = self._run_with(self.stage1, scene, objects, skipped, view, seed, start, avoid, memory)
        again = not plan.ok or (bool(cfg.fallback_for) and uncompared(plan, cfg.eval_threshold) in cfg.fallback_for)
        fallback = self._fallback_stage() if again else None
        if fallback is None:
            return plan
        fits = cfg.neighbour_fits is not None and cfg.neighbour_fits.in_fallback
        second = self._run_with(fallback, scene, objects, skipped, view, seed, start, avoid, memory, fits, second=True)
        second.reused += plan.reused
        # After a grasp the first plan found: only a compared choice replaces it.
        if second.ok and (not plan.ok or uncompared(second, cfg.eval_threshold) is None):
            second.fallback = True
            return second
        if not plan.ok:
            plan.reason = f"{plan.reason}; with the fallback filter: {second.reason}"
        plan.timing = second.timing  # from the same start: both plans
        return plan

    def _fallback_stage(self) -> Stage1 | None:
        """Stage 1 with `config.fallback_filter` (and `fallback_match` when set; built once per Stage-1
        config), or None without a fallback filter."""
        cfg = self.config
        if cfg.fallback_filter is None:
            return None
        stage_cfg = dataclasses.replace(cfg.stage1, filter=cfg.fallback_filter, match=cfg.fallback_match or cfg.stage1.match,
                                        fit_grasps=cfg.fit_grasps)
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
                  fits: bool | str = True, second: bool = False) -> Plan:
        """One plan with this Stage 1; fits: whether the neighbours' fits are obstacles (`neighbour_fits`):
        True, False, or "prefer" (the candidates that pass the test first; all of them when those give
        no grasp, `NeighbourFitConfig.in_fallback`); second: this is the second plan (`fallback_filter`)."""
        prefer_fit = self.config.prefer_fit_grasps is True or (second and self.config.prefer_fit_grasps == "second")
        compiled = _compile_count()
        candidates, reused = self._stage1(stage1, objects, view, seed, memory)
        if not fits or self.config.neighbour_fits is None:
            plan = self._choose(stage1, scene, objects, skipped, view, seed, start, avoid, candidates, compiled,
                                prefer_fit=prefer_fit)
        else:
            clear, fitted = self._without_fit_collisions(stage1, candidates, objects, seed)
            plan = self._choose(stage1, scene, objects, skipped, view, seed, start, avoid, clear, compiled, fitted,
                                prefer_fit=prefer_fit)
            if fits == "prefer" and not plan.ok and sum(map(len, clear)) < sum(map(len, candidates)):
                # What the test removed may be all there is: plan as without it rather than find nothing.
                plan = self._choose(stage1, scene, objects, skipped, view, seed, start, avoid, candidates, compiled,
                                prefer_fit=prefer_fit)
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
                fitted: tuple | None = None, prefer_fit: bool = False) -> Plan:
        """Stage 2 and the decision on Stage 1's candidates (one Candidates per object); prefer_fit: the
        passing grasps on the fits first (`PlannerConfig.prefer_fit_grasps`, in this plan)."""
        cfg = self.config
        labels = [label for label, _, _ in objects]
        t1 = time.perf_counter()
        infos = sorted(
            skipped + [{"label": lab, "points": len(o), "candidates": len(c), "reason": c.reason}
                       for (lab, o, _), c in zip(objects, candidates)],
            key=lambda d: d["label"],
        )
        n_candidates = sum(len(c) for c in candidates)
        if n_candidates == 0:
            detail = "; ".join(f"object {lab}: {c.reason}" for lab, c in zip(labels, candidates))
            timing = {"stage1_s": t1 - start, "stage2_s": 0.0, "total_s": t1 - start, "compiled": _compile_count() != compiled}
            return self._empty(f"no candidates: {detail}", infos, start, candidates, timing)

        kept = self._kept(candidates, avoid)
        if not sum(len(k) for k in kept):
            timing = {"stage1_s": t1 - start, "stage2_s": 0.0, "total_s": t1 - start, "compiled": _compile_count() != compiled}
            reason = (f"all {n_candidates} candidates are within {cfg.avoid_distance:g} m and {cfg.avoid_angle_deg:g} deg "
                      f"of the {len(avoid)} pose(s) to avoid")
            return self._empty(reason, infos, start, candidates, timing)
        obj, rank = stage2_subset([len(k) for k in kept], cfg.max_stage2_candidates)
        row = np.asarray([kept[o][r] for o, r in zip(obj, rank)], np.int64).reshape(-1)
        m = len(obj)
        slots = cfg.stage2_slots(m)
        offsets = np.cumsum([0] + [len(c) for c in candidates])[:-1]
        poses, widths = padded_batch(np.concatenate([c.poses for c in candidates])[offsets[obj] + row],
                                     np.concatenate([c.widths for c in candidates])[offsets[obj] + row], slots)
        scene_pad, scene_mask = self._scene(scene, seed)
        thresholds = np.array([cfg.eval_threshold, cfg.refine_threshold], np.float32)
        if not self._stage2_ready:  # compile every batch size now, so that no later plan stalls
            # The judge network's sizes too, up to its largest robust call.
            largest = 0 if self.judge is None else cfg.stage2_slots(cfg.robust.top * (PERTURBATIONS + 1))
            for size in cfg.stage2_sizes:
                empty = padded_batch(np.zeros((0, 4, 4), np.float32), np.zeros(0, np.float32), size)
                args = (scene_pad, scene_mask, *empty, np.zeros(size, bool), seed, thresholds)
                # A size already exported to the cache is only loaded (~0.3 s) when first used: a warm
                # process's first plan then loads one Stage-2 program, not all of them.
                for judge in (False, True) if size <= largest else (False,):
                    if (judge or size != slots) and not exported.ready("stage2", *self._stage2_call(*args, judge)[1:]):
                        self._score(*args, judge)
                if cfg.use_refinement:  # the host-side decision of re-scored or rejected refinements, per size
                    self._decide(np.zeros(size, np.float32), np.zeros((size, cfg.spec.num_refinements), np.float32),
                                 np.zeros(size, bool))
            self._stage2_ready = True
        out, choice = self._score(scene_pad, scene_mask, poses, widths, np.arange(slots) < m, seed, thresholds)
        t2 = time.perf_counter()
        scores = {
            "eval_prob": out["eval_prob"][:m],
            "refine_prob": out["refine_prob"][:m],
            "valid": out["valid"][:m],
            "target": np.asarray(labels, np.int64)[obj],
            "object": obj,
            "object_candidate": row,
        }
        timing = {"stage1_s": t1 - start, "stage2_s": t2 - t1, "total_s": t2 - start, "compiled": _compile_count() != compiled}
        rejected = 0
        allowed = None  # the candidates the evaluated choice may take (None: all)
        if cfg.failed_last is not None and len(avoid) and int(choice["kind"]) == KIND_EVALUATED:
            clouds = [cloud for _, cloud, _ in objects]
            scores["failures"] = failure_counts(avoid, clouds, cfg.spec, cfg.failed_last)[obj]
            allowed = least_failed(scores["eval_prob"], scores["valid"], scores["failures"], cfg.eval_threshold)
            choice = evaluated_choice(choice, scores["eval_prob"], scores["valid"] & allowed, cfg.eval_threshold)
        if prefer_fit and int(choice["kind"]) == KIND_EVALUATED:
            on_fit = np.array([candidates[o].primitive_id[r] < 0 for o, r in zip(obj, row)], bool).reshape(-1)
            usable = scores["valid"] if allowed is None else scores["valid"] & allowed
            first = preferred_rows(scores["eval_prob"], usable, on_fit, cfg.eval_threshold)
            allowed = first if allowed is None else allowed & first
            choice = evaluated_choice(choice, scores["eval_prob"], scores["valid"] & allowed, cfg.eval_threshold)
        if cfg.lever_weight > 0 and int(choice["kind"]) == KIND_EVALUATED:
            centroids = np.stack([np.mean(cloud, axis=0) for _, cloud, _ in objects])[obj]
            choice = prefer_short_lever(choice, scores, poses[:m], centroids, cfg)
        if cfg.robust is not None and int(choice["kind"]) == KIND_EVALUATED:
            clear = None
            if cfg.robust.prefer_clearance > 0:
                clear = lambda index: self._clear(stage1, index, scores, objects, poses[:m], widths[:m], view, seed, fitted)
            choice = self._robust(choice, scores, poses[:m], widths[:m], scene_pad, scene_mask, seed, thresholds,
                                  fitted, stage1.config.filter.approach_clearance, allowed, clear)
            t2 = time.perf_counter()
            timing.update(stage2_s=t2 - t1, total_s=t2 - start, compiled=_compile_count() != compiled)
        if cfg.use_refinement and cfg.refine_rescore and int(choice["kind"]) != KIND_EVALUATED:
            choice = self._rescore(scores, poses[:m], widths[:m], scene_pad, scene_mask, seed, thresholds)
            t2 = time.perf_counter()
            timing.update(stage2_s=t2 - t1, total_s=t2 - start, compiled=_compile_count() != compiled)
        if int(choice["kind"]) == KIND_REFINED:
            choice, rejected = self._collision_free(stage1, choice, scores, objects, candidates, view, seed, fitted)
            t2 = time.perf_counter()
            timing.update(stage2_s=t2 - t1, total_s=t2 - start, compiled=_compile_count() != compiled)
        kind = int(choice["kind"])
        if kind == KIND_NONE:
            plan = self._empty(self._why_not(scores, m, rejected), infos, start, candidates, timing)
            plan.scores, plan.score, plan.refinements_rejected = scores, float(choice["score"]), rejected
            return plan
        index = int(choice["index"])
        initial = candidates[obj[index]].poses[row[index]]
        refined = kind == KIND_REFINED
        return Plan(
            pose=np.asarray(choice["pose"], np.float64) if refined else initial.copy(),
            width=float(candidates[obj[index]].widths[row[index]]),
            target=int(labels[obj[index]]),
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

    def _rescore(self, scores: dict, poses: np.ndarray, widths: np.ndarray, scene_pad, scene_mask, seed: int,
                 thresholds) -> dict:
        """The refinements judged again (`PlannerConfig.refine_rescore`, `rescored_refinements`): each of the
        refine head's best proposals scored by E-RNet's evaluation head at its refined pose, in one Stage-2
        call on the smallest batch that holds them. Adds scores["refine_score"] [M, K] (0 where not
        re-scored) and decides again on it -> choice."""
        cfg = self.config

        def judge(index, variant):
            n = len(index)
            slots = cfg.stage2_slots(n)  # a Stage-2 batch size, so that no plan compiles
            refined, refined_widths = padded_refinements(poses, widths, index, variant, slots, cfg.spec)
            out, _ = self._score(scene_pad, scene_mask, refined, refined_widths, np.arange(slots) < n, seed, thresholds)
            return np.where(out["valid"][:n], out["eval_prob"][:n], 0.0)

        scores["refine_score"] = rescored_refinements(scores["refine_prob"], scores["valid"], cfg.refine_rescore, judge)
        return self._decide(scores["eval_prob"], scores["refine_score"], scores["valid"])

    def _clear(self, stage1: Stage1, index: np.ndarray, scores: dict, objects: list, poses: np.ndarray,
               widths: np.ndarray, view, seed: int, fitted: tuple | None) -> np.ndarray:
        """`RobustChoice.prefer_clearance`: whether each candidate of rows index [t] clears the observed
        obstacles (this plan's Stage-1 filter (iv) with the margin, on the same crops) and the neighbours'
        fits `fitted` (when given) by the margin -> bool [t]."""
        cfg = self.config
        margin = cfg.robust.prefer_clearance
        wide = dataclasses.replace(stage1.config, filter=dataclasses.replace(stage1.config.filter, obstacle_margin=margin))
        if wide not in self._margin_stages:
            self._margin_stages[wide] = Stage1(self.stage1.db, wide, share=self.stage1)
        tester = self._margin_stages[wide]
        index = np.asarray(index, np.int64)
        owner = np.asarray(scores["object"], np.int64)[index]
        clear = np.ones(len(index), bool)
        for o in np.unique(owner):
            rows = owner == o
            _, cloud, obstacles = objects[o]
            # Object o's Stage-1 call cropped its obstacles with seed + o (`Stage1.chunked`): the same crop.
            found = tester.collisions(cloud, obstacles, poses[index[rows]], widths[index[rows]], view, seed + int(o),
                                      cfg.support_plane)
            clear[rows] = ~found["collision_scene"]
        if fitted is not None and cfg.neighbour_fits is not None:
            fits, mask, pairs = fitted
            grown = dataclasses.replace(cfg.neighbour_fits, margin=max(margin, cfg.neighbour_fits.margin))
            clear &= ~neighbours.fit_hits(poses[index], widths[index], owner.astype(np.int32), fits, mask, cfg.spec, grown,
                                          stage1.config.filter.approach_clearance, cfg.stage2_sizes, pairs)
        return clear

    def _robust(self, choice: dict, scores: dict, poses: np.ndarray, widths: np.ndarray, scene_pad, scene_mask,
                seed: int, thresholds, fitted: tuple | None = None, sweep: float = 0.0, allowed=None,
                clear=None) -> dict:
        """An evaluated choice made again with `PlannerConfig.robust`: the best-evaluated passing
        candidates judged at perturbed poses in one Stage-2 call (`robust_scores`); with
        `RobustChoice.fits` and the neighbours' fits `fitted` (`neighbours.obstacle_fits`), a perturbed
        pose whose hand meets one scores 0. allowed bool [M] or None: the candidates it may choose from
        (`PlannerConfig.failed_last`). Adds scores["robust_score"] [M] and scores["perturbed_score"] [M, P]
        (the judged scores at the P perturbed poses; NaN where not judged); clear: `RobustChoice.prefer_clearance`'s
        test, judged rows [t] -> bool [t] (adds scores["clear"] [M]) -> choice, score its eval_prob."""
        cfg = self.config
        test_fits = cfg.robust.fits and fitted is not None

        own = self.judge is None  # with a judge network, it also scores the candidate's own pose
        per = PERTURBATIONS + (0 if own else 1)

        def judge(index):
            perturbed = np.asarray(gripper.perturbed_poses(poses[index], cfg.robust.shift, cfg.robust.angle_deg), np.float32)
            if not own:
                perturbed = np.concatenate([np.asarray(poses[index], np.float32)[:, None], perturbed], axis=1)
            n = perturbed.shape[0] * per
            slots = cfg.stage2_slots(n)  # a Stage-2 batch size, so that no plan compiles
            pad_poses, pad_widths = padded_batch(perturbed.reshape(n, 4, 4), np.repeat(widths[index], per), slots)
            out, _ = self._score(scene_pad, scene_mask, pad_poses, pad_widths, np.arange(slots) < n, seed, thresholds,
                                 judge=not own)
            judged = np.where(out["valid"][:n], out["eval_prob"][:n], 0.0)
            if test_fits:
                fits, mask, pairs = fitted
                owner = np.repeat(np.asarray(scores["object"], np.int32)[index], per)
                hits = neighbours.fit_hits(pad_poses[:n], pad_widths[:n], owner, fits, mask, cfg.spec,
                                           cfg.neighbour_fits, sweep, cfg.stage2_sizes, pairs)
                judged = np.where(hits, 0.0, judged)
            judged = judged.reshape(-1, per)
            scores["perturbed_score"][index] = judged  # kept for whoever studies the choice (eval.counterfactual)
            return judged

        valid = scores["valid"] if allowed is None else scores["valid"] & allowed
        scores["perturbed_score"] = np.full((len(valid), per), np.nan, np.float32)
        scores["robust_score"] = robust_scores(scores["eval_prob"], valid, cfg.eval_threshold, cfg.robust.top, judge, own,
                                               minimum=1 if cfg.robust.must_pass else 2)
        if clear is not None:
            judged = np.flatnonzero(np.isfinite(scores["robust_score"]))
            scores["clear"] = np.zeros(len(valid), bool)
            if len(judged):
                scores["clear"][judged] = clear(judged)
            choice = robust_choice(choice, preferred(scores, scores["clear"]))
        else:
            choice = robust_choice(choice, scores)
        if not cfg.robust.must_pass:
            return choice
        decide = lambda e: self._decide(e, scores["refine_prob"], scores["valid"])
        judge_again = lambda e, judged: robust_scores(e, valid & ~judged, cfg.eval_threshold, cfg.robust.top, judge, own,
                                                      minimum=1)
        return passing_robust_choice(choice, scores, cfg.eval_threshold, decide, judge_again)

    def _decide(self, eval_prob: np.ndarray, refine_score: np.ndarray, valid: np.ndarray) -> dict:
        """`decide` on the host's scores [M], [M, K], [M], padded to the Stage-2 batch size that holds M so
        that it compiles once per batch size, not once per candidate count -> choice (pose None)."""
        cfg = self.config
        m = len(eval_prob)
        slots = cfg.stage2_slots(m)
        pad = lambda a, fill: np.concatenate([a, np.full((slots - m, *a.shape[1:]), fill, a.dtype)])
        index, kind, variant, best = (np.asarray(v) for v in _jitted_decide(
            pad(np.asarray(eval_prob, np.float32), 0.0), pad(np.asarray(refine_score, np.float32), 0.0),
            pad(np.asarray(valid, bool), False), np.float32(cfg.eval_threshold), np.float32(cfg.refine_threshold),
            np.bool_(cfg.use_refinement)))
        return {"index": index, "kind": kind, "variant": variant, "score": best, "pose": None}

    def _collision_free(self, stage1: Stage1, choice: dict, scores: dict, objects: list, candidates: list, view,
                        seed: int, fitted: tuple | None = None):
        """The policy's choice with every refined pose it would execute checked by Stage 1's obstacle and
        table tests first ((iv), (v) of `Stage1.collisions`, and the other objects' fitted superquadrics
        `fitted` when given, `neighbours.obstacle_fits`): Stage 1 checked each candidate's initial pose,
        but a refinement deepens and turns the hand, and E-RNet's crop does not show all the obstacles or
        the table. A refined pose that fails is left out and the policy decides again (another
        refinement, or none) (`collision_free`). -> (choice, refined poses left out)."""
        cfg = self.config

        def collides(index):
            o, r = int(scores["object"][index]), int(scores["object_candidate"][index])
            _, cloud, obstacles = objects[o]
            # Every variant of this candidate in one call: the policy may turn to another of them next.
            variants = np.asarray(gripper.refined_poses(candidates[o].poses[r].astype(np.float32), cfg.spec))
            widths = np.full(len(variants), candidates[o].widths[r], np.float32)
            # Object o's Stage-1 call cropped its obstacles with seed + o (`Stage1.chunked`): the same crop.
            # A deepened pose that reaches into the table is backed off it first, as Stage 1 backs its
            # candidates off (`lift_to_plane`): on objects lying on the table that undoes some deepening.
            found = stage1.collisions(cloud, obstacles, variants, widths, view, seed + o, cfg.support_plane, lift=True)
            # The obstacles and the table, not the target: the target lies in E-RNet's crop, and its refine
            # head was trained on how these very refinements fared against it in simulation.
            hits = found["collision_scene"] | found["below_support"]
            if fitted is not None:  # and the other objects' hidden sides, as the candidates were
                fits, mask, pairs = fitted
                hits = hits | neighbours.fit_hits(found["poses"], widths, np.full(len(widths), o, np.int32), fits, mask,
                                                  cfg.spec, cfg.neighbour_fits, stage1.config.filter.approach_clearance,
                                                  cfg.stage2_sizes, pairs)
            moved = np.any(found["poses"] != variants, axis=(1, 2))
            return hits, found["poses"], moved

        # The refinements' scores the policy decided on: the re-scored ones when `_rescore` ran.
        refine_score = scores.get("refine_score", scores["refine_prob"])
        return collision_free(choice, scores["eval_prob"], refine_score, scores["valid"], collides, self._decide)

    def _stage2_call(self, scene_pad, scene_mask, poses, widths, slots, seed: int, thresholds, judge: bool = False):
        """(function, arguments, static key) of one Stage-2 call, for `exported.call` / `exported.ready`;
        judge: with the judge network instead of the model."""
        cfg = self.config
        model, (graphdef, state) = (self.judge, self._judge_network) if judge else (self.model, (self.graphdef, self.state))
        return (
            functools.partial(_stage2, graphdef, spec=cfg.spec),
            (state, scene_pad, scene_mask, poses, widths, slots, jax.random.key(seed), thresholds,
             np.bool_(cfg.use_refinement)),
            (type(model).__qualname__, repr(model.config), cfg.spec),
        )

    def _score(self, scene_pad, scene_mask, poses, widths, slots, seed: int, thresholds, judge: bool = False):
        """One Stage-2 call (`_stage2`) -> (scores, choice) as NumPy. Exported once to the cache, keyed by
        the network's class and config (which fix its graphdef). judge: with the judge network."""
        fn, args, static = self._stage2_call(scene_pad, scene_mask, poses, widths, slots, seed, thresholds, judge)
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


def prefer_short_lever(choice: dict, scores: dict, poses: np.ndarray, centroids: np.ndarray, cfg: PlannerConfig) -> dict:
    """An evaluated choice made again with `PlannerConfig.lever_weight`: among the valid candidates on the
    chosen candidate's object whose eval_prob exceeds the threshold, the highest eval_prob - lever_weight
    * lever arm (ties: lowest index). poses [M, 4, 4], centroids [M, 3] (each candidate's object's),
    scores["object"] [M] -> choice, score its eval_prob."""
    e = np.asarray(scores["eval_prob"], np.float64)
    same = np.asarray(scores["object"]) == scores["object"][int(choice["index"])]
    passing = same & passing_mask(e, scores["valid"], cfg.eval_threshold)
    rank = e - cfg.lever_weight * gripper.lever_arm(poses, centroids, cfg.spec, xp=np)
    index = int(np.argmax(np.where(passing, rank, -np.inf)))
    return {**choice, "index": np.int32(index), "score": np.float32(e[index])}


def robust_scores(eval_prob, valid, threshold: float, top: int, judge, own: bool = True, minimum: int = 2) -> np.ndarray:
    """`PlannerConfig.robust`'s scores: the `top` best-evaluated valid candidates with eval_prob above
    `threshold` (eval_prob [M], valid [M]), each judged at its perturbed poses by `judge(index [t])` ->
    [t, P] (the evaluation head's scores there, 0 where it cannot judge) -> [M]: the mean of the
    candidate's own score and its P perturbed ones (own False: of the P judged scores alone, e.g. a
    judge network's, which scores the own pose among them), NaN where not judged (all NaN when fewer
    than `minimum` candidates pass: by default two, with fewer there is nothing to compare)."""
    e = np.asarray(eval_prob, np.float32)
    passing = np.flatnonzero(passing_mask(e, valid, threshold))
    index = passing[np.argsort(-e[passing], kind="stable")][:top]
    robust = np.full(len(e), np.nan, np.float32)
    if len(index) >= max(1, minimum):
        judged = np.asarray(judge(index), np.float32)
        robust[index] = (e[index] + judged.sum(axis=1)) / (1 + judged.shape[1]) if own else judged.mean(axis=1)
    return robust


def robust_choice(choice: dict, scores: dict) -> dict:
    """The evaluated choice made again on scores["robust_score"] [M] (`robust_scores`): the highest
    robust score (ties: the higher eval_prob, then the lowest index); the choice unchanged where no
    candidate was judged. -> choice, score its eval_prob."""
    robust = np.asarray(scores["robust_score"], np.float32)
    if not np.isfinite(robust).any():
        return choice
    e = np.asarray(scores["eval_prob"], np.float32)
    order = np.lexsort((np.arange(len(e)), -e, -np.where(np.isfinite(robust), robust, -np.inf)))
    index = int(order[0])
    return {**choice, "index": np.int32(index), "score": np.float32(e[index])}


def preferred(scores: dict, prefer: np.ndarray) -> dict:
    """scores with robust_score [M] left only on the judged candidates marked in prefer bool [M], when some
    but not all judged ones are (`RobustChoice.prefer_clearance`); else scores unchanged."""
    robust = np.asarray(scores["robust_score"], np.float32)
    judged = np.isfinite(robust)
    rows = preferred_rows(robust, judged, prefer, -np.inf)
    if rows[judged].all():
        return scores
    return {**scores, "robust_score": np.where(rows, robust, np.nan).astype(np.float32)}


def passing_robust_choice(choice: dict, scores: dict, threshold: float, decide, judge_again) -> dict:
    """`RobustChoice.must_pass`: an evaluated choice stands only if its robust score (scores["robust_score"]
    [M], NaN where not judged) passes `threshold` too. When it does not, no judged candidate does (it had
    the highest mean): their means become their evaluations (scores["eval_prob"] [M] updated in place,
    so that refinement and the caller see them as not passing), `decide(eval_prob)` -> choice decides
    again, and an evaluated choice among the candidates not yet judged is judged in turn
    (`judge_again(eval_prob, judged bool [M])` -> robust scores [M], NaN where not judged) -> choice."""
    while int(choice["kind"]) == KIND_EVALUATED:
        robust = np.asarray(scores["robust_score"], np.float32)
        index = int(choice["index"])
        if not np.isfinite(robust[index]) or robust[index] > threshold:
            return choice
        judged = np.isfinite(robust)
        scores["eval_prob"] = np.where(judged, np.minimum(scores["eval_prob"], robust), scores["eval_prob"]).astype(np.float32)
        choice = decide(scores["eval_prob"])
        if int(choice["kind"]) == KIND_EVALUATED:
            again = np.asarray(judge_again(scores["eval_prob"], judged), np.float32)
            scores["robust_score"] = np.where(judged, robust, again).astype(np.float32)
            choice = robust_choice(choice, {**scores, "robust_score": np.where(judged, np.nan, again)})
    return choice


def uncompared(plan: Plan, threshold: float) -> str | None:
    """How `plan`'s grasp was chosen without a comparison: "refined" (no evaluation passed), "lone" (an
    evaluated grasp, the only candidate whose eval_prob passes `threshold`), None (compared with other
    passing candidates, or no grasp)."""
    if plan.kind == "refined":
        return "refined"
    if plan.kind == "evaluated" and int(passing_mask(plan.scores["eval_prob"], plan.scores["valid"], threshold).sum()) < 2:
        return "lone"
    return None


def passing_mask(eval_prob, valid, threshold: float) -> np.ndarray:
    """The candidates whose evaluation passes: valid [M] with a finite eval_prob [M] above threshold -> bool [M]."""
    e = np.asarray(eval_prob)
    return np.asarray(valid, bool) & np.isfinite(e) & (e > threshold)


def failure_counts(avoid, clouds, spec: GripperSpec, radius: float) -> np.ndarray:
    """How many of the failed grasps avoid [F, 4, 4] each object was on (`PlannerConfig.failed_last`):
    a grasp counts for the object with an observed point nearest its closing region's centre
    (`gripper.closing_centre`), when that point is within `radius` metres; clouds: the objects'
    observed points (clouds[b] [N_b, 3]) -> int [B]."""
    counts = np.zeros(len(clouds), np.int64)
    avoid = np.asarray(avoid, np.float64).reshape(-1, 4, 4)
    if not len(avoid) or not len(clouds):
        return counts
    centres = np.asarray(gripper.closing_centre(avoid, spec, np), np.float64)  # [F, 3]
    nearest = np.stack([np.sqrt(np.min(np.sum((np.asarray(c, np.float64)[None] - centres[:, None]) ** 2, -1), 1))
                        for c in clouds], 1)  # [F, B]
    on = np.argmin(nearest, 1)
    hit = nearest[np.arange(len(avoid)), on] <= radius
    np.add.at(counts, on[hit], 1)
    return counts


def least_failed(eval_prob, valid, failures, threshold: float) -> np.ndarray:
    """`PlannerConfig.failed_last`'s candidates: those on the objects with the fewest failed grasps
    (failures int [M], per candidate: its object's count) among the objects with a valid candidate whose
    eval_prob [M] exceeds `threshold` -> bool [M] (all True when none passes)."""
    e, failures = np.asarray(eval_prob, np.float32), np.asarray(failures)
    passing = passing_mask(e, valid, threshold)
    if not passing.any():
        return np.ones(len(e), bool)
    return failures == failures[passing].min()


def preferred_rows(eval_prob, valid, prefer, threshold: float) -> np.ndarray:
    """The candidates a preference leaves to choose from: those marked in prefer bool [M] when one of them
    is valid [M] with an eval_prob [M] above `threshold`, else all -> bool [M]."""
    prefer = np.asarray(prefer, bool)
    if (passing_mask(eval_prob, valid, threshold) & prefer).any():
        return prefer
    return np.ones(len(prefer), bool)


def evaluated_choice(choice: dict, eval_prob, valid, threshold: float) -> dict:
    """The evaluated choice made again among valid [M]: the highest eval_prob [M] above threshold (ties:
    the lowest index); the choice unchanged when it is among them or none passes -> choice."""
    e = np.asarray(eval_prob, np.float32)
    passing = passing_mask(e, valid, threshold)
    if not passing.any() or passing[int(choice["index"])]:
        return choice
    index = int(np.argmax(np.where(passing, e, -np.inf)))
    return {**choice, "index": np.int32(index), "score": np.float32(e[index])}


def stage2_subset(counts, budget: int) -> tuple[np.ndarray, np.ndarray]:
    """Which Stage-1 candidates Stage 2 scores: counts [B] (candidates per object, in match order) ->
    (object [M], row [M]), M = min(sum(counts), budget). All of them when they fit; otherwise
    round-robin over objects in match order (rank 0 of every object, then rank 1, ...), so every
    object keeps its best-matched candidates. Returned in (object, row) order."""
    obj = np.concatenate([np.full(n, i, np.int64) for i, n in enumerate(counts)] + [np.zeros(0, np.int64)])
    row = np.concatenate([np.arange(n, dtype=np.int64) for n in counts] + [np.zeros(0, np.int64)])
    if len(obj) > budget:
        keep = np.sort(np.lexsort((obj, row))[:budget])  # by row, then object
        obj, row = obj[keep], row[keep]
    return obj, row


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
