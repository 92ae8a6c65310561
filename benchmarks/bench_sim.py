"""Simulation speed: scenes, the depth camera and grasp trials on the C engine and MJX (by hand).

    python -m benchmarks.bench_sim [--trials 128] [--nthread 2] [--mjx-trials 8] [--mjx-objects 2]
                                   [--objects tiny|seen|...] [--skip-cpu | --skip-mjx]
                                   [--mjx-backend mjx|mjx-jax|mjx-warp]

Trials: top-down grasps of every object of a tiny-set scene (`envs.simple_grasps`), jittered by a few
millimetres and degrees so that they mix successes, collisions and drops, repeated up to --trials.
"Full" trials simulate every phase (early_stop=False; 1020 steps of 2 ms); "early stop" is what a
labeller gets (trials stop once their outcome is decided). MJX: the first call's time minus a second
call's is the compile time; steps/s counts every simulated world-step.
"""

from __future__ import annotations

import argparse
import functools
import os

import numpy as np

from benchmarks.common import jittered_top_down_grasps as candidates
from benchmarks.common import time_call as timed
from envs import camera, trial
from envs import scene as scene_lib
from envs.objects import load_object_set, tiny_object_set


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--trials", type=int, default=128)
    parser.add_argument("--nthread", type=int, default=os.cpu_count())
    parser.add_argument("--mjx-trials", type=int, default=8)
    parser.add_argument("--mjx-objects", type=int, default=2, help="cubes in the MJX reference scene")
    parser.add_argument("--skip-mjx", action="store_true")
    parser.add_argument("--mjx-backend", default="mjx", help="mjx (warp on a GPU where warp-lang is installed, else jax), mjx-jax or mjx-warp")
    parser.add_argument("--skip-cpu", action="store_true", help="only the MJX row")
    parser.add_argument(
        "--objects", default="tiny", help="object set of the C-engine scenes (tiny: convex shapes; seen: YCB + procedural, prepared on first use)"
    )
    args = parser.parse_args()
    objects = tiny_object_set() if args.objects == "tiny" else load_object_set(args.objects)
    steps = sum(trial.TrialConfig().phase_steps(0.002))
    print(f"{os.cpu_count()} CPUs, {args.nthread} engine threads; trial = {steps} steps of 2 ms; objects: {args.objects}\n")

    if not args.skip_cpu:
        cpu_tables(objects, args, steps)
    if not args.skip_mjx:
        mjx_table(objects, args, steps)


def cpu_tables(objects, args, steps: int) -> None:
    print("| scene | objects on table | make_scene (s) | camera 640x480 (ms) | points per visible object (median) |")
    print("|---|---:|---:|---:|---:|")
    scenes = {}
    for n in (5, 10, 20):
        seconds, _, scene = timed(lambda n=n: scene_lib.make_scene(objects, n, seed=0))
        camera_s, _, obs = timed(lambda scene=scene: camera.observe(scene))
        counts = [len(c) for c in obs.object_clouds().values()]
        scenes[n] = scene
        print(f"| {n} objects | {scene.present.sum()} | {seconds:.2f} | {1e3 * camera_s:.0f} | {np.median(counts):.0f} |")

    # The cores may be shared: trials per CPU-second times the threads is the rate on idle cores.
    print("\n| backend | scene | trials | mode | wall (s) | trials/s | steps/s | trials per CPU-s | outcomes |")
    print("|---|---|---:|---|---:|---:|---:|---:|---|")
    for n, scene in scenes.items():
        targets, poses, widths = candidates(scene, args.trials)
        modes = [("full", False), ("early stop", True)] if n == 5 else [("full", False)]
        for mode, early in modes:
            config = trial.TrialConfig(early_stop=early)
            seconds, cpu, result = timed(
                functools.partial(
                    trial.run_trials, scene, targets, poses, widths, config=config, nthread=args.nthread
                )
            )
            counts = ", ".join(f"{k} {v}" for k, v in result.counts().items() if v)
            rate = args.trials / seconds
            step_rate = f"{rate * steps:.0f}" if not early else "-"
            print(
                f"| cpu | {n} objects | {args.trials} | {mode} | {seconds:.2f} | {rate:.1f} | {step_rate} | "
                f"{args.trials / cpu:.1f} | {counts} |"
            )


def mjx_table(objects, args, steps: int) -> None:
    import jax

    print("| backend | scene | trials | mode | wall (s) | trials/s | steps/s | trials per CPU-s | outcomes |")
    print("|---|---|---:|---|---:|---:|---:|---:|---|")

    # On a CPU, MJX's mesh-mesh collisions are slow (5 cubes: ~15 ms per world-step here, 5 different
    # meshes: no result within 25 min), so the default reference scene is 2 cubes; on a GPU pass
    # --mjx-objects 5 and more --mjx-trials.
    cube = [a for a in objects if a.name.endswith("box_a")]
    scene = scene_lib.make_scene(cube, args.mjx_objects, seed=0)
    m = args.mjx_trials
    targets, poses, widths = candidates(scene, m)
    config = trial.TrialConfig(early_stop=False)
    reference = trial.run_trials(scene, targets, poses, widths, config=config, nthread=args.nthread)
    run = functools.partial(trial.run_trials, scene, targets, poses, widths, backend=args.mjx_backend)
    first, _, _ = timed(run)
    seconds, cpu, result = timed(run)
    agree = float(np.mean(result.outcome == reference.outcome))
    counts = ", ".join(f"{k} {v}" for k, v in result.counts().items() if v)
    print(
        f"| {args.mjx_backend} ({jax.devices()[0].platform}) | {args.mjx_objects} cubes | {m} | full, compile {first - seconds:.0f} s | "
        f"{seconds:.2f} | {m / seconds:.1f} | {m * steps / seconds:.0f} | {m / cpu:.1f} | "
        f"{counts}; same outcome as cpu: {agree:.0%} |"
    )


if __name__ == "__main__":
    main()
