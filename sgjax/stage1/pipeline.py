"""Stage 1 of SuperGrasp: single-view cloud -> grasp candidates (paper Sec. IV-B).

fit a superquadric (EMS) -> match it against the primitive database (top K1 by d_shape, top K2 by s)
-> transfer the matched primitives' template grasps (T = T_sq^q (T_sq^c)^-1) -> widths adapted to the
observed cloud by the paper's own width rule (`Stage1Config.adapt_width`) -> coarse filtering.

`Stage1` holds the database on the device and one jit-compiled pipeline, batched over objects with
fixed shapes (clouds padded to `max_object_points`, scene crops to `max_scene_points`, candidates
compacted to `max_candidates` slots), so repeated calls never recompile. `generate_candidates` is the
one-object convenience wrapper; `Stage1.batch` runs many objects in one call.

Clouds are in metres in any frame; pass `viewpoint` (the camera position in that frame; default the
origin, right for camera-frame clouds) so normals are oriented towards the camera.
"""

from __future__ import annotations

import dataclasses
import functools
import json

import jax
import jax.numpy as jnp
import numpy as np

from sgjax.geometry import pointcloud
from sgjax.stage1.filters import (
    NO_PLANE,
    FilterConfig,
    coarse_filter,
    estimate_normals,
    lift_to_plane,
    map_chunks,
    pose_collisions,
    removal_counts,
    scene_filter,
    windowed_scene_test,
)
from sgjax.stage1.ems import EMSConfig, FitResult, _fit_one
from sgjax.stage1.fit_grasps import FitGraspConfig, fit_top_down_grasps
from sgjax.geometry.gripper import GripperSpec, recentre_and_widen, to_gripper_frame
from sgjax.utils import exported
from sgjax.utils.cache import enable_compilation_cache
from sgjax.stage1.matching import MatchConfig, MatchDB, match, transfer_grasps
from sgjax.stage1.database import DBConfig, PrimitiveDB, load_database


# `Stage1.collisions` pads its poses to a multiple of this (one compiled shape for a few poses).
POSE_SLOTS = 8


@dataclasses.dataclass(frozen=True)
class Stage1Config:
    """Everything Stage 1 needs except the database. Hashable (a static jit argument)."""

    ems: EMSConfig = EMSConfig()
    match: MatchConfig = MatchConfig()
    filter: FilterConfig = FilterConfig()
    spec: GripperSpec = GripperSpec()
    max_object_points: int = 1024
    max_scene_points: int = 4096
    # An obstacle crop of more than max_scene_points points is first thinned to one point per voxel of
    # this side (metres; 0: not), then drawn at random down to max_scene_points; one that fits is kept
    # whole. In 20-object scenes a crop holds 10-28k camera points and a random 4,096 of them can drop a
    # neighbour's sliver between the fingers; a 4 mm grid keeps every occupied cell (2-5.6k points
    # there) at no cost to filter (iv), whose work is set by max_scene_points (docs/benchmark.md).
    obstacle_voxel: float = 0.004
    max_candidates: int = 1024  # transferred slots kept (in match order) for filtering
    scene_margin: float = 0.12  # scene points farther than this from the object's box cannot touch the gripper
    target_exclusion: float = 0.002  # scene points this close to an object point are the object itself
    # Re-apply the paper's width rule (delta from the surface) to the observed cloud after transfer,
    # re-centring each grasp on it by at most max_recentre: a matched primitive of another size would
    # otherwise close a finger into the object (`sgjax.geometry.gripper.adapt_to_cloud`, `recentre_and_widen`).
    adapt_width: bool = True
    max_recentre: float = 0.005
    # Objects rest on the support plane, which hides their bottom: with a plane given, EMS also fits the
    # observed points projected onto it (the object's footprint), so a single view seen from above does
    # not collapse into a flat superquadric. The filters still see only the observed points.
    footprint: bool = True
    # Scene points this close above the support plane are the table: filter (v) tests it exactly, so
    # they leave the obstacle cloud, whose test grows the gripper by `filter.obstacle_margin`.
    table_band: float = 0.005
    # Grasps whose fingers reach into the support plane are backed off along the approach by at most
    # max_lift to clear it by filter.support_clearance (`sgjax.stage1.filters.lift_to_plane`) rather
    # than removed by filter (v): on thin lying objects these are the grasps that close low enough.
    max_lift: float = 0.01
    # Top-down grasps on the fit itself, ahead of the transferred ones (`sgjax.stage1.fit_grasps`;
    # primitive_id -1). None: the paper's candidates only. The planner sets it (`PlannerConfig.fit_grasps`).
    fit_grasps: FitGraspConfig | None = None

    def __post_init__(self):
        if not self.obstacle_voxel >= 0.0:
            raise ValueError(f"obstacle_voxel must be >= 0 metres (0: no grid), got {self.obstacle_voxel}")


