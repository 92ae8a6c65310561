"""The paper's PointNetGPD baseline and its two ablations (Table I) as benchmark methods.

  pointnetgpd      GPD-style geometric candidates (sgjax/samplers/gpd.py: antipodal sampling, the deepest
                   collision-free placement, centring and width, re-checked; its antipodal ranking is
                   not used) scored by the PointNetGPD evaluator (sgjax/stage2/pointnetgpd.py); the best-scored
                   candidate is executed (PointNetGPD executes its best grasp; no threshold).
  s1+pointnetgpd   "Ours (S1) + PointNetGPD": SuperGrasp's Stage 1 (sgjax/stage1/pipeline.py, every visible
                   object, the rest of the scene as obstacles, the observed table as support plane)
                   scored by PointNetGPD; the best is executed.
  gpd+s2           "PointNetGPD + Ours (S2)": the GPD-style candidates scored by E-RNet and chosen by
                   SuperGrasp's decision policy as the planner applies it (`sgjax.planner`: the best
                   evaluation > 0.7, else the best refinement > 0.7, a refinement re-scored at its
                   refined pose (`refine_rescore`) and executed only once it passes the generator's
                   own collision test against the other objects and the table, else no grasp).

Options (`eval.methods.make_method`): `model` -- the network: a run directory, a model instance, or
None for the shipped default (`sgjax/models/pointnetgpd_default` for the PointNetGPD methods,
`sgjax/models/ernet_default` for gpd+s2; a missing default raises FileNotFoundError naming the path
and the training command); `small_db` / `db` -- Stage 1's primitive database (s1+pointnetgpd only);
`config` -- a `BaselineConfig` (its spec is the gripper every method here plans for; the registry's
`gripper` option gives `BaselineConfig.with_gripper`); a network checkpoint trained for another gripper
than that is warned about (`sgjax.stage2.checkpoint.warn_gripper`).

Both networks score the scene as the labelling pipeline cropped it: the observation (objects and table)
cropped to the workspace (the registry's default config, `eval.methods`: `envs.scene.stage2_scene_cloud`,
as labelling, training and SuperGrasp), on a voxel grid of `scene_cloud.voxel` (3 mm), at most `scene_cloud.max_points` points
(`sgjax.stage2.scene_cloud.SceneCloudConfig`, seeded). Fixed shapes, so no call after the first recompiles: the
candidates are padded (identity pose, NaN width: invalid for both networks) to `max_candidates`
slots; more candidates than slots -> a seeded uniform subset of the GPD-style ones, or, for Stage 1,
every object's best-matched ones first (round-robin over objects in match order, as the planner);
Stage 1 runs objects in batches of `stage1_batch_sizes`.

Timing: stage1_s = candidate generation, stage2_s = scene cloud + network + decision.
"""

from __future__ import annotations

import dataclasses
import functools
import time

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx

from sgjax.samplers import gpd as gpd_sampler
from eval.protocol import Decision, near_grasps
from sgjax.geometry import gripper, pointcloud
from sgjax import policy
from sgjax.geometry.gripper import GripperSpec
from sgjax.stage1.filters import lift_to_plane
from sgjax.stage1.pipeline import Stage1Config
from sgjax.stage2 import checkpoint
from sgjax.stage2.scene_cloud import SceneCloudConfig


