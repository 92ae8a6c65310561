"""Planner benchmark: Stage-1, Stage-2 and total wall time per plan on CPU, after compile (run by hand).

    python -m benchmarks.bench_plan [--repeats 5] [--small-db] [--model RUN_DIR] [--objects 5]
                                    [--setting seen-10] [--scenes 7] [--reference COMMIT] [--rounds 2]

Scene: a tabletop (30k points on a 60 cm table, 1 mm noise) with `--objects` boxes and cylinders
(single-view clouds of superquadrics, 1500 points each), labelled per object; camera above the table.
`plan` runs Stage 1 on every object and one Stage-2 call on all their candidates; `plan_masked` runs
one object. The model is the shipped default when it exists, else a light E-RNet with random weights
(the timing does not depend on the weights; the decision does). The database is the default one from
the cache (built on first use) unless --small-db. The load average is printed: the 2 cores of the dev
machine are shared, so compare numbers of one run only.

--setting seen-10|seen-20|unseen-10: decluttering benchmark scenes instead (--scenes: comma-separated
scene indices of seed 0, default 7: the setting's objects dropped in MuJoCo, the fixed depth camera's
labelled first view, ~260k points), planned as `sgjax declutter` plans them (its table plane for filter (v)).

--reference COMMIT: also time the planner of another commit (e.g. the one before a speed-up) on the same
scenes, in alternating rounds (--rounds) of separate processes, and print both, their ratio and whether
each plan chose the same grasp. The commit is checked out once as a git worktree under
$SGJAX_CACHE/bench/; the scenes are made here, by the current code, and handed to both.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time

import numpy as np

CAMERA = np.array([0.0, -0.35, 0.75])
KEYS = ("stage1_s", "stage2_s", "total_s")


def make_scene(n_objects: int = 5, seed: int = 0, n_table: int = 30000, n_per_object: int = 1500):
    """-> (points [N, 3], labels [N]): table at z = 0 (label -1) and objects 0..n_objects-1 on it."""
    from sgjax.geometry import synthetic
    from sgjax.geometry.superquadric import Superquadric

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
    from envs.objects import load_object_set
    from eval.declutter import DeclutterConfig, get_setting, make_benchmark_scene
    from sgjax.geometry.pointcloud import table_plane

    cfg = DeclutterConfig()
    s = get_setting(setting)
    scene = make_benchmark_scene(load_object_set(s.object_set), s.n_objects, 0, index, cfg)
    obs = camera_lib.observe(scene, cfg.camera, seed=0)
    camera = np.asarray(cfg.camera.position, np.float64)
    return obs.points, obs.point_labels, camera, table_plane(obs.points, obs.point_labels)


def save_scenes(args, path: str) -> list[str]:
    """Make the scenes to plan and save them to path (.npz) -> their names."""
    arrays, names = {}, []
    if args.setting:
        for i, index in enumerate(int(s) for s in args.scenes.split(",")):
            points, labels, camera, plane = declutter_scene(args.setting, index)
            arrays.update({f"points{i}": points, f"labels{i}": labels, f"camera{i}": camera, f"plane{i}": np.asarray(plane)})
            names.append(f"{args.setting} scene {index}")
    else:
        points, labels = make_scene(args.objects)
        arrays.update({"points0": points, "labels0": labels, "camera0": CAMERA, "plane0": np.full(4, np.nan)})
        names.append(f"synthetic, {args.objects} objects")
    np.savez(path, **arrays)
    return names


def worker(scenes_path: str, out_path: str, repeats: int, model_dir: str | None, small_db: bool, sizes) -> None:
    """Plan every saved scene (`plan` over all objects, then `plan_masked` on its first object) with the
    sgjax importable here, and write the timings and choices to out_path (JSON)."""
    import jax
    from flax import nnx

    from sgjax.planner import Planner, PlannerConfig
    from sgjax.stage1.database import DBConfig, load_database
    from sgjax.stage2.ernet import ERNet, ERNetConfig, load_default_model

    if model_dir:
        model, model_name = model_dir, model_dir
    else:
        try:
            model, model_name = load_default_model(), "shipped default"
        except FileNotFoundError:
            model, model_name = ERNet(ERNetConfig.light(), rngs=nnx.Rngs(0)), "light, random weights"
    db = load_database(DBConfig.small() if small_db else DBConfig())
    data = np.load(scenes_path)
    results, planners = [], {}
    for i in range(sum(k.startswith("points") for k in data.files)):
        points, labels, camera, plane = (data[f"{k}{i}"] for k in ("points", "labels", "camera", "plane"))
        plane = None if np.isnan(plane).any() else tuple(float(v) for v in plane)
        if plane not in planners:
            planners[plane] = Planner(model, db, PlannerConfig(support_plane=plane, stage1_batch_sizes=sizes))
        planner = planners[plane]
        target = labels == labels[labels >= 0].min()
        for case, fn in (("plan", lambda: planner.plan(points, labels, camera, seed=0)),
                         ("plan_masked", lambda: planner.plan_masked(points, target, camera, seed=0))):
            start = time.perf_counter()
            fn()
            first = time.perf_counter() - start
            plans = [fn() for _ in range(repeats)]
            last = plans[-1]
            results.append({
                "scene": i, "case": case, "first_s": first,
                **{key: [p.timing[key] for p in plans] for key in KEYS},
                "objects": int(len(np.unique(labels[labels >= 0]))), "points": int(len(points)),
                "candidates": int(last.n_candidates), "kind": last.kind, "target": last.target,
                "pose": None if last.pose is None else np.asarray(last.pose).tolist(), "reason": last.reason,
            })
    import sgjax

    info = {"sgjax": os.path.dirname(os.path.dirname(sgjax.__file__)), "jax": jax.__version__, "platform": jax.devices()[0].platform, "model": model_name, "db": len(db)}
    with open(out_path, "w") as f:
        json.dump({"info": info, "results": results}, f)


def run_worker(tree: str, scenes_path: str, args, tmp: str, tag: str) -> dict:
    """This script's worker in a new process, importing sgjax (and envs, eval) from tree."""
    out = os.path.join(tmp, f"{tag}.json")
    cmd = [sys.executable, os.path.abspath(__file__), "--worker", scenes_path, "--worker-out", out,
           "--repeats", str(args.repeats), "--batch-sizes", args.batch_sizes]
    cmd += ["--model", args.model] if args.model else []
    cmd += ["--small-db"] if args.small_db else []
    env = dict(os.environ, PYTHONPATH=tree + os.pathsep + os.environ.get("PYTHONPATH", ""))
    subprocess.run(cmd, check=True, env=env, cwd=tree)
    with open(out) as f:
        return json.load(f)


