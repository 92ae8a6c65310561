"""Planner benchmark: Stage-1, Stage-2 and total wall time per plan on CPU, after compile (run by hand).

    python benchmarks/bench_plan.py [--repeats 5] [--small-db] [--model RUN_DIR] [--objects 5]
                                    [--setting seen-10]

Scene: a tabletop (30k points on a 60 cm table, 1 mm noise) with `--objects` boxes and cylinders
(single-view clouds of superquadrics, 1500 points each), labelled per object; camera above the table.
`plan` runs Stage 1 on every object and one Stage-2 call on all their candidates; `plan_target` runs
one object. The model is the shipped default when it exists, else a light E-RNet with random weights
(the timing does not depend on the weights; the decision does). The database is the default one from
the cache (built on first use) unless --small-db. The 2 cores of the dev machine are shared: numbers
vary with other jobs (the load average is printed). Prints a markdown table.

--setting seen-10|seen-20|unseen-10: a decluttering benchmark scene instead (scene 7 of seed 0: the
setting's objects dropped in MuJoCo, the fixed depth camera's labelled cloud, ~260k points), as
`sgjax declutter` plans it (its table plane for filter (v)).
"""

from __future__ import annotations

import argparse
import os
import statistics
import time

import jax
import numpy as np
from flax import nnx

from sgjax.geometry import synthetic
from sgjax.stage2.ernet import ERNet, ERNetConfig, load_default_model
from sgjax.planner import Planner, PlannerConfig
from sgjax.stage1.database import DBConfig, load_database
from sgjax.geometry.superquadric import Superquadric

CAMERA = np.array([0.0, -0.35, 0.75])


def make_scene(n_objects: int = 5, seed: int = 0, n_table: int = 30000, n_per_object: int = 1500):
    """-> (points [N, 3], labels [N]): table at z = 0 (label -1) and objects 0..n_objects-1 on it."""
    rng = np.random.default_rng(seed)
    clouds = [np.c_[rng.uniform(-0.3, 0.3, (n_table, 2)), rng.normal(0, 0.001, n_table)]]
    labels = [np.full(n_table, -1)]
    for k in range(n_objects):
        half = rng.uniform([0.018, 0.018, 0.025], [0.035, 0.035, 0.06])
        eps = (0.1, rng.choice([0.1, 1.0]))  # boxes and cylinders
        yaw = rng.uniform(0, np.pi)
        rot = np.array([[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1.0]])
        angle = 2 * np.pi * k / max(n_objects, 1)
        centre = np.array([0.15 * np.cos(angle), 0.15 * np.sin(angle), half[2]])
        sq = Superquadric.create(half, eps, rot, centre)
        cloud = synthetic.single_view_cloud(sq, n_per_object, view=CAMERA - centre, seed=rng)
        cloud = cloud[cloud[:, 2] > 0.002]  # the face on the table is hidden
        clouds.append(cloud)
        labels.append(np.full(len(cloud), k))
    return np.concatenate(clouds), np.concatenate(labels)


def declutter_scene(setting: str, index: int = 7):
    """-> (points [N, 3], labels [N], camera [3], table plane (n, d)): a benchmark scene's first view."""
    from envs import camera as camera_lib
    from eval.declutter import DeclutterConfig, get_setting, make_benchmark_scene
    from sgjax.geometry.pointcloud import table_plane
    from envs.objects import load_object_set

    cfg = DeclutterConfig()
    s = get_setting(setting)
    scene = make_benchmark_scene(load_object_set(s.object_set), s.n_objects, 0, index, cfg)
    obs = camera_lib.observe(scene, cfg.camera, seed=0)
    camera = np.asarray(cfg.camera.position, np.float64)
    return obs.points, obs.point_labels, camera, table_plane(obs.points, obs.point_labels)


def run(fn, repeats: int):
    """-> (first call seconds (compile + run), [Plan of each later call])."""
    t = time.perf_counter()
    fn()
    first = time.perf_counter() - t
    return first, [fn() for _ in range(repeats)]


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--small-db", action="store_true")
    parser.add_argument("--model", help="an E-RNet run directory (default: the shipped model, else random light)")
    parser.add_argument("--objects", type=int, default=5)
    parser.add_argument("--setting", help="a decluttering benchmark scene instead of the synthetic one")
    parser.add_argument("--batch-sizes", default="4", help="Stage-1 batch sizes, comma-separated (PlannerConfig)")
    args = parser.parse_args()

    if args.model:
        model, model_name = args.model, args.model
    else:
        try:
            model, model_name = load_default_model(), "shipped default"
        except FileNotFoundError:
            model, model_name = ERNet(ERNetConfig.light(), rngs=nnx.Rngs(0)), "light, random weights"
    db = load_database(DBConfig.small() if args.small_db else DBConfig())
    sizes = tuple(int(b) for b in args.batch_sizes.split(","))
    config, camera = PlannerConfig(stage1_batch_sizes=sizes), CAMERA
    if args.setting:
        points, labels, camera, plane = declutter_scene(args.setting)
        config = PlannerConfig(support_plane=plane, stage1_batch_sizes=sizes)
        args.objects = len(np.unique(labels[labels >= 0]))
    else:
        points, labels = make_scene(args.objects)
    planner = Planner(model, db, config)
    target = labels == labels[labels >= 0].min()

    print(f"jax {jax.__version__}, {jax.devices()[0].platform}, load average {os.getloadavg()[0]:.1f}; "
          f"E-RNet {model_name}; database {len(db)} primitives; scene {len(points)} points, {args.objects} objects; "
          f"Stage-1 batch sizes {sizes}; "
          f"best and median of {args.repeats} calls after compile\n")
    print("| call | first call (s) | Stage 1 (s) | Stage 2 (s) | total (s) | candidates | decision |")
    print("|---|---:|---:|---:|---:|---:|---|")
    cases = [
        (f"plan, {args.objects} objects", lambda: planner.plan(points, labels, camera, seed=0)),
        ("plan_masked, 1 target", lambda: planner.plan_masked(points, target, camera, seed=0)),
    ]
    for name, fn in cases:
        first, plans = run(fn, args.repeats)
        cols = []
        for key in ("stage1_s", "stage2_s", "total_s"):
            values = [p.timing[key] for p in plans]
            cols.append(f"{min(values):.3f} / {statistics.median(values):.3f}")
        p = plans[-1]
        decision = p.kind or f"none ({p.reason[:40]})"
        print(f"| {name} | {first:.1f} | {' | '.join(cols)} | {p.n_candidates} | {decision} |")


if __name__ == "__main__":
    main()