@dataclasses.dataclass(frozen=True)
class BaselineConfig:
    """Settings of the baseline methods (hashable).

    gpd: the GPD-style candidate generator (its spec must equal stage1's).
    stage1: SuperGrasp's Stage 1 (s1+pointnetgpd); its spec is the gripper of every method here.
    max_candidates: candidate slots scored per plan (padded and masked).
    min_object_points, stage1_batch_sizes: as `sgjax.planner.PlannerConfig` (objects with fewer
        points are skipped; objects run through Stage 1 in chunks of these sizes).
    scene_cloud: the scene cloud the networks crop from (sgjax knows no workspace: the benchmark's registry
        gives the workspace crop of labelling, `envs.scene.stage2_scene_cloud`).
    eval_threshold, refine_threshold, use_refinement, refine_rescore: SuperGrasp's decision policy
        (gpd+s2), as `sgjax.planner.PlannerConfig` (refine_rescore 0: the paper's rule, the refine head alone).
    """

    gpd: gpd_sampler.GPDConfig = dataclasses.field(default_factory=gpd_sampler.GPDConfig)
    stage1: Stage1Config = dataclasses.field(default_factory=Stage1Config)
    max_candidates: int = 512
    min_object_points: int = 50
    stage1_batch_sizes: tuple[int, ...] = (4,)
    scene_cloud: SceneCloudConfig = SceneCloudConfig()
    eval_threshold: float = 0.7
    refine_threshold: float = 0.7
    use_refinement: bool = True
    refine_rescore: int = 64

    def __post_init__(self):
        object.__setattr__(self, "stage1_batch_sizes", tuple(sorted({int(b) for b in self.stage1_batch_sizes})))
        if self.gpd.spec != self.stage1.spec:
            raise ValueError("BaselineConfig: the GPD generator and Stage 1 must use the same GripperSpec")
        if not 0 <= self.refine_rescore <= self.max_candidates:
            raise ValueError(f"refine_rescore must be in [0, max_candidates={self.max_candidates}], got {self.refine_rescore}")
        if self.max_candidates < 1 or not self.stage1_batch_sizes or self.stage1_batch_sizes[0] < 1:
            raise ValueError("max_candidates and stage1_batch_sizes must be >= 1")
        if self.min_object_points < pointcloud.MIN_POINTS:
            raise ValueError(f"min_object_points must be >= {pointcloud.MIN_POINTS}")
        policy.check_thresholds(self)

    @property
    def spec(self) -> GripperSpec:
        return self.stage1.spec

    def with_gripper(self, gripper: GripperSpec) -> BaselineConfig:
        """These settings for `gripper`: the GPD-style generator's and Stage 1's spec (the two that must agree)."""
        if self.spec == gripper and self.gpd.spec == gripper:
            return self
        return dataclasses.replace(self, gpd=dataclasses.replace(self.gpd, spec=gripper),
                                   stage1=dataclasses.replace(self.stage1, spec=gripper))


# ---------------------------------------------------------------------------------------------
# Candidates.


@dataclasses.dataclass
class CandidateSet:
    """Candidates padded to `slots`: poses [S, 4, 4] f32 (identity padding), widths [S] f32 (NaN
    padding), n real ones first; found = candidates before the budget; target [S] object label (-1
    unknown); reason when n == 0; info JSON-able counts."""

    poses: np.ndarray
    widths: np.ndarray
    n: int
    found: int
    target: np.ndarray
    reason: str = ""
    info: dict = dataclasses.field(default_factory=dict)


def _padded(poses, widths, target, slots: int, found: int, reason: str = "", info=None) -> CandidateSet:
    out_p, out_w = policy.padded_batch(poses, widths, slots)  # the planner's Stage-2 padding
    out_t = np.full(slots, -1, np.int64)
    out_t[:len(widths)] = target
    return CandidateSet(out_p, out_w, len(widths), found, out_t, reason, dict(info or {}))


def _empty(slots: int, reason: str, info=None) -> CandidateSet:
    return _padded(np.zeros((0, 4, 4)), np.zeros(0), np.zeros(0, np.int64), slots, 0, reason, info)


def without_avoided(cands: CandidateSet, avoid, spec: GripperSpec) -> CandidateSet:
    """cands less the candidates that are the same grasp as a pose in avoid [F, 4, 4] (the harness's
    memory of failed grasps), re-padded to the same slots; the reason says so when none is left."""
    n = cands.n
    near = near_grasps(cands.poses[:n], avoid, spec)
    if not near.any():
        return cands
    keep = np.flatnonzero(~near)
    info = {**cands.info, "avoided": int(near.sum())}
    reason = "" if len(keep) else f"all {n} candidates are the same grasp as one that already failed"
    return _padded(cands.poses[keep], cands.widths[keep], cands.target[keep], len(cands.widths), cands.found, reason, info)


def gpd_candidates(points, labels, viewpoint, seed: int, config: BaselineConfig) -> CandidateSet:
    """The GPD-style generator (sgjax/samplers/gpd.py stages 1 and 2) -> its kept candidates, padded.

    A seeded uniform subset of them when there are more than `max_candidates` (both the samples and the
    slots times `gpd_sampler.budget_factor` for scenes with many objects in view)."""
    # The sampling budget and the scored slots grow alike with the objects in view (`GPDConfig.objects_per_budget`).
    cfg, factor = gpd_sampler.scaled_to_scene(config.gpd, labels)
    slots = config.max_candidates * factor
    cloud, mask, table_z, n = gpd_sampler.prepare_cloud(points, labels, cfg, seed)
    if n < cfg.min_points:
        return _empty(slots, f"only {n} object points seen", {"object_points": n})
    view = np.asarray(viewpoint, np.float32).reshape(3)
    sampled = gpd_sampler.candidates(cloud, mask, view, np.float32(table_z), jax.random.key(seed), cfg)
    m = cfg.num_samples * cfg.num_angles
    out = gpd_sampler.evaluate(sampled["poses"].reshape(m, 4, 4), sampled["valid"].reshape(m), cloud, mask,
                       sampled["normals"], np.float32(table_z), cfg)
    out = jax.tree_util.tree_map(np.asarray, out)
    kept = np.flatnonzero(out["valid"])
    info = {"object_points": n, "sampled": m, "collision_free": int(np.asarray(sampled["valid"]).sum()),
            "kept": len(kept)}
    if len(kept) == 0:
        return _empty(slots, f"no GPD candidate kept among {m} sampled ({info['collision_free']} collision-free)", info)
    if len(kept) > slots:
        kept = np.sort(np.random.default_rng(seed).choice(kept, slots, replace=False))
    return _padded(out["poses"][kept], out["widths"][kept], np.full(len(kept), -1), slots, int(info["kept"]), info=info)


