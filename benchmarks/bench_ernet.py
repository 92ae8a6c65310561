"""E-RNet (Stage 2) speed on CPU (run by hand; prints markdown tables).

    python -m benchmarks.bench_ernet [--repeats 5] [--configs light paper light-swept] [--train-steps 5]

Scene: a ~20k-point cluttered tabletop (table plane + single-view clouds of 6 superquadrics, 1 mm
noise). Candidates: near-top-down grasps on the objects (random tilt <= 30 deg, yaw, width 4-8 cm).
`score` time = crop from the scene + input preparation + network, one jitted call, after compile
(compile time reported separately); the best of --repeats runs. Stage breakdown: each stage jitted
on its own. Training: samples/s of the jitted train step at batch 128 on synthetic samples.
The 2 cores of the dev machine are shared: numbers vary with other jobs (the load average is printed).
"""

from __future__ import annotations

import argparse
import os
import time

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx

from benchmarks.common import time_jitted
from sgjax.stage2 import crops, ernet
from sgjax.geometry import synthetic
from sgjax.stage2.ernet import LIGHT_BACKBONE, ERNet, ERNetConfig
from sgjax.stage2.pointnet2 import BackboneConfig, SetAbstractionConfig
from sgjax.geometry.gripper import GripperSpec
from sgjax.geometry.superquadric import Superquadric
from train import dataset, trainer

SPEC = GripperSpec()
CONFIGS = {
    "light": ERNetConfig.light,
    "paper": ERNetConfig.paper,
    "light-swept": lambda: ERNetConfig.light(hand_points=32),  # the swept input (hand feature)
    "light-swept128": lambda: ERNetConfig.light(hand_points=128),
    # Between light and paper: twice light's centroids, neighbours and widths, the random sampler.
    "medium-swept": lambda: ERNetConfig.light(
        hand_points=32, n_points=768, n_anchor=192, anchor_mlp=(256,), eval_hidden=(128, 64), refine_hidden=(128, 64),
        backbone=BackboneConfig(
            (SetAbstractionConfig(64, 0.015, 16, (32, 64)), SetAbstractionConfig(16, 0.04, 16, (64, 128))),
            ((128,), (128, 128)), sampler="random",
        ),
    ),
    "paper-swept": lambda: ERNetConfig.paper(hand_points=32),
    # light-swept with twice the centroids (64 / 16, first radius 1.5 cm), light's widths (docs/stage2.md,
    # "Wider and finer networks").
    "fine-swept": lambda: ERNetConfig.light(
        hand_points=32,
        backbone=BackboneConfig(
            (SetAbstractionConfig(64, 0.015, 8, (16, 32)), SetAbstractionConfig(16, 0.04, 8, (32, 64))),
            ((64,), (64, 64)), sampler="random",
        ),
    ),
    # light-swept with 96-wide feature propagation and 256 / 128 heads (docs/stage2.md, "Wider and finer networks").
    "wide-swept": lambda: ERNetConfig.light(
        hand_points=32, eval_hidden=(256, 128), refine_hidden=(256, 128),
        backbone=BackboneConfig(LIGHT_BACKBONE.set_abstraction, ((96,), (96, 96)), sampler="random"),
    ),
}


def make_scene(seed: int = 0, n_table: int = 12000, n_per_object: int = 1350, n_objects: int = 6):
    """-> (scene[N, 3] world, z up, table at z = 0; object centres [K, 3]; object tops [K])."""
    rng = np.random.default_rng(seed)
    table = np.c_[rng.uniform(-0.3, 0.3, (n_table, 2)), rng.normal(0, 0.001, n_table)]
    clouds, centres, tops = [table], [], []
    camera = np.array([0.0, -0.3, 0.8])
    for k in range(n_objects):
        scale = rng.uniform(0.02, 0.045, 3)
        eps = rng.uniform(0.2, 1.5, 2)
        yaw = rng.uniform(0, 2 * np.pi)
        rot = np.array([[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1.0]])
        centre = np.array([0.25 * np.cos(2 * np.pi * k / n_objects), 0.25 * np.sin(2 * np.pi * k / n_objects), 0.0]) * 0.6
        centre[2] = scale[2]
        sq = Superquadric.create(scale, eps, rot, centre)
        view = camera - centre
        clouds.append(synthetic.single_view_cloud(sq, n_per_object, view=view, seed=rng))
        centres.append(centre)
        tops.append(2 * scale[2])
    return np.concatenate(clouds).astype(np.float32), np.array(centres), np.array(tops)


def make_candidates(m: int, centres: np.ndarray, tops: np.ndarray, seed: int = 1):
    """-> poses[M, 4, 4], widths[M]: approach roughly downwards onto the objects, object by object (the
    order the planner hands Stage 2 its candidates in, which the crop's chunks rely on)."""
    rng = np.random.default_rng(seed)
    which = np.sort(rng.integers(0, len(centres), m))
    poses = np.tile(np.eye(4, dtype=np.float32), (m, 1, 1))
    for i in range(m):
        tilt, azimuth, yaw = np.deg2rad(rng.uniform(0, 30)), rng.uniform(0, 2 * np.pi), rng.uniform(0, np.pi)
        z = -np.array([np.sin(tilt) * np.cos(azimuth), np.sin(tilt) * np.sin(azimuth), np.cos(tilt)])
        x = np.cross(z, [np.cos(yaw), np.sin(yaw), 0.0])
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
        target = centres[which[i]] + [0, 0, 0.5 * tops[which[i]]] + rng.normal(0, 0.01, 3)
        poses[i, :3, :3] = np.stack([x, y, z], -1)
        poses[i, :3, 3] = target - 0.04 * z  # fingers reach ~4 cm past the origin into the object
    return poses, rng.uniform(0.04, 0.08, m).astype(np.float32)


