"""Single-view superquadric fits on rendered clouds: extent errors and surviving Stage-1 candidates.

Run by hand:  python -m benchmarks.bench_single_view_fit [--scenes 14] [--objects 4] [--per-object]

Scenes of the "seen" object set are dropped onto the table by the simulator (`envs.scene.make_scene`)
and rendered by the default camera (`envs.camera`, 0.71 m away, 50 deg down); every object with at
least `--min-points` points gives one single-view cloud. Stage 1 (`Stage1(None)`, the full database)
runs on each cloud with the scene cloud, the camera position as viewpoint and the table as support
plane, once per EMS configuration:

  - before: EMS without the visibility term (`visibility_weight=0, visibility_fit=0`: the fit does
    not use the viewpoint, as before the term existed);
  - after:  the default EMSConfig (the viewpoint tells EMS which fitted surface the camera saw).

Ground truth: the mesh's extents in its own frame (`ObjectAsset.extents`) and the settled pose.
Fitted full extents (2 a) are matched to the true axes by the rotations (largest |cos|, one to one);
"sorted" compares sorted extents instead. Irregular objects (clamps, fork) are not superquadrics, so
their errors do not go to zero. Candidates are those that survive every coarse filter; a second table
says how many each filter removed. The Stage-1 time per object includes cropping the whole scene
cloud on the host, so compare it only within one run (`benchmarks/bench_stage1.py` times Stage 1
alone). Prints markdown tables.
"""

from __future__ import annotations

import argparse
import dataclasses
import time

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.spatial.transform import Rotation

from envs import camera as camera_lib
from envs import scene as scene_lib
from envs.objects import load_object_set
from sgjax.stage1.ems import EMSConfig
from sgjax.stage1.database import DBConfig, load_database
from sgjax.stage1.pipeline import Stage1, Stage1Config

CONFIGS = {
    "before": EMSConfig(visibility_weight=0.0, visibility_fit=0.0),
    "after": EMSConfig(),
}


@dataclasses.dataclass
class View:
    """One object's single-view cloud and its ground truth."""

    name: str
    cloud: np.ndarray  # [n, 3] world frame
    scene: np.ndarray  # [P, 3] the whole observed cloud (table and other objects included)
    extents: np.ndarray  # [3] mesh extents in the object frame
    rotation: np.ndarray  # [3, 3] object frame -> world
    viewpoint: np.ndarray  # [3] camera position


def render_views(n_scenes: int, n_objects: int, seed: int, min_points: int) -> list[View]:
    objects = load_object_set("seen")
    cam = camera_lib.CameraConfig()
    views = []
    for k in range(n_scenes):
        scene = scene_lib.make_scene(objects, n_objects, seed + k)
        obs = camera_lib.observe(scene, cam)
        poses = scene.object_poses()
        for i in np.flatnonzero(scene.present):
            cloud = obs.object_cloud(int(i))
            if len(cloud) < min_points:
                continue
            rot = Rotation.from_quat(poses[i][3:], scalar_first=True).as_matrix()
            views.append(View(scene.assets[i].name, cloud, obs.points, np.asarray(scene.assets[i].extents), rot,
                              np.asarray(cam.position)))
    return views


def extent_errors(scale: np.ndarray, rotation: np.ndarray, view: View) -> tuple[float, float, np.ndarray, np.ndarray]:
    """(matched-axes mean relative error, sorted-extents error, fitted [3], true [3] in matched order)."""
    fitted = 2.0 * np.asarray(scale, np.float64)
    rows, cols = linear_sum_assignment(-np.abs(view.rotation.T @ np.asarray(rotation, np.float64)))
    true, fit = view.extents[rows], fitted[cols]
    matched = float(np.mean(np.abs(fit - true) / true))
    s_true, s_fit = np.sort(view.extents), np.sort(fitted)
    return matched, float(np.mean(np.abs(s_fit - s_true) / s_true)), fit, true