def round_robin(counts, budget: int) -> tuple[np.ndarray, np.ndarray]:
    """counts [B] candidates per object (in match order) -> (object [M], row [M]), M = min(total,
    budget): all when they fit, else rank 0 of every object, then rank 1, ... (in (object, row) order)."""
    obj = np.concatenate([np.full(n, i, np.int64) for i, n in enumerate(counts)] + [np.zeros(0, np.int64)])
    row = np.concatenate([np.arange(n, dtype=np.int64) for n in counts] + [np.zeros(0, np.int64)])
    if len(obj) > budget:
        keep = np.sort(np.lexsort((obj, row))[:budget])
        obj, row = obj[keep], row[keep]
    return obj, row


class Stage1Candidates:
    """SuperGrasp's Stage 1 over every visible object of an observation, padded to max_candidates."""

    def __init__(self, config: BaselineConfig, db=None, small_db: bool = False):
        from sgjax.stage1.pipeline import Stage1

        if db is None and (small_db or config.spec != GripperSpec()):
            # The database of the config's gripper (the default one's ships; another's is built on first use).
            from sgjax.stage1.database import DBConfig, load_database

            db = load_database(DBConfig.for_gripper(config.spec, small_db), progress=False)
        self.config = config
        self.stage1 = Stage1(db, config.stage1)

    def __call__(self, points, labels, viewpoint, seed: int) -> CandidateSet:
        cfg, slots = self.config, self.config.max_candidates
        points = np.asarray(points, np.float64)
        labels = np.asarray(labels).astype(np.int64)
        finite = np.all(np.isfinite(points), axis=1)
        points, labels = points[finite], labels[finite]
        ids, counts = np.unique(labels[labels >= 0], return_counts=True)
        objects = [int(i) for i, c in zip(ids, counts) if c >= cfg.min_object_points]
        info = {"objects": len(ids), "planned_objects": len(objects)}
        if not objects:
            return _empty(slots, f"no object with at least {cfg.min_object_points} visible points", info)
        clouds = [points[labels == k] for k in objects]
        scenes = [points[labels != k] for k in objects]  # obstacles: the rest (Stage 1 takes an empty one)
        found = self.stage1.chunked(clouds, scenes, viewpoint, seed, pointcloud.table_plane(points, labels), cfg.stage1_batch_sizes)
        sizes = [len(c) for c in found]
        info["stage1_candidates"] = int(sum(sizes))
        if not sum(sizes):
            detail = "; ".join(f"object {k}: {c.reason}" for k, c in zip(objects, found))
            return _empty(slots, f"no Stage-1 candidates: {detail}", info)
        obj, row = round_robin(sizes, slots)
        poses = np.stack([found[o].poses[r] for o, r in zip(obj, row)])
        widths = np.asarray([found[o].widths[r] for o, r in zip(obj, row)])
        return _padded(poses, widths, np.asarray(objects)[obj], slots, int(sum(sizes)), info=info)


# ---------------------------------------------------------------------------------------------
# Networks.


@functools.cache
def _decide():
    from sgjax.policy import decide

    return jax.jit(decide)


def _orthonormal(pose) -> np.ndarray:
    pose = np.asarray(pose, np.float64).copy()
    u, _, vt = np.linalg.svd(pose[:3, :3])
    pose[:3, :3] = u @ vt
    pose[3] = [0.0, 0.0, 0.0, 1.0]
    return pose


# ---------------------------------------------------------------------------------------------
# The methods.