@dataclasses.dataclass
class Candidates:
    """Grasp candidates of one object (NumPy), in match order (best primitive first).

    poses [M, 4, 4] (gripper frame of `sgjax.geometry.gripper` -> world), widths [M];
    provenance: primitive_id [M] (row in the database), template_id [M] (index among that
    primitive's grasps), match_rank [M] (0..K2-1), match_score [M] (the paper's s); a grasp on the fit
    itself (`Stage1Config.fit_grasps`) has primitive_id -1, match_rank -1, match_score 0 and its index
    among the fit's grasps as template_id;
    points_between [M]: target points between the fingers. `superquadric` is the fitted FitResult,
    `counts` says how many candidates each filter removed, `reason` why the set is empty (else None).
    """

    poses: np.ndarray
    widths: np.ndarray
    primitive_id: np.ndarray
    template_id: np.ndarray
    match_rank: np.ndarray
    match_score: np.ndarray
    points_between: np.ndarray
    superquadric: FitResult | None
    counts: dict
    reason: str | None = None
    # The candidates that reached filter (iv) (passed the rest, within its slots), kept or not, as arrays
    # named like the fields above: `Stage1.rescene` tests them against other obstacles without Stage 1.
    before_scene: dict | None = None

    def __len__(self) -> int:
        return len(self.widths)

    def to_dict(self, top: int | None = None) -> dict:
        """JSON-ready summary with the first `top` grasps (all when None)."""
        n = len(self) if top is None else min(top, len(self))
        out = {"count": len(self), "counts": self.counts, "reason": self.reason, "grasps": []}
        if self.superquadric is not None:
            sq = self.superquadric
            out["superquadric"] = {
                "scale": np.asarray(sq.scale).tolist(),
                "epsilon": np.asarray(sq.epsilon).tolist(),
                "translation": np.asarray(sq.translation).tolist(),
            }
        for i in range(n):
            out["grasps"].append(
                {
                    "pose": np.round(self.poses[i], 6).tolist(),
                    "width": round(float(self.widths[i]), 6),
                    "primitive_id": int(self.primitive_id[i]),
                    "template_id": int(self.template_id[i]),
                    "match_score": round(float(self.match_score[i]), 6),
                }
            )
        return out

    def to_json(self, top: int | None = None) -> str:
        return json.dumps(self.to_dict(top))


# The Candidates fields with one row per candidate (what selecting candidates selects).
ROW_FIELDS = ("poses", "widths", "primitive_id", "template_id", "match_rank", "match_score", "points_between")


def _empty(counts: dict, reason: str, fit: FitResult | None, before_scene: dict | None = None) -> Candidates:
    z = np.zeros(0)
    return Candidates(np.zeros((0, 4, 4)), z, z.astype(int), z.astype(int), z.astype(int), z, z.astype(int), fit, counts, reason,
                      before_scene)


def _selected(arrays: dict, rows: np.ndarray, fit: FitResult, counts: dict, before_scene: dict | None) -> Candidates:
    """Candidates from named arrays (the `ROW_FIELDS`; float64 poses / widths / scores) at rows."""
    taken = {name: arrays[name][rows] for name in ROW_FIELDS}
    for name in ("poses", "widths", "match_score"):
        taken[name] = taken[name].astype(np.float64)
    return Candidates(**taken, superquadric=fit, counts=counts, before_scene=before_scene)


def _reason(counts: dict, cfg: Stage1Config) -> str:
    parts = [
        f"{counts['collision_object']} collide with the object",
        f"{counts['too_few_points']} have fewer than {cfg.filter.min_points} points between the fingers",
        f"{counts['normal_angle']} fail the {cfg.filter.max_normal_angle_deg:g} deg normal test",
    ]
    if counts.get("below_support"):
        parts.append(f"{counts['below_support']} reach below the support plane")
    if counts.get("collision_scene"):
        parts.append(f"{counts['collision_scene']} collide with the scene")
    if counts.get("scene_untested"):
        parts.append(f"{counts['scene_untested']} were beyond the scene test's {cfg.filter.scene_slots} slots")
    return f"all {counts['transferred']} transferred candidates were removed: " + ", ".join(parts)