def run(stage: Stage1, views: list[View], seed: int) -> list[dict]:
    # One call to compile, then time each object's call (fit + match + transfer + filters, scene included).
    v = views[0]
    stage(v.cloud, v.scene, v.viewpoint, seed, support_plane=scene_lib.TABLE_PLANE)
    rows = []
    for v in views:
        t0 = time.perf_counter()
        cands = stage(v.cloud, v.scene, v.viewpoint, seed, support_plane=scene_lib.TABLE_PLANE)
        seconds = time.perf_counter() - t0
        sq = cands.superquadric
        err, sorted_err, fit, true = extent_errors(np.asarray(sq.scale), np.asarray(sq.rotation), v)
        rows.append({
            "name": v.name, "err": err, "sorted_err": sorted_err, "over": bool(np.any(fit > 1.5 * true)),
            "under": bool(np.any(fit < true / 1.5)), "fit": fit, "true": true, "eps": np.asarray(sq.epsilon),
            "candidates": len(cands), "counts": cands.counts, "seconds": seconds,
        })
    return rows


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--scenes", type=int, default=14)
    parser.add_argument("--objects", type=int, default=4, help="objects dropped per scene")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--min-points", type=int, default=60)
    parser.add_argument("--per-object", action="store_true")
    parser.add_argument("--set", nargs="*", default=[], metavar="FIELD=VALUE",
                        help="EMSConfig fields of an extra configuration to compare, e.g. --set visibility_fit=0.5")
    args = parser.parse_args()
    configs = dict(CONFIGS)
    if args.set:
        default = EMSConfig()

        def parse(key: str, text: str):
            kind = type(getattr(default, key))
            return text.lower() in ("1", "true", "yes") if kind is bool else kind(text)

        changes = {k: parse(k, v) for k, v in (a.split("=", 1) for a in args.set)}
        configs[" ".join(args.set)] = dataclasses.replace(CONFIGS["after"], **changes)

    views = render_views(args.scenes, args.objects, args.seed, args.min_points)
    db = load_database(DBConfig())
    print(f"{len(views)} single-view clouds ({np.median([len(v.cloud) for v in views]):.0f} points median) "
          f"from {args.scenes} scenes; database: {len(db)} primitives\n")
    results = {name: run(Stage1(db, Stage1Config(ems=cfg)), views, args.seed) for name, cfg in configs.items()}

    def col(rows, key):
        return np.array([r[key] for r in rows], np.float64)

    print("| EMS | extent error, mean | median | sorted-extent error | any extent > 1.5x true | any < true/1.5 "
          "| candidates, mean | median | objects with 0 | with < 10 | Stage 1 per object (median) |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for name, rows in results.items():
        err, cand = col(rows, "err"), col(rows, "candidates")
        print(f"| {name} | {err.mean():.2f} | {np.median(err):.2f} | {col(rows, 'sorted_err').mean():.2f} "
              f"| {100 * col(rows, 'over').mean():.0f} % | {100 * col(rows, 'under').mean():.0f} % "
              f"| {cand.mean():.0f} | {np.median(cand):.0f} | {int(np.sum(cand == 0))} | {int(np.sum(cand < 10))} "
              f"| {1e3 * np.median(col(rows, 'seconds')):.0f} ms |")
    keys = ["transferred", "collision_object", "too_few_points", "normal_angle", "collision_scene", "below_support"]
    print("\n| EMS | " + " | ".join(f"{k}, mean" for k in keys) + " |")
    print("|---|" + "---:|" * len(keys))
    for name, rows in results.items():
        print(f"| {name} | " + " | ".join(f"{np.mean([r['counts'].get(k, 0) for r in rows]):.0f}" for k in keys) + " |")
    if args.per_object:
        names = list(results)
        print("\n| object | true extents (cm) | " + " | ".join(f"{n}: fit (cm), eps, candidates" for n in names) + " |")
        print("|---|---|" + "---|" * len(names))
        for i, v in enumerate(views):
            cells = []
            for n in names:
                r = results[n][i]
                cells.append(f"{np.array2string(100 * r['fit'], precision=1)}, {np.array2string(r['eps'], precision=2)}, "
                             f"{r['candidates']}")
            print(f"| {v.name} | {np.array2string(100 * results[names[0]][i]['true'], precision=1)} | "
                  + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