class _CandidateMethod:
    """Candidates from a generator, then a network and a decision on the scene cloud."""

    name = ""
    generator_name = ""

    def __init__(self, network, config: BaselineConfig | None, generator):
        self.config = config or BaselineConfig()
        self.generator = generator
        self.graphdef, state = nnx.split(network)
        # Commit the weights as the planner does: every instance with this network shares one compile.
        self.state = jax.device_put(state, jax.devices()[0])

    def plan(self, points: np.ndarray, labels: np.ndarray, viewpoint, seed: int = 0, avoid=None) -> Decision:
        start = time.perf_counter()
        points, labels = np.asarray(points), np.asarray(labels)
        cands = without_avoided(self.generator(points, labels, viewpoint, seed), avoid, self.config.spec)
        mid = time.perf_counter()
        info = {"generator": self.generator_name, "candidates": cands.found, "scored": cands.n, **cands.info}
        if cands.n == 0:
            return Decision(None, 0.0, 0.0, cands.reason, {"stage1_s": mid - start, "stage2_s": 0.0, "total_s": mid - start}, info)
        cfg = self.config
        scene, mask, _ = cfg.scene_cloud.make(points, None, seed)
        pose, width, score, reason, extra = self._decide(cands, scene, mask, seed, points, labels)
        end = time.perf_counter()
        timing = {"stage1_s": mid - start, "stage2_s": end - mid, "total_s": end - start}
        info.update(extra)
        if pose is None:
            return Decision(None, 0.0, float(score), reason, timing, info)
        return Decision(_orthonormal(pose), float(width), float(score), "", timing, info)


class PointNetGPDMethod(_CandidateMethod):
    """`pointnetgpd` (generator "gpd") and `s1+pointnetgpd` (generator "stage1"): the best PointNetGPD score."""

    def __init__(self, generator: str = "gpd", model=None, small_db: bool = False, db=None, config=None):
        from sgjax.stage2 import pointnetgpd

        config = config or BaselineConfig()
        if generator not in ("gpd", "stage1"):
            raise ValueError(f"generator must be 'gpd' or 'stage1', got {generator!r}")
        network = pointnetgpd.as_model(model, config.spec)  # first: a missing checkpoint fails before the database loads
        checkpoint.warn_gripper("PointNetGPD", model, checkpoint.POINTNETGPD_DEFAULT_DIR, config.spec)
        if generator == "gpd":
            self.name, make = "pointnetgpd", functools.partial(gpd_candidates, config=config)
        else:
            self.name, make = "s1+pointnetgpd", Stage1Candidates(config, db, small_db)
        self.generator_name = generator
        super().__init__(network, config, make)

    def _decide(self, cands: CandidateSet, scene, mask, seed: int, points=None, labels=None):
        from sgjax.stage2 import pointnetgpd

        out = pointnetgpd.score(self.graphdef, self.state, scene, cands.poses, cands.widths, mask,
                                spec=self.config.spec, key=jax.random.key(seed))
        prob, valid = np.asarray(out.prob), np.asarray(out.valid) & (np.arange(len(cands.widths)) < cands.n)
        extra = {"valid": int(valid.sum())}
        if not valid.any():
            return None, 0.0, 0.0, f"none of the {cands.n} candidates has a scene point in its closing region", extra
        best = int(np.argmax(np.where(valid, prob, -1.0)))
        extra.update(kind="best", index=best, target=int(cands.target[best]))
        return cands.poses[best], cands.widths[best], prob[best], "", extra