def with_footprint(points: jax.Array, mask: jax.Array, plane: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Clouds plus their projections onto the support plane: points [B, N, 3], mask [B, N], plane [B, 4]
    (n, d; NO_PLANE adds nothing; points below the plane add nothing) -> points [B, 2N, 3], mask [B, 2N]."""
    normal, offset = plane[:, None, :3], plane[:, None, 3:]
    height = jnp.sum(points * normal, -1, keepdims=True) + offset  # [B, N, 1]
    projected = points - height * normal
    # Only points in the plane's free space rest on it (NO_PLANE has a zero normal: nothing added).
    above = (height[..., 0] > 0.0) & jnp.any(normal != 0.0, -1)
    return jnp.concatenate([points, projected], 1), jnp.concatenate([mask, mask & above], 1)


def _pipeline(obj, obj_mask, scene, scene_mask, viewpoint, plane, scale, neighbours, db: MatchDB, cfg: Stage1Config,
              has_scene: bool, has_view: bool = True):
    """Fixed-shape Stage 1 over B objects. obj [B, N, 3], scene [B, S, 3], viewpoint [B, 3], plane [B, 4],
    scale [B] (observed points per kept object point), neighbours (index [B, N, k], ok [B, N, k]): each
    object point's nearest neighbours (`knn_indices`)."""
    # A known viewpoint tells EMS which of the fitted surface the camera should have seen.
    ems_obj, ems_mask = with_footprint(obj, obj_mask, plane) if cfg.footprint else (obj, obj_mask)
    fit = jax.vmap(lambda p, m, v: _fit_one(p, m, cfg.ems, v if has_view else None))(ems_obj, ems_mask, viewpoint)
    result = match(fit.scale, fit.epsilon, db, cfg.match)
    poses, widths, mask = transfer_grasps(fit.superquadric, result, db)  # [B, K2, G, ...]
    b, k2, g = mask.shape
    poses, widths, mask = poses.reshape(b, k2 * g, 4, 4), widths.reshape(b, k2 * g), mask.reshape(b, k2 * g)
    f = 0
    if cfg.fit_grasps is not None:  # the fit's own grasps first, so that max_candidates never drops them
        on_fit = jax.vmap(lambda sq, pl: fit_top_down_grasps(sq, pl, cfg.spec, cfg.fit_grasps))(fit.superquadric, plane)
        f = cfg.fit_grasps.count
        poses, widths, mask = (jnp.concatenate([a, c], 1) for a, c in zip(on_fit, (poses, widths, mask)))
    mask &= fit.valid[:, None]
    # Compact the valid slots to the front (stable: match order is kept), then keep max_candidates.
    order = jnp.argsort(~mask, axis=1, stable=True)[:, : cfg.max_candidates]
    take = lambda x: jnp.take_along_axis(x, order.reshape(order.shape + (1,) * (x.ndim - 2)), 1)
    poses, widths, valid = take(poses), take(widths), take(mask)
    own = order < f  # a grasp on the fit: match rank and primitive -1
    rank = jnp.where(own, -1, (order - f) // g)
    template = jnp.where(own, order, (order - f) % g)
    if cfg.max_lift > 0.0:
        lift = lambda p, w, pl: lift_to_plane(p, w, pl, cfg.spec, cfg.filter.support_clearance, cfg.max_lift)[0]
        poses = jax.vmap(lift)(poses, widths, plane)
    normals = estimate_normals(obj, obj_mask, viewpoint, neighbours=neighbours)

    # The fit's own grasps skip the normal test (iii) unless their config asks for it.
    skip_normal = own if cfg.fit_grasps is not None and not cfg.fit_grasps.normal_test else jnp.zeros_like(own)

    def one(p, w, v, sk, o, om, nrm, pl, sc, sq):
        def part(pc, wc, vc, skc):  # a chunk of candidates: the tests over candidate x object point pairs
            local = to_gripper_frame(o, pc)  # [m, N, 3]: shared by the adaptation and the filters
            if cfg.adapt_width:
                shift, wc = recentre_and_widen(local, om, wc, cfg.spec, cfg.max_recentre)
                # Re-centring moves each grasp along its own closing axis: its local x shifts by as much.
                pc = pc.at[:, :3, 3].add(shift[:, None] * pc[:, :3, 0])
                local = local.at[..., 0].add(-shift[:, None])
            tested = coarse_filter(pc, wc, vc, o, om, nrm, None, None, cfg.spec, cfg.filter, pl, sc, object_local=local,
                                   superquadric=sq, skip_normal=skc)
            return pc, wc, tested

        return map_chunks(part, cfg.filter.chunk, p, w, v, sk)

    poses, widths, filt = jax.vmap(one)(poses, widths, valid, skip_normal, obj, obj_mask, normals, plane, scale,
                                        fit.superquadric)
    if has_scene:  # (iv) last, on the candidates that passed the rest
        # Object by object (`lax.map`, not vmap), so that its chunks of slots no candidate reached are skipped.
        def with_scene(args):
            f, p, w, s, sm, view = args
            return scene_filter(f, p, w, s, sm, cfg.spec, cfg.filter, view if has_view else None)

        filt = jax.lax.map(with_scene, (filt, poses, widths, scene, scene_mask, viewpoint))
    return {
        "fit": fit,
        "poses": poses,
        "widths": widths,
        "valid": valid,
        "total_valid": jnp.sum(mask, 1),
        "filter": filt,
        "primitive_id": jnp.where(own, -1, jnp.take_along_axis(result.index, jnp.maximum(rank, 0), 1)),
        "template_id": template,
        "match_rank": rank,
        "match_score": jnp.where(own, 0.0, jnp.take_along_axis(result.score, jnp.maximum(rank, 0), 1)),
    }


class Stage1:
    """Stage 1 with its database on the device. Call it on one object, or `batch` on many.

    share: another Stage1 on the same database whose matching coefficients (`match_db`, a device copy
    of the database) this one reuses when both have the same `config.match`, e.g. a second Stage 1
    that differs only in its filters."""

    def __init__(self, db: PrimitiveDB | None = None, config: Stage1Config = Stage1Config(), share: Stage1 | None = None):
        enable_compilation_cache()
        self.db = load_database(DBConfig()) if db is None else db
        self.config = config
        if share is not None and share.db is self.db and share.config.match == config.match:
            self.match_db = share.match_db
        else:
            self.match_db = MatchDB.from_db(self.db, config.match)

    def off_table(self, points: np.ndarray, plane) -> np.ndarray:
        """Which of points [N, 3] can be obstacles: bool [N], False within `table_band` above the support
        plane plane [4] (None: all True). Filter (v) judges the table exactly; the planner drops these
        points once per scene, before each object's crop, which repeats this test."""
        return _off_table(points, _planes(plane, 1)[0], self.config.table_band)

    def _crop_scene(self, scene: np.ndarray, obj: np.ndarray, seed: int, plane: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The obstacles near the object: scene points within scene_margin of its box that are not the
        object's own (farther than target_exclusion from every object point) nor the table (within
        table_band above the support plane [4]), padded to max_scene_points; more than that many are
        thinned on the `obstacle_voxel` grid, then subsampled."""
        from scipy.spatial import cKDTree

        cfg = self.config
        lo, hi = obj.min(0) - cfg.scene_margin, obj.max(0) + cfg.scene_margin
        near = scene[np.all((scene >= lo) & (scene <= hi), axis=1)]
        near = near[_off_table(near, plane, cfg.table_band)]
        if len(near):
            # Only points in the object's own box (grown by the exclusion radius) can be that close to it.
            ex = cfg.target_exclusion
            close = np.flatnonzero(np.all((near >= obj.min(0) - ex) & (near <= obj.max(0) + ex), axis=1))
            own = np.zeros(len(near), bool)
            if len(close):
                own[close] = cKDTree(obj).query(near[close], distance_upper_bound=ex)[0] <= ex
            near = near[~own]
        if cfg.obstacle_voxel > 0 and len(near) > cfg.max_scene_points:
            near = pointcloud.voxel_downsample(near, cfg.obstacle_voxel)[0]
        near = pointcloud.downsample(near, cfg.max_scene_points, seed) if len(near) else near
        out = np.zeros((cfg.max_scene_points, 3), np.float32)
        out[: len(near)] = near
        return out, np.arange(cfg.max_scene_points) < len(near)

    def _crops(self, scenes, clouds, seed: int, plane: np.ndarray, b: int) -> tuple[np.ndarray, np.ndarray]:
        """The obstacle crops of b batch slots (`_crop_scene`, seed + i for slot i): scenes (items None or
        [S_i, 3]) and clouds for the first len(scenes) slots, plane [b, 4] -> (scene [b, max_scene_points, 3],
        mask [b, max_scene_points]); slots without obstacles are all padding."""
        scene = np.zeros((b, self.config.max_scene_points, 3), np.float32)
        mask = np.zeros(scene.shape[:2], bool)
        for i, s in enumerate(scenes):
            if s is not None:
                # Obstacles need no shape test (a table alone is flat), only finite points.
                s = pointcloud.as_points(s, f"scene cloud {i}")
                if len(s):
                    scene[i], mask[i] = self._crop_scene(s, clouds[i], seed + i, plane[i])
        return scene, mask

    def batch(self, objects, scenes=None, viewpoints=None, seed: int = 0, support_plane=None) -> list[Candidates]:
        """Candidates for B objects in one compiled call.

        objects: sequence of clouds [N_i, 3]; scenes: None or a sequence (items None or [S_i, 3], S_i may be 0);
        viewpoints: None or [B, 3]; support_plane: None, [4] or [B, 4], the table as (n, d) with free
        space n . x + d > 0 (filter (v)). Bad clouds give an empty Candidates with the reason, not an
        error (the single-object `__call__` raises instead).
        """
        cfg = self.config
        if len(objects) == 0:
            raise pointcloud.CloudError("no object clouds given")
        clouds, bad = [], {}
        for i, o in enumerate(objects):
            try:
                clouds.append(pointcloud.as_cloud(o, f"object cloud {i}"))
            except pointcloud.CloudError as exc:
                if np.ndim(o) != 2 or np.shape(o)[-1] != 3:
                    raise  # a wrong shape is a programming error, not a bad observation
                bad[i] = str(exc)
                clouds.append(np.zeros((1, 3)))  # fitted as invalid, reported with the message above
        obj, obj_mask = pointcloud.pad_clouds(clouds, cfg.max_object_points, seed, n_points=cfg.max_object_points)
        b = len(clouds)
        plane = _planes(support_plane, b)
        has_scene = scenes is not None and any(s is not None for s in scenes)
        if has_scene:
            if len(scenes) != b:
                raise ValueError(f"got {b} object clouds but {len(scenes)} scene clouds")
            scene, scene_mask = self._crops(scenes, clouds, seed, plane, b)
        else:
            scene, scene_mask = np.zeros((b, 1, 3), np.float32), np.zeros((b, 1), bool)
        view = np.zeros((b, 3), np.float32) if viewpoints is None else np.asarray(viewpoints, np.float32).reshape(b, 3)
        # Filter (ii) counts the observed points between the fingers, not the subsample's.
        scale = np.array([len(c) for c in clouds], np.float32) / np.maximum(obj_mask.sum(1), 1)
        neighbours = knn_indices(obj, obj_mask, cfg.filter.normal_neighbours)
        has_view = viewpoints is not None
        # Exported once to the cache (jit-compiled as ever): a new process skips the ~10-40 s of tracing EMS.
        out = exported.call(
            "stage1", functools.partial(_pipeline, cfg=cfg, has_scene=has_scene, has_view=has_view),
            (obj, obj_mask, scene, scene_mask, view, plane, scale, neighbours, self.match_db), (cfg, has_scene, has_view),
        )
        out = jax.tree_util.tree_map(np.asarray, out)
        return [_empty({"transferred": 0, "kept": 0}, bad[i], None) if i in bad else self._unpack(out, i) for i in range(b)]

    def chunked(self, objects, scenes, viewpoint, seed: int = 0, support_plane=None, sizes=(4,)) -> list[Candidates]:
        """`batch` over any number of objects in chunks of the given batch sizes, so that a scene of any
        size compiles at most len(sizes) shapes: each chunk takes the largest size that fits the objects
        left, and the smallest size is padded with dummy clouds (reported bad, dropped) when none fits.

        objects: sequence of clouds [N_i, 3]; scenes: a sequence of the same length (items None or
        [S_i, 3]); viewpoint [3] (shared); seed, support_plane as in `batch`.
        """
        if len(scenes) != len(objects):
            raise ValueError(f"got {len(objects)} object clouds but {len(scenes)} scene clouds")
        view = np.asarray(viewpoint, np.float64).reshape(3)
        out: list[Candidates] = []
        for begin, size, count in _chunks(len(objects), sizes):
            pad = size - count
            result = self.batch(list(objects[begin : begin + count]) + [np.zeros((1, 3))] * pad,
                                list(scenes[begin : begin + count]) + [None] * pad, np.tile(view, (size, 1)),
                                seed + begin, support_plane)
            out.extend(result[:count])
        return out

    def rescene(self, previous: list[Candidates], objects, scenes, viewpoint, seed: int = 0, support_plane=None,
                sizes=(4,)) -> list[Candidates]:
        """Filter (iv) again, on other obstacles, for objects Stage 1 has already seen: the candidates of
        each `previous` result that reached (iv) (`Candidates.before_scene`) are tested against the obstacle
        crop of its scene, as `chunked` would crop it, with nothing else recomputed (no fit, no matching,
        no other filter). For an object whose cloud has not changed since, e.g. while a neighbour was
        grasped: `Stage1Memory` decides that.

        previous: Candidates with before_scene; objects: their clouds now [N_i, 3] (the crop leaves them
        out); scenes: obstacles now (items None or [S_i, 3]; None and empty alike: nothing to meet);
        viewpoint [3]; seed, support_plane, sizes as in `chunked` -> one Candidates per object, its counts
        updated with the new (iv): what `chunked` gives with these obstacles (given as arrays, so that
        (iv) and its `scene_slots` apply), from the same object clouds and seed.
        """
        cfg = self.config
        if not (len(previous) == len(objects) == len(scenes)):
            raise ValueError(f"got {len(previous)} previous results, {len(objects)} object and {len(scenes)} scene clouds")
        if any(p.before_scene is None for p in previous):
            raise ValueError("rescene needs results of Stage1.batch / chunked (Candidates.before_scene)")
        slots = cfg.max_candidates  # every candidate that passed (i)-(iii) and (v); (iv) takes them in windows
        has_view = viewpoint is not None
        view = np.asarray(viewpoint if has_view else np.zeros(3), np.float32).reshape(3)
        out: list[Candidates] = []
        for begin, size, count in _chunks(len(objects), sizes):
            poses = np.tile(np.eye(4, dtype=np.float32), (size, slots, 1, 1))
            widths = np.zeros((size, slots), np.float32)
            active = np.zeros((size, slots), bool)
            for i in range(count):
                before = previous[begin + i].before_scene
                k = len(before["widths"])
                poses[i, :k], widths[i, :k], active[i, :k] = before["poses"], before["widths"], True
            clouds = [pointcloud.as_cloud(o, f"object cloud {i}") for i, o in enumerate(objects[begin : begin + count])]
            scene, scene_mask = self._crops(scenes[begin : begin + count], clouds, seed + begin, _planes(support_plane, size),
                                            size)
            hit = exported.call("stage1_rescene", functools.partial(_rescene, cfg=cfg, has_view=has_view),
                                (poses, widths, active, scene, scene_mask, np.tile(view, (size, 1))),
                                (cfg.spec, cfg.filter, has_view))
            hit, untested = (np.asarray(x) for x in hit)
            for i in range(count):
                prev = previous[begin + i]
                reached = len(prev.before_scene["widths"])
                collided, skipped = hit[i, :reached], untested[i, :reached]
                clear = ~collided & ~skipped
                counts = dict(prev.counts, collision_scene=int(collided.sum()), kept=int(clear.sum()),
                              scene_untested=int(skipped.sum()))
                if not counts["kept"]:
                    out.append(_empty(counts, _reason(counts, cfg), prev.superquadric, prev.before_scene))
                else:
                    out.append(_selected(prev.before_scene, np.flatnonzero(clear), prev.superquadric, counts,
                                         prev.before_scene))
        return out

    def collisions(self, object_points, scene_points, poses, widths, viewpoint=None, seed: int = 0,
                   support_plane=None, lift: bool = False) -> dict[str, np.ndarray]:
        """Stage 1's collision tests (`filters.pose_collisions`: (i) target, (iv) obstacles, (v) table) on
        given grasps of one object, with the object cloud and obstacle crop prepared as `batch` prepares
        them: for poses Stage 1 did not make, such as refined ones, before they are executed.

        object_points [N, 3]; scene_points [S, 3] or None (obstacles: the scene without the target);
        poses [K, 4, 4], widths [K]; viewpoint [3] or None; support_plane [4] or None; lift: first back
        poses that reach into the support plane off it along their approach, as Stage 1 does with its
        candidates (`filters.lift_to_plane`, at most `max_lift`), and test those
        -> {"collision_object", "collision_scene", "below_support", "collides"}: each bool [K], and
        "poses" [K, 4, 4] (float32): the poses tested (lifted or as given).
        Shapes are padded (K to a multiple of POSE_SLOTS), so repeated calls do not recompile.
        """
        cfg = self.config
        cloud = pointcloud.as_cloud(object_points, "object cloud")
        poses = np.asarray(poses, np.float32)
        widths = np.asarray(widths, np.float32)
        if poses.ndim != 3 or poses.shape[1:] != (4, 4) or widths.shape != poses.shape[:1]:
            raise ValueError(f"need poses [K, 4, 4] and widths [K], got {poses.shape} and {widths.shape}")
        k = len(poses)
        slots = max(POSE_SLOTS, -(-k // POSE_SLOTS) * POSE_SLOTS)
        padded_poses = np.tile(np.eye(4, dtype=np.float32), (slots, 1, 1))
        padded_widths = np.zeros(slots, np.float32)
        padded_poses[:k], padded_widths[:k] = poses, widths
        obj, obj_mask = pointcloud.pad_clouds([cloud], cfg.max_object_points, seed, n_points=cfg.max_object_points)
        plane = _planes(support_plane, 1)[0]
        scene, scene_mask = np.zeros((cfg.max_scene_points, 3), np.float32), np.zeros(cfg.max_scene_points, bool)
        if scene_points is not None:
            s = pointcloud.as_points(scene_points, "scene cloud")
            if len(s):
                scene, scene_mask = self._crop_scene(s, cloud, seed, plane)
        has_view = viewpoint is not None
        view = np.zeros(3, np.float32) if viewpoint is None else np.asarray(viewpoint, np.float32).reshape(3)

        def check(p, w, o, om, s, sm, pl, v):
            if lift:
                p = lift_to_plane(p, w, pl, cfg.spec, cfg.filter.support_clearance, cfg.max_lift)[0]
            return p, pose_collisions(p, w, o, om, s, sm, pl, cfg.spec, cfg.filter, v if has_view else None)

        tested, out = exported.call("pose_collisions", check,
                                    (padded_poses, padded_widths, obj[0], obj_mask[0], scene, scene_mask, plane, view),
                                    (cfg.spec, cfg.filter, cfg.max_object_points, cfg.max_scene_points, has_view,
                                     lift and cfg.max_lift))
        out = {name: np.asarray(value)[:k] for name, value in out.items()}
        out["collides"] = out["collision_object"] | out["collision_scene"] | out["below_support"]
        out["poses"] = np.asarray(tested)[:k]
        return out

    def _unpack(self, out: dict, i: int) -> Candidates:
        fit = jax.tree_util.tree_map(lambda x: x[i], out["fit"])
        if not fit.valid:
            return _empty({"transferred": 0, "kept": 0}, pointcloud.describe_status(int(fit.status)), fit)
        filt = jax.tree_util.tree_map(lambda x: x[i], out["filter"])
        counts = removal_counts(filt, out["valid"][i])
        counts["truncated"] = int(out["total_valid"][i]) - counts["transferred"]
        arrays = {name: out[name][i] for name in ("poses", "widths", "primitive_id", "template_id", "match_rank",
                                                   "match_score")}
        arrays["points_between"] = filt.points_between
        # Every candidate that reached (iv), tested or not, in match order: `rescene` runs (iv)'s windows again.
        reached = np.flatnonzero(filt.keep | filt.collision_scene | filt.scene_untested)
        before_scene = {name: value[reached] for name, value in arrays.items()}
        if not filt.keep.any():
            return _empty(counts, _reason(counts, self.config), fit, before_scene)
        return _selected(arrays, np.flatnonzero(filt.keep), fit, counts, before_scene)

    def __call__(self, object_points, scene_points=None, viewpoint=None, seed: int = 0, support_plane=None) -> Candidates:
        """Candidates for one object cloud [N, 3]; raises CloudError naming the problem for bad input."""
        cloud = pointcloud.as_cloud(object_points, "object cloud")  # raises for empty/NaN/too few/flat clouds
        views = None if viewpoint is None else np.asarray(viewpoint, np.float32)[None]
        return self.batch([cloud], None if scene_points is None else [scene_points], views, seed, support_plane)[0]


def _chunks(n: int, sizes) -> list[tuple[int, int, int]]:
    """How `Stage1.chunked` splits n objects over batch sizes: (begin, size, count) per batch. Each takes
    the largest size that fits the objects left, and the smallest size (padded) when none fits."""
    sizes = sorted({int(b) for b in sizes})
    if not sizes or sizes[0] < 1:
        raise ValueError(f"batch sizes must be positive integers, got {sizes}")
    out, begin = [], 0
    while begin < n:
        size = max((b for b in sizes if b <= n - begin), default=sizes[0])
        count = min(size, n - begin)
        out.append((begin, size, count))
        begin += count
    return out


def _rescene(poses, widths, active, scene, scene_mask, viewpoint, cfg: Stage1Config, has_view: bool):
    """Filter (iv) over B objects' candidates as Stage 1 runs it (`windowed_scene_test`): poses [B, T, 4, 4],
    widths [B, T], active [B, T] (the candidates that reached (iv), first), scene [B, S, 3], scene_mask
    [B, S], viewpoint [B, 3] -> (collision bool [B, T], untested bool [B, T]). Object by object
    (`lax.map`), so that each pays only for the windows it needs."""
    def one(args):
        p, w, a, s, sm, v = args
        return windowed_scene_test(p, w, a, s, sm, cfg.spec, cfg.filter, v if has_view else None)

    return jax.lax.map(one, (poses, widths, active, scene, scene_mask, viewpoint))


def knn_indices(points: np.ndarray, mask: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """`filters.nearest_neighbours` on the host with a k-d tree: points [B, N, 3], mask [B, N] ->
    (index int32 [B, N, k], ok bool [B, N, k]), k capped at N. Same sets up to ties in distance."""
    from scipy.spatial import cKDTree

    b, n, _ = points.shape
    k = min(k, n)
    index, ok = np.zeros((b, n, k), np.int32), np.zeros((b, n, k), bool)
    for i in range(b):
        valid = np.flatnonzero(mask[i])
        kk = min(k, len(valid))
        if kk == 0:
            continue
        _, j = cKDTree(points[i, valid]).query(points[i], kk)
        index[i, :, :kk] = valid[np.asarray(j).reshape(n, kk)]
        ok[i, :, :kk] = True
    return index, ok


def _off_table(points: np.ndarray, plane: np.ndarray, band: float) -> np.ndarray:
    """points [N, 3], a unit-normal plane [4] from `_planes` -> bool [N]: not within band above it."""
    if not np.any(plane[:3] != 0.0):  # NO_PLANE
        return np.ones(len(points), bool)
    return points @ plane[:3] + plane[3] >= band


def _planes(support_plane, b: int) -> np.ndarray:
    """None / [4] / [B, 4] -> [B, 4] float32 unit-normal planes (NO_PLANE where None)."""
    if support_plane is None:
        return np.tile(np.asarray(NO_PLANE, np.float32), (b, 1))
    plane = np.asarray(support_plane, np.float64)
    if plane.shape not in ((4,), (b, 4)):
        raise ValueError(f"support_plane must have shape [4] or [{b}, 4], got {plane.shape}")
    plane = np.broadcast_to(plane, (b, 4))
    norm = np.linalg.norm(plane[:, :3], axis=1)
    if not np.isfinite(plane).all() or (norm < 1e-9).any():
        raise ValueError(f"support_plane must be finite with a non-zero normal, got {plane.tolist()}")
    return (plane / norm[:, None]).astype(np.float32)


@functools.lru_cache(maxsize=4)
def _default_stage1(config: Stage1Config) -> Stage1:
    return Stage1(None, config)


def generate_candidates(
    object_points,
    scene_points=None,
    *,
    db: PrimitiveDB | None = None,
    config: Stage1Config = Stage1Config(),
    viewpoint=None,
    seed: int = 0,
    support_plane=None,
) -> Candidates:
    """Stage-1 grasp candidates for one object cloud [N, 3] (metres), optionally avoiding a scene cloud.

    Uses the default database from the cache (built on first use) unless `db` is given. For many
    objects, build one `Stage1(db, config)` and call `.batch(...)`.
    """
    stage = _default_stage1(config) if db is None else Stage1(db, config)
    return stage(object_points, scene_points, viewpoint, seed, support_plane)
