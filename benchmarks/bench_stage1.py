"""Stage-1 benchmark: time per object (fit + match + transfer + filter), matching alone, candidate counts.

Run by hand:  python -m benchmarks.bench_stage1 [--small-db] [--objects 48]
Prints markdown tables. Uses the default primitive database from the cache (built on first use).
Queries are single-view clouds (800 points, 1 mm noise) of random primitives standing on a table.
"""

from __future__ import annotations

import argparse
import time

import jax
import jax.numpy as jnp
import numpy as np
import trimesh
from scipy.spatial.transform import Rotation

from sgjax.stage1.matching import match
from sgjax.stage1.database import DBConfig, load_database
from sgjax.stage1.primitives import FAMILIES, Primitive, primitive_mesh
from sgjax.stage1.pipeline import Stage1, Stage1Config

CAMERA = np.array([0.45, -0.1, 0.55])


def random_object(rng: np.random.Generator) -> Primitive:
    family = FAMILIES[rng.integers(len(FAMILIES))]
    a = rng.uniform(0.025, 0.055)  # graspable across at least one side
    b, h = rng.uniform(0.025, 0.09), rng.uniform(0.03, 0.15)
    dims = {"cuboid": (b, a, h), "cylinder": (a, a, h), "elliptical_cylinder": (b, a, h), "frustum": (a, a * rng.uniform(0.4, 0.9), h)}
    return Primitive(family, dims[family])


def single_view(p: Primitive, rng: np.random.Generator, n: int = 800) -> np.ndarray:
    mesh = primitive_mesh(p)
    pose = np.eye(4)
    pose[:3, :3] = Rotation.from_euler("z", rng.uniform(0, 360), degrees=True).as_matrix()
    pose[:3, 3] = [rng.uniform(-0.1, 0.2), rng.uniform(-0.15, 0.15), 0.5 * p.extents[2]]
    mesh.apply_transform(pose)
    pts, face = trimesh.sample.sample_surface(mesh, 8 * n, seed=int(rng.integers(1 << 30)))
    pts = pts[np.sum(mesh.face_normals[face] * (CAMERA - pts), 1) > 0][:n]
    return pts + rng.normal(0, 0.001, pts.shape)


def timed(fn, repeats: int) -> float:
    fn()
    t = time.perf_counter()
    for _ in range(repeats):
        fn()
    return (time.perf_counter() - t) / repeats


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--small-db", action="store_true")
    parser.add_argument("--objects", type=int, default=48)
    args = parser.parse_args()
    db = load_database(DBConfig.small() if args.small_db else DBConfig())
    stage = Stage1(db, Stage1Config())
    rng = np.random.default_rng(0)
    objects = [random_object(rng) for _ in range(args.objects)]
    clouds = [single_view(p, rng) for p in objects]
    table = np.c_[rng.uniform(-0.25, 0.35, (20000, 2)), np.zeros(20000)]

    print(f"database: {len(db)} primitives, {int(db.num_grasps.sum())} grasps, jax {jax.__version__}, "
          f"{jax.devices()[0].platform}\n")
    t0 = time.perf_counter()
    stage(clouds[0], viewpoint=CAMERA)
    compile_s = time.perf_counter() - t0
    one = timed(lambda: [stage(c, viewpoint=CAMERA) for c in clouds[:8]], 2) / 8
    stage(clouds[0], np.concatenate([table, clouds[0]]), viewpoint=CAMERA)
    with_scene = timed(lambda: [stage(c, np.concatenate([table, c]), viewpoint=CAMERA) for c in clouds[:8]], 2) / 8
    batch = clouds[:16]
    stage.batch(batch, viewpoints=np.tile(CAMERA, (16, 1)))
    per_batch = timed(lambda: stage.batch(batch, viewpoints=np.tile(CAMERA, (16, 1))), 2) / 16

    fit = stage(clouds[0], viewpoint=CAMERA).superquadric
    q_scale, q_eps = jnp.asarray(fit.scale)[None], jnp.asarray(fit.epsilon)[None]
    match_s = timed(lambda: jax.block_until_ready(match(q_scale, q_eps, stage.match_db)), 200)

    print("| Stage 1 on CPU (after compile) | time |")
    print("|---|---:|")
    print(f"| per object, 800 points, 1 object per call | {one * 1e3:.1f} ms (target <= 60 ms) |")
    print(f"| per object, with a 20k-point scene cloud | {with_scene * 1e3:.1f} ms |")
    print(f"| per object, 16 objects per call | {per_batch * 1e3:.1f} ms |")
    print(f"| matching alone, 1 query vs {len(db)} primitives | {match_s * 1e3:.3f} ms (target <= 1 ms) |")
    print(f"| first call (compile) | {compile_s:.1f} s |\n")

    results = stage.batch(clouds, [np.concatenate([table, c]) for c in clouds], np.tile(CAMERA, (len(clouds), 1)))
    keys = ["transferred", "collision_object", "too_few_points", "normal_angle", "collision_scene", "kept"]
    counts = np.array([[r.counts.get(k, 0) for k in keys] for r in results])
    same_family = [np.mean([db.primitive(int(i)).family == p.family for i in np.unique(r.primitive_id)]) if len(r) else 0.0
                   for r, p in zip(results, objects)]
    print(f"| candidates per object ({len(clouds)} objects, with table) | mean | median | min | max |")
    print("|---|---:|---:|---:|---:|")
    for k, col in zip(keys, counts.T):
        label = {"transferred": "transferred (top K2 primitives)", "kept": "kept"}.get(k, f"removed: {k}")
        print(f"| {label} | {col.mean():.0f} | {np.median(col):.0f} | {col.min()} | {col.max()} |")
    print(f"\nobjects with no candidate: {sum(len(r) == 0 for r in results)} / {len(results)}; "
          f"matched primitives of the object's own family: {100 * np.mean(same_family):.0f} %")


if __name__ == "__main__":
    main()