class GPDStage2Method(_CandidateMethod):
    """`gpd+s2`: GPD-style candidates, E-RNet scores, SuperGrasp's decision policy."""

    name = "gpd+s2"
    generator_name = "gpd"

    def __init__(self, model=None, config=None):
        from sgjax.stage2 import ernet

        config = config or BaselineConfig()
        network = ernet.as_model(model, config.spec)
        checkpoint.warn_gripper("E-RNet", model, checkpoint.ERNET_DEFAULT_DIR, config.spec)
        super().__init__(network, config, functools.partial(gpd_candidates, config=config))

    def _decide(self, cands: CandidateSet, scene, mask, seed: int, points=None, labels=None):
        from sgjax.stage2 import ernet

        cfg = self.config
        spec = cfg.spec
        score_fn = lambda poses, widths: ernet.score(self.graphdef, self.state, scene, poses, widths, mask, spec=spec,
                                                     key=jax.random.key(seed))
        out = score_fn(cands.poses, cands.widths)
        valid = np.asarray(out.valid) & (np.arange(len(cands.widths)) < cands.n)
        eval_prob, refine_prob = np.asarray(out.eval_prob), np.asarray(out.refine_prob)
        decide_again = lambda e, r, v: _choice(_decide()(e, r, v, np.float32(cfg.eval_threshold),
                                                         np.float32(cfg.refine_threshold), np.bool_(cfg.use_refinement)))
        choice = decide_again(eval_prob, refine_prob, valid)
        refine_score = refine_prob
        extra = {"valid": int(valid.sum())}
        if cfg.use_refinement and cfg.refine_rescore and choice["kind"] != policy.KIND_EVALUATED:
            # As the planner: the refine head's best proposals judged at their refined pose (`rescored_refinements`).
            def judge(index, variant):
                n = len(index)
                # Padded to the one shape this method scores: no new compile.
                judged = score_fn(*policy.padded_refinements(cands.poses, cands.widths, index, variant,
                                                              len(cands.widths), spec))
                return np.where(np.asarray(judged.valid)[:n], np.asarray(judged.eval_prob)[:n], 0.0)

            refine_score = policy.rescored_refinements(refine_prob, valid, cfg.refine_rescore, judge)
            choice = decide_again(eval_prob, refine_score, valid)
        rejected = 0
        if choice["kind"] == policy.KIND_REFINED:
            collides = _RefinedCollisions(cands, points, labels, cfg, seed)
            choice, rejected = policy.collision_free(choice, eval_prob, refine_score, valid, collides, decide_again)
        index, kind, variant, score = choice["index"], choice["kind"], choice["variant"], choice["score"]
        if rejected:
            extra["refinements_rejected"] = rejected
        if kind == policy.KIND_NONE:
            if not valid.any():
                reason = f"none of the {cands.n} candidates has a scene point in its closing region (E-RNet valid = False)"
            else:
                reason = f"best eval {eval_prob[valid].max():.2f} <= {cfg.eval_threshold:g}"
                if not cfg.use_refinement:
                    reason += " (refinement disabled)"
                elif rejected:
                    reason += f", and the {rejected} refined pose(s) scored above {cfg.refine_threshold:g} collide"
                else:
                    best = refine_score[valid].max()
                    what = "re-scored refinement" if refine_score is not refine_prob else "refine"
                    reason += f" and best {what} {best:.2f} <= {cfg.refine_threshold:g}"
            return None, 0.0, score, reason, extra
        pose = cands.poses[index]
        if kind == policy.KIND_REFINED:
            pose = np.asarray(choice["pose"], np.float64)
            extra.update(kind="refined", refine_variant=variant)
        else:
            extra.update(kind="evaluated")
        extra.update(index=index)
        return pose, cands.widths[index], score, "", extra


def _choice(out) -> dict:
    """`decide`'s outputs as the planner's choice dict (pose None: the refined pose is made on the host)."""
    index, kind, variant, score = (np.asarray(v).item() for v in out)
    return {"index": int(index), "kind": int(kind), "variant": int(variant), "score": float(score), "pose": None}


class _RefinedCollisions:
    """`collides(index)` for `sgjax.policy.collision_free` on GPD-style candidates: every refined variant
    of candidate `index` under the generator's own collision test (`gpd_sampler.hand_collisions`) against
    the observed objects other than the grasped one (the object with most points between the fingers:
    it lies in E-RNet's crop, whose refine head judged how refinements fare against it) and the table."""

    def __init__(self, cands: CandidateSet, points, labels, config: BaselineConfig, seed: int):
        self.cands, self.config = cands, config
        self.cloud, self.mask, self.table_z, _, self.labels = gpd_sampler.prepare_labelled_cloud(points, labels, config.gpd, seed)

    def __call__(self, index: int):
        spec = self.config.spec
        pose = self.cands.poses[index].astype(np.float32)
        refined = np.asarray(gripper.refined_poses(pose, spec), np.float32)
        widths = np.full(len(refined), self.cands.widths[index], np.float32)
        # As the planner: a deepened hand that reaches into the table is backed off it along its approach
        # first (at most Stage 1's max_lift), which undoes some deepening (`filters.lift_to_plane`).
        plane = np.array([0.0, 0.0, 1.0, -self.table_z if np.isfinite(self.table_z) else 1e3], np.float32)
        variants = np.asarray(lift_to_plane(jnp.asarray(refined), widths, plane, spec, self.config.gpd.table_clearance,
                                            self.config.stage1.max_lift)[0])
        between = np.asarray(gripper.points_in_closing_region(self.cloud, pose, widths[0], spec)) & self.mask
        held = self.labels[between]
        target = np.bincount(held).argmax() if len(held) else -1
        obstacles = self.mask & (self.labels != target)
        hits = np.asarray(gpd_sampler.hand_collisions(variants, widths, self.cloud, obstacles, np.float32(self.table_z),
                                                      self.config.gpd))
        return hits, variants, np.any(variants != refined, axis=(1, 2))
