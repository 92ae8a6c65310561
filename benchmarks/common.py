"""What several scripts of benchmarks/ share: timers, jittered grasps for trial benches, and a reference
commit's tree to time this code against. Heavy imports (JAX, the simulator) happen inside the functions,
so that a script's --help and its worker processes stay light."""

from __future__ import annotations

import os
import subprocess
import time

import numpy as np

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))  # the repository root


def time_call(fn):
    """fn() once -> (wall seconds, CPU seconds of all this process's threads, result)."""
    start, cpu = time.perf_counter(), time.process_time()
    out = fn()
    return time.perf_counter() - start, time.process_time() - cpu, out


def time_jitted(fn, repeats: int):
    """A jitted call timed: fn() once (tracing and compiling), then `repeats` more -> (compile seconds:
    the first call minus the best, best seconds, the last result); every call waits for its result."""
    import jax

    t0 = time.perf_counter()
    jax.block_until_ready(fn())
    first = time.perf_counter() - t0
    runs = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = jax.block_until_ready(fn())
        runs.append(time.perf_counter() - t0)
    return first - min(runs), min(runs), out


def jittered_top_down_grasps(scene, n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """n top-down grasps over the objects of `scene` (an `envs.scene.Scene`; `envs.simple_grasps`), each
    turned by ~10 degrees about its approach and moved by ~5 mm, so that trials mix successes, collisions
    and drops -> targets[n], poses[n, 4, 4], widths[n]."""
    from scipy.spatial.transform import Rotation

    from envs import simple_grasps

    rng = np.random.default_rng(seed)
    targets, poses, widths = [], [], []
    for index in np.flatnonzero(scene.present):
        p, w = simple_grasps.top_down_grasps(scene, int(index))
        targets += [int(index)] * len(w)
        poses += list(p)
        widths += list(w)
    pick = rng.integers(0, len(poses), n)
    poses = np.asarray(poses)[pick]
    turn = Rotation.from_euler("z", rng.normal(0.0, 10.0, (n, 1)), degrees=True).as_matrix()
    poses[:, :3, :3] = poses[:, :3, :3] @ turn
    poses[:, :3, 3] += rng.normal(0.0, 0.005, (n, 3))
    return np.asarray(targets)[pick], poses, np.asarray(widths)[pick]


def reference_tree(commit: str) -> str:
    """A detached git worktree of `commit` under $SGJAX_CACHE/bench/ (made once) -> its path. A script
    that times this code against it runs its worker with that tree first on PYTHONPATH; the worker must
    not import `benchmarks` (an older tree may not have this module)."""
    from sgjax.utils.cache import cache_dir

    sha = subprocess.run(["git", "-C", REPO, "rev-parse", commit], check=True, capture_output=True, text=True).stdout.strip()
    path = os.path.join(cache_dir(), "bench", f"ref-{sha[:12]}")
    if not os.path.isdir(path):
        os.makedirs(os.path.dirname(path), exist_ok=True)
        subprocess.run(["git", "-C", REPO, "worktree", "add", "--detach", path, sha], check=True, capture_output=True)
    return path


def stage1_only_planner(spec, db=None):
    """The planner with no Stage-2 network (`scorers.Stage1Order`, no refinement) for gripper `spec`: the
    default preset's Stage 1, on `db` (None: the database of `spec`, built on first use)."""
    from sgjax import presets
    from sgjax.planner import stage1_order_planner
    from sgjax.stage1.database import DBConfig, load_database

    db = load_database(DBConfig.for_gripper(spec, False), progress=False) if db is None else db
    return stage1_order_planner(db, presets.get("default", gripper=spec))


def first_views(setting, config, scenes: int, seed: int) -> list:
    """The first view of each of a decluttering setting's scenes 0..scenes-1 (an `eval.declutter.Setting`,
    seen through `config`) -> [(points [N, 3], labels [N])], as the benchmark's first plan sees them."""
    from envs.objects import load_object_set
    from eval import declutter

    objects = load_object_set(setting.object_set)
    views = []
    for s in range(scenes):
        scene = declutter.make_benchmark_scene(objects, setting.n_objects, seed, s, config)
        views.append(declutter.observe(scene, config, seed=declutter.scene_seed(seed, s))[1:3])
    return views
