"""Why an object is left on the table: is it graspable at all, and do Stage 1's candidates include the
grasps that work? (run by hand; prints a markdown table).

    python benchmarks/object_graspability.py --objects unseen --names superquadric_006,superquadric_003
                                             [--drops 4] [--model RUN_DIR] [--relabel-axes] [--json OUT]

Each named object is dropped alone on the table `--drops` times (seeded scenes, `envs.scene.make_scene`),
seen by the benchmark's camera, and these grasps are simulated with the benchmark's trial (lift,
reorient, 1 N):

  oracle     top-down grasps from the ground-truth mesh (`eval.oracle.top_down_candidates`: the mesh's two
             most horizontal axes and 24 yaws, fingertips 4 / 8 / 12 / 18 / 25 / 35 mm below the top, at
             least 3 mm above the table): whether the object can be picked up at all as it lies
  stage1     Stage 1's transferred candidates that pass only the collision and table tests ((i), (v):
             point count, normal test and the extra filters off): what the primitive matching offers
  default    those of them the planner's default filter keeps, and `fallback` those its fallback keeps
  passed     those of them E-RNet scores above 0.7

Per object: successes / grasps per column, and the best E-RNet score. `--relabel-axes`: Stage 1 with
`MatchConfig(relabel_axes=True)` (the fit's axes also matched relabelled). The same seed gives the same
scenes and outcomes.
"""

from __future__ import annotations

import argparse
import dataclasses
import json

import numpy as np

from envs import camera as camera_lib
from envs import scene as scene_lib
from envs import trial as trial_lib
from envs.scene import stage2_scene_cloud
from eval import declutter
from eval.benchmark import resolve_objects
from eval.oracle import top_down_candidates
from sgjax.geometry.pointcloud import table_plane
from sgjax.planner import FALLBACK_FILTER, Planner, PlannerConfig
from sgjax.stage1.filters import FilterConfig
from sgjax.stage1.matching import MatchConfig
from sgjax.stage1.pipeline import Stage1, Stage1Config
from sgjax.stage2 import ernet

# (ii), (iii) and the extra filters off: only the gripper meeting the object (i) or the table (v) removes.
OPEN_FILTER = FilterConfig(shadow_depth=0.0, hidden_contacts="accept", max_normal_angle_deg=89.9, min_points=1)
ORACLE_DEPTHS = (0.004, 0.008, 0.012, 0.018, 0.025, 0.035)


def _keys(c) -> set:
    return {(int(p), int(t)) for p, t in zip(c.primitive_id, c.template_id)}


def probe(asset, drops: int, planner: Planner, config: declutter.DeclutterConfig) -> dict:
    """Successes / grasps per column (module doc) over `drops` seeded single-object scenes."""
    stages = {name: Stage1(planner.stage1.db, dataclasses.replace(planner.stage1.config, filter=f), share=planner.stage1)
              for name, f in (("stage1", OPEN_FILTER), ("fallback", FALLBACK_FILTER))}
    stages["default"] = planner.stage1
    view = np.asarray(config.camera.position, np.float64)
    counts = {k: [0, 0] for k in ("oracle", "stage1", "default", "fallback", "passed")}
    best = 0.0
    for seed in range(drops):
        scene = scene_lib.make_scene([asset], 1, seed, config.scene, config.gripper)
        poses, widths = zip(*(top_down_candidates(scene, 0, depth=d, table_clearance=0.003, yaws=24) for d in ORACLE_DEPTHS))
        ok = np.asarray(trial_lib.run_trials(scene, 0, np.concatenate(poses), np.concatenate(widths), config=config.trial).label)
        counts["oracle"][0] += int(ok.sum())
        counts["oracle"][1] += len(ok)
        obs = camera_lib.observe(scene, config.camera, seed=seed)
        points, labels = obs.points, obs.point_labels
        plane = table_plane(points, labels)
        found = {k: s(points[labels == 0], points[labels < 0], view, seed, plane) for k, s in stages.items()}
        cands = found["stage1"]
        if not len(cands):
            continue
        ok = np.asarray(trial_lib.run_trials(scene, 0, cands.poses, np.clip(cands.widths, 0, config.gripper.max_opening),
                                             config=config.trial).label)
        cloud, mask, _ = planner.config.scene_cloud.make(points, None, seed)
        scores = np.asarray(ernet.score(planner.graphdef, planner.state, cloud, cands.poses.astype(np.float32),
                                        cands.widths.astype(np.float32), mask, spec=config.gripper).eval_prob)
        best = max(best, float(scores.max()))
        pairs = list(zip(cands.primitive_id.tolist(), cands.template_id.tolist()))
        kept = {k: _keys(found[k]) for k in ("default", "fallback")}
        groups = {"stage1": np.ones(len(ok), bool), "passed": scores > planner.config.eval_threshold,
                  **{k: np.array([p in keys for p in pairs], bool) for k, keys in kept.items()}}
        for k, rows in groups.items():
            counts[k][0] += int(ok[rows].sum())
            counts[k][1] += int(rows.sum())
    return {"counts": counts, "best_score": best}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--objects", default="unseen", help="object set (default unseen)")
    parser.add_argument("--names", required=True, help="comma-separated object names (suffixes of the set's names)")
    parser.add_argument("--drops", type=int, default=4)
    parser.add_argument("--model", default=None, help="E-RNet run directory (default: the shipped one)")
    parser.add_argument("--relabel-axes", action="store_true", help="Stage 1 with MatchConfig(relabel_axes=True)")
    parser.add_argument("--json", default=None, help="also write the results here")
    args = parser.parse_args()
    assets, _, _ = resolve_objects(declutter.get_setting("seen-10"), args.objects)
    config = declutter.DeclutterConfig()
    stage1 = Stage1Config(match=MatchConfig(relabel_axes=args.relabel_axes))
    planner = Planner(args.model, config=PlannerConfig(stage1=stage1, scene_cloud=stage2_scene_cloud(), fallback_filter=None))
    results = {}
    print("| object | oracle top-down | Stage 1, (i) + (v) only | default filter keeps | fallback keeps | E-RNet > 0.7 | best score |")
    print("|---|---:|---:|---:|---:|---:|---:|")
    for name in args.names.split(","):
        matches = [a for a in assets if a.name.endswith(name)]
        if len(matches) != 1:
            raise SystemExit(f"{name!r} names {len(matches)} objects of {args.objects!r}; give a unique suffix")
        out = results[matches[0].name] = probe(matches[0], args.drops, planner, config)
        cells = [f"{ok} / {n}" for ok, n in out["counts"].values()]
        print(f"| {matches[0].name} | " + " | ".join(cells) + f" | {out['best_score']:.2f} |", flush=True)
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(results, fh, indent=1)


if __name__ == "__main__":
    main()
