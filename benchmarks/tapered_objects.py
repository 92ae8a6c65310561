"""Single views of tapered objects against cylinders: how often the grasps SuperGrasp would execute succeed
(run by hand; prints a markdown table).

    python benchmarks/tapered_objects.py [--placements 8] [--top 8] [--small-db] [--model RUN_DIR]
                                         [--objects tapered|flat] [--no-fit-grasps] [--seed 0] [--json OUT]

A superquadric cannot taper, so a frustum's single-view fit is a cylinder or a box and its matched
primitives are rarely frusta (docs/limitations.md). What matters to a user is whether the grasps
transferred from them work. Each object of the set (default "tapered": two cylinders, two frusta, an
open cup; `envs.objects.tapered_sources`) is placed alone on the table `--placements` times per
placement kind (standing; frusta also on their narrow end; lying on the side), at a seeded random table
position and yaw, settled, and seen by the benchmark's fixed depth camera. The default planner
(`supergrasp`'s: Stage 1 with the table plane, the shipped E-RNet, the labelling's Stage-2 scene cloud)
plans on it; then in simulation (`envs.trial.run_trials`, the benchmark's lift / reorient / 1 N trial):

  chosen   the grasp the planner executes (one per placement; "none" counts as a failure)
  top      its `--top` best-scored candidates by E-RNet (those that pass 0.7 and the rest)
  stage1   up to `--top` Stage-1 candidates, spread evenly over its list (what Stage 1 offers)

Rows per object and placement kind, then per shape class (cylinder / frustum / cup). The same seed gives
the same placements and outcomes.

`--objects flat` (two lenses, a pebble, a puck, a tile; `envs.objects`) places each flat on its largest face
("standing": its thin z axis up). `--no-fit-grasps`: the planner without its top-down grasps on the fit
(`PlannerConfig.fit_grasps = None`, the paper's candidates).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from envs.objects import load_object_set  # noqa: E402
from eval import single_object  # noqa: E402
from eval.report import markdown_table  # noqa: E402


def kinds_for(name: str) -> tuple[str, ...]:
    # Cylinders and the cup have no narrow end to stand on (an upside-down cup is a frustum shell); flat
    # objects rest on their largest face (z up).
    if name.startswith("flat/"):
        return ("standing",)
    return single_object.KINDS if single_object.shape_class(name) == "frustum" else ("standing", "lying")


def run(args) -> list[dict]:
    from eval.supergrasp import PlannerMethod

    config = None
    if args.no_fit_grasps:
        from envs.scene import stage2_scene_cloud
        from sgjax.planner import PlannerConfig

        config = PlannerConfig(scene_cloud=stage2_scene_cloud(), fit_grasps=None)
    method = PlannerMethod("supergrasp", True, model=args.model, small_db=args.small_db, config=config)
    rng = np.random.default_rng(args.seed)
    rows = []
    for asset in load_object_set(args.objects):
        for kind in kinds_for(asset.name):
            for i, pose in enumerate(single_object.placements(asset.extents, kind, args.placements, rng)):
                seed = int(rng.integers(2**31))
                setup = single_object.alone(asset, pose, seed)
                if setup is None:
                    continue
                plan = method.full_plan(setup.obs.points, setup.obs.point_labels, setup.viewpoint, seed)
                row = {"object": asset.name, "class": single_object.shape_class(asset.name), "kind": kind, "placement": i,
                       "candidates": int(plan.n_candidates), "chosen": 0.0, "top": None, "stage1": None,
                       "plan_kind": plan.kind, "reason": plan.reason}
                poses, widths, groups = [], [], []
                if plan.ok:
                    poses.append(plan.pose), widths.append(plan.width), groups.append("chosen")
                if plan.n_candidates:
                    top_poses, top_widths = single_object.best_scored(plan, args.top)
                    poses += top_poses
                    widths += top_widths
                    groups += ["top"] * len(top_poses)
                    c = plan.candidates[0]
                    for r in single_object.spread_rows(len(c), args.top):
                        poses.append(c.poses[r]), widths.append(c.widths[r]), groups.append("stage1")
                ok, groups = single_object.success(setup, poses, widths), np.asarray(groups)
                for g in ("chosen", "top", "stage1"):
                    if (groups == g).any():
                        row[g] = float(ok[groups == g].mean())
                rows.append(row)
                print(f"{asset.name} {kind} {i}: {row['candidates']} candidates, chosen {row['chosen']:.0f} "
                      f"top {row['top']} stage1 {row['stage1']} ({plan.kind or plan.reason[:60]})", flush=True)
    return rows


def _mean(values) -> str:
    values = [v for v in values if v is not None]
    return f"{100 * np.mean(values):.0f} %" if values else "-"


def table(rows: list[dict], key, first: str) -> str:
    groups: dict = {}
    for r in rows:
        groups.setdefault(key(r), []).append(r)
    body = [[*k, len(g), f"{np.mean([r['candidates'] for r in g]):.0f}", _mean(r["chosen"] for r in g),
             _mean(r["top"] for r in g), _mean(r["stage1"] for r in g)] for k, g in sorted(groups.items())]
    return markdown_table([first, "placement", "n", "candidates",
                           "chosen succeeds", "top candidates succeed", "Stage-1 sample succeeds"], body)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--placements", type=int, default=8, help="placements per object and kind")
    parser.add_argument("--top", type=int, default=8)
    parser.add_argument("--objects", default="tapered")
    parser.add_argument("--model", default=None, help="an E-RNet run directory (default: the shipped one)")
    parser.add_argument("--small-db", action="store_true")
    parser.add_argument("--no-fit-grasps", action="store_true", help="PlannerConfig.fit_grasps = None (the paper's candidates)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", default=None, help="also write the rows here")
    args = parser.parse_args()
    start = time.perf_counter()
    rows = run(args)
    print()
    print(table(rows, lambda r: (r["object"], r["kind"]), "object"))
    print()
    print(table(rows, lambda r: (r["class"], r["kind"]), "class"))
    print(f"\n{len(rows)} placements in {time.perf_counter() - start:.0f} s; load average {os.getloadavg()[0]:.1f}")
    if args.json:
        from sgjax.utils.files import atomic_write_text

        atomic_write_text(args.json, json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