def best_of(fn, repeats: int) -> tuple[float, float]:
    """-> (compile + first call seconds minus a steady call, best steady seconds)."""
    compile_s, run_s, _ = time_jitted(fn, repeats)
    return max(compile_s, 0.0), run_s


def stage_breakdown(model: ERNet, scene, poses, widths, repeats: int) -> dict[str, float]:
    config = model.config
    crop_fn = crops.crop_function(config.crop)
    crop = jax.jit(lambda s, p, w: crop_fn(s, p, w, SPEC, config.crop_points))
    prepare = jax.jit(lambda r, w: ernet.prepare_inputs(r.points, r.mask, w, SPEC, config))
    graphdef, state = nnx.split(model)
    network = jax.jit(lambda st, i: ernet.forward_chunked(nnx.merge(graphdef, st), i))  # as `score` runs it
    region = crop(scene, poses, widths)
    inputs = prepare(region, widths)
    return {
        "crop": best_of(lambda: crop(scene, poses, widths), repeats)[1],
        "prepare": best_of(lambda: prepare(region, widths), repeats)[1],
        "network": best_of(lambda: network(state, inputs), repeats)[1],
        "region points (mean)": float(np.mean(np.asarray(region.count))),
    }


def train_throughput(config: ERNetConfig, steps: int) -> tuple[float, float]:
    """-> (compile seconds, samples/s) of the train step at batch 128."""
    cfg = trainer.TrainConfig(batch_size=128, model=config)
    samples = dataset.synthetic_samples(128, seed=0)
    graphdef, params = nnx.split(ERNet(config, rngs=nnx.Rngs(0)))
    tx, train_step, _ = trainer.make_steps(graphdef, cfg)
    opt_state = tx.init(params)
    batch = jax.device_put(dataset.make_batch(samples, np.arange(128), np.ones(128, np.float32)))
    t0 = time.perf_counter()
    params, opt_state, stats = train_step(params, opt_state, batch, jax.random.key(0), jnp.float32(1.0))
    jax.block_until_ready(stats)
    first = time.perf_counter() - t0
    t0 = time.perf_counter()
    for i in range(steps):
        params, opt_state, stats = train_step(params, opt_state, batch, jax.random.key(i + 1), jnp.float32(1.0))
    jax.block_until_ready(stats)
    per_step = (time.perf_counter() - t0) / steps
    return first - per_step, 128 / per_step


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--configs", nargs="+", default=["light", "paper"], choices=sorted(CONFIGS))
    parser.add_argument("--candidates", type=int, nargs="+", default=[128, 512])
    parser.add_argument("--train-steps", type=int, default=5)
    args = parser.parse_args()

    scene, centres, tops = make_scene()
    print(f"jax {jax.__version__}, {jax.devices()}, {os.cpu_count()} cores, load average {os.getloadavg()[0]:.1f}")
    print(f"scene: {len(scene)} points\n")
    print("| config | candidates | compile (s) | score (ms) | ms / candidate | candidates/s |")
    print("|---|---:|---:|---:|---:|---:|")
    models = {name: ERNet(CONFIGS[name](), rngs=nnx.Rngs(0)) for name in args.configs}
    for name, model in models.items():
        graphdef, state = nnx.split(model)
        for m in args.candidates:
            poses, widths = make_candidates(m, centres, tops)
            call = lambda g=graphdef, s=state, p=poses, w=widths: ernet.score(g, s, scene, p, w)
            compile_s, run_s = best_of(call, args.repeats)
            print(f"| {name} | {m} | {compile_s:.1f} | {run_s * 1e3:.1f} | {run_s * 1e3 / m:.3f} | {m / run_s:.0f} |")

    m = max(args.candidates)
    poses, widths = make_candidates(m, centres, tops)
    print(f"\nStages at {m} candidates (each jitted alone, ms):\n")
    print("| config | crop | prepare | network | region points (mean) |")
    print("|---|---:|---:|---:|---:|")
    for name, model in models.items():
        b = stage_breakdown(model, scene, poses, widths, args.repeats)
        print(f"| {name} | {b['crop'] * 1e3:.1f} | {b['prepare'] * 1e3:.1f} | {b['network'] * 1e3:.1f} | {b['region points (mean)']:.0f} |")

    if args.train_steps:
        print("\nTraining (batch 128, jitted step incl. noise + input preparation):\n")
        print("| config | compile (s) | samples/s |")
        print("|---|---:|---:|")
        for name in args.configs:
            compile_s, rate = train_throughput(CONFIGS[name](), args.train_steps)
            print(f"| {name} | {compile_s:.1f} | {rate:.0f} |")
    print(f"\nload average at the end: {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
