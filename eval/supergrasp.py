"""`supergrasp` and `supergrasp-norefine`: thin adapters over `sgjax.planner.Planner`.

The planner is imported lazily, so the rest of the benchmark works without it. Options pass through:
`model` (an ERNet, a `sgjax train` run directory, or None for the planner's default checkpoint),
`small_db` (the small primitive database, for tests and smoke runs), `db` (a PrimitiveDB), `preset`
(a named configuration, `sgjax.presets`; the method's name becomes e.g. `supergrasp@paper` unless it is
"default") or `config` (a PlannerConfig instead), `gripper` (the GripperSpec the preset plans for, on
that gripper's primitive database; the benchmark passes its simulated gripper). `use_refinement` is set
by the method's name; a preset's Stage-2 scene cloud is cropped to the workspace and voxelised exactly as
the labelling pipeline did for training.

The table: unless the config sets `support_plane`, each plan gives the planner the plane z = median z
of the observation's table points (labels < 0), as the GPD baseline does, so Stage 1 drops grasps that
reach below the table. That is read from the observation, not from the simulator.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from eval.protocol import Decision, check_gripper, with_preset
from sgjax.geometry.pointcloud import table_plane
from sgjax.stage1.memory import Stage1Memory

TIMING_KEYS = ("stage1_s", "stage2_s", "total_s")


class PlannerMethod:
    """A `Method` over `sgjax.planner.Planner` (with or without the refinement branch)."""

    def __init__(self, name: str, use_refinement: bool, model=None, small_db: bool = False, db=None, config=None,
                 preset: str = "default", gripper=None):
        from sgjax import presets
        from sgjax.geometry.gripper import GripperSpec
        from sgjax.planner import Planner

        if config is None:  # the Stage-2 scene cloud exactly as in labelling (train/label.py)
            from envs.scene import stage2_scene_cloud

            config = presets.get(preset, gripper=gripper, scene_cloud=stage2_scene_cloud())
        elif preset != "default":
            raise ValueError("give a planner preset or a config, not both")
        else:
            check_gripper(name, config.spec, gripper)  # as every method of the registry (`eval.methods`)
        if db is None and (small_db or config.spec != GripperSpec()):
            # The database of the planner's gripper (the default one's ships; another's is built into the
            # cache on first use).
            from sgjax.stage1.database import DBConfig, load_database

            db = load_database(DBConfig.for_gripper(config.spec, small_db), progress=False)
        self.config = dataclasses.replace(config, use_refinement=use_refinement)
        self.name = with_preset(name, preset)
        self.planner = Planner(model=model, db=db, config=self.config)
        # Stage 1 of an object whose cloud has not changed since the scene's last plan is not run again
        # (`sgjax.stage1.memory`); the harness starts each scene with `begin_scene`.
        self.memory = Stage1Memory()

    def begin_scene(self) -> None:
        """A new scene: forget the last one's Stage-1 results (memory None: Stage 1 on every object)."""
        if self.memory is not None:
            self.memory.forget()

    def full_plan(self, points: np.ndarray, labels: np.ndarray, viewpoint, seed: int = 0, avoid=None):
        """The planner's whole `sgjax.planner.Plan` (candidates and scores included) for an observation
        (points [N, 3], labels [N]), with the table plane read from it as `plan` does."""
        points, labels = np.asarray(points), np.asarray(labels)
        if self.config.support_plane is None:
            plane = table_plane(points, labels)
            config = self.config if plane is None else dataclasses.replace(self.config, support_plane=plane)
            if config != self.planner.config:
                self.planner.config = config
        return self.planner.plan(points, labels, np.asarray(viewpoint, np.float64), seed, avoid, self.memory)

    def plan(self, points: np.ndarray, labels: np.ndarray, viewpoint, seed: int = 0, avoid=None) -> Decision:
        plan = self.full_plan(points, labels, viewpoint, seed, avoid)
        timing = {k: float((plan.timing or {}).get(k, 0.0)) for k in TIMING_KEYS}
        info = {"kind": plan.kind, "target": plan.target, "n_candidates": int(plan.n_candidates),
                "compiled": bool((plan.timing or {}).get("compiled", False))}
        if plan.refinements_rejected:
            info["refinements_rejected"] = int(plan.refinements_rejected)
        if plan.fallback:
            info["fallback"] = True
        if plan.reused:
            info["reused"] = int(plan.reused)
        if plan.candidate_index is not None and plan.scores:
            # A grasp on the fitted superquadric itself (`sgjax.stage1.fit_grasps`), not a transferred one.
            row = plan.candidate_index
            cands = plan.candidates[int(plan.scores["object"][row])]
            if cands.primitive_id[int(plan.scores["object_candidate"][row])] < 0:
                info["fit_grasp"] = True
            robust = plan.scores.get("robust_score")
            if robust is not None and np.isfinite(robust[row]):
                # `PlannerConfig.robust`: how many judged candidates evaluated higher than the one executed
                # (0: the paper's choice too).
                info["robust_rank"] = int(np.sum(np.isfinite(robust) & (plan.scores["eval_prob"] > plan.scores["eval_prob"][row])))
        if plan.pose is None:
            return Decision(None, 0.0, 0.0, plan.reason or "no grasp", timing, info)
        return Decision(np.asarray(plan.pose, np.float64), float(plan.width), float(plan.score), "", timing, info)