def _merge(runs: list[dict]) -> list[dict]:
    """Rounds of one code -> per (scene, case) row with every round's timings pooled."""
    rows = [dict(r) for r in runs[0]["results"]]
    for run in runs[1:]:
        for row, r in zip(rows, run["results"]):
            for key in KEYS + ("first_s",):
                row[key] = (row[key] if isinstance(row[key], list) else [row[key]]) + (
                    r[key] if isinstance(r[key], list) else [r[key]])
    return rows


def _cell(values) -> str:
    values = values if isinstance(values, list) else [values]
    return f"{min(values):.3f} / {statistics.median(values):.3f}"


def _decision(row: dict) -> str:
    return row["kind"] or f"none ({(row['reason'] or '')[:40]})"


def _same(a: dict, b: dict) -> str:
    if a["kind"] is None or b["kind"] is None:
        return "yes" if a["kind"] == b["kind"] else "no"
    close = a["target"] == b["target"] and np.allclose(a["pose"], b["pose"], atol=1e-4)
    return "yes" if close else "no"


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--small-db", action="store_true")
    parser.add_argument("--model", help="an E-RNet run directory (default: the shipped model, else random light)")
    parser.add_argument("--objects", type=int, default=5)
    parser.add_argument("--setting", help="decluttering benchmark scenes instead of the synthetic one")
    parser.add_argument("--scenes", default="7", help="with --setting: comma-separated scene indices (seed 0)")
    parser.add_argument("--batch-sizes", default="1,2,4", help="Stage-1 batch sizes, comma-separated (PlannerConfig)")
    parser.add_argument("--reference", help="also time this commit's planner on the same scenes")
    parser.add_argument("--rounds", type=int, default=2, help="with --reference: alternating rounds per code")
    parser.add_argument("--worker", help=argparse.SUPPRESS)
    parser.add_argument("--worker-out", help=argparse.SUPPRESS)
    args = parser.parse_args()
    sizes = tuple(int(b) for b in args.batch_sizes.split(","))
    if args.worker:
        worker(args.worker, args.worker_out, args.repeats, args.model, args.small_db, sizes)
        return
    from benchmarks.common import REPO, reference_tree  # not in the worker: a reference tree may predate it

    with tempfile.TemporaryDirectory() as tmp:
        scenes_path = os.path.join(tmp, "scenes.npz")
        names = save_scenes(args, scenes_path)
        trees = {"current": REPO}
        if args.reference:
            trees = {f"reference {args.reference}": reference_tree(args.reference), "current": REPO}
        runs: dict[str, list[dict]] = {tag: [] for tag in trees}
        for r in range(args.rounds if args.reference else 1):
            for tag, tree in trees.items():
                runs[tag].append(run_worker(tree, scenes_path, args, tmp, f"{tag.split()[0]}-{r}"))

    for tag, tree in trees.items():  # each code really ran from its own tree
        if os.path.realpath(runs[tag][0]["info"]["sgjax"]) != os.path.realpath(tree):
            raise SystemExit(f"{tag}: sgjax was imported from {runs[tag][0]['info']['sgjax']}, not {tree}")
    info = runs["current"][0]["info"]
    print(f"jax {info['jax']}, {info['platform']}, load average {os.getloadavg()[0]:.1f}; E-RNet {info['model']}; "
          f"database {info['db']} primitives; Stage-1 batch sizes {sizes}; best / median of "
          f"{args.repeats} calls after compile x {len(runs['current'])} process(es) per code\n")
    print("| scene | call | code | first call (s) | Stage 1 (s) | Stage 2 (s) | total (s) | candidates | decision |")
    print("|---|---|---|---:|---:|---:|---:|---:|---|")
    merged = {tag: _merge(r) for tag, r in runs.items()}
    for i, row in enumerate(merged["current"]):
        call = f"{row['case']}, {row['objects'] if row['case'] == 'plan' else 1} object(s)"
        for tag in trees:
            r = merged[tag][i]
            cols = " | ".join(_cell(r[key]) for key in KEYS)
            print(f"| {names[r['scene']]} | {call} | {tag} | {_cell(r['first_s'])} | {cols} | {r['candidates']} | "
                  f"{_decision(r)} |")
    if args.reference:
        ref = merged[f"reference {args.reference}"]
        print("\n| scene | call | Stage 1 ratio | Stage 2 ratio | total ratio | same grasp |")
        print("|---|---|---:|---:|---:|---|")
        for r, c in zip(ref, merged["current"]):
            ratio = lambda key: ("–" if statistics.median(r[key]) <= 0 else
                                 f"{statistics.median(c[key]) / statistics.median(r[key]):.2f}")
            print(f"| {names[c['scene']]} | {c['case']} | {ratio('stage1_s')} | {ratio('stage2_s')} | "
                  f"{ratio('total_s')} | {_same(r, c)} |")
        print("\n(ratio: current / reference, of the medians; below 1 is faster)")


if __name__ == "__main__":
    main()
