"""Collision-hull size against trial speed and trial outcomes on the C engine (run by hand).

    python -m benchmarks.bench_hulls [--objects seen] [--scenes 3] [--objects-per-scene 5] [--trials 128]
                                     [--hulls 64,32,24,16] [--nthread 2]

`SceneConfig.max_hull_vertices` (MuJoCo's maxhullvert) caps each convex collision piece. The scene is
made and settled once with the first cap (the reference, the default 64); every other cap recompiles
the same assets and starts from that settled state, so each trial starts from the same object poses
(a capped hull is a subset of the full hull's vertices: it only shrinks, never overlaps). The same
jittered top-down grasps (`benchmarks.common.jittered_top_down_grasps`) are run as full trials (no early stop) under every
cap; "same outcome" compares each trial with the reference cap's. Prints a markdown table.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import os

import numpy as np

from benchmarks.common import jittered_top_down_grasps as candidates
from benchmarks.common import time_call as timed
from envs import scene as scene_lib
from envs import trial
from envs.objects import load_object_set, tiny_object_set


def with_hull_cap(scene: scene_lib.Scene, cap: int) -> scene_lib.Scene:
    """The same scene and state, its model recompiled with max_hull_vertices = cap."""
    config = dataclasses.replace(scene.config, max_hull_vertices=cap)
    model = scene_lib.build_spec(scene.assets, config, scene.gripper).compile()
    return dataclasses.replace(scene, model=model, config=config)


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--objects", default="seen")
    parser.add_argument("--scenes", type=int, default=3)
    parser.add_argument("--objects-per-scene", type=int, default=5)
    parser.add_argument("--trials", type=int, default=128)
    parser.add_argument("--hulls", default="64,32,24,16")
    parser.add_argument("--nthread", type=int, default=os.cpu_count())
    args = parser.parse_args()
    caps = [int(c) for c in args.hulls.split(",")]
    objects = tiny_object_set() if args.objects == "tiny" else load_object_set(args.objects)
    config = trial.TrialConfig(early_stop=False)
    rows = {cap: {"seconds": 0.0, "trials": 0, "same": 0, "same_success": 0, "success": 0, "invalid": 0} for cap in caps}
    per_scene = []  # the reference cap's full trials/s in each scene
    for seed in range(args.scenes):
        base = scene_lib.make_scene(objects, args.objects_per_scene, seed, scene_lib.SceneConfig(max_hull_vertices=caps[0]))
        targets, poses, widths = candidates(base, args.trials, seed)
        reference = None
        for cap in caps:
            scene = base if cap == caps[0] else with_hull_cap(base, cap)
            run = functools.partial(trial.run_trials, scene, targets, poses, widths, config=config, nthread=args.nthread)
            seconds, _, result = timed(run)
            outcome = np.asarray(result.outcome)
            if reference is None:
                reference = outcome
                per_scene.append(len(outcome) / seconds)
            success = outcome == int(trial.Outcome.SUCCESS)
            ref_success = reference == int(trial.Outcome.SUCCESS)
            row = rows[cap]
            row["seconds"] += seconds
            row["trials"] += len(outcome)
            row["same"] += int(np.sum(outcome == reference))
            row["same_success"] += int(np.sum(success == ref_success))
            row["success"] += int(success.sum())
            row["invalid"] += int(np.sum(outcome == int(trial.Outcome.INVALID)))

    print(f"{os.cpu_count()} CPUs, {args.nthread} engine threads; objects {args.objects}; {args.scenes} scenes of "
          f"{args.objects_per_scene} objects, {args.trials} full trials each; reference cap {caps[0]}\n")
    print("| max_hull_vertices | trials | wall (s) | trials/s | successes | same outcome | same success/failure | invalid |")
    print("|---:|---:|---:|---:|---:|---:|---:|---:|")
    for cap, row in rows.items():
        n = row["trials"]
        print(f"| {cap} | {n} | {row['seconds']:.2f} | {n / row['seconds']:.1f} | {row['success']} | "
              f"{row['same'] / n:.1%} | {row['same_success'] / n:.1%} | {row['invalid']} |")
    rates = ", ".join(f"{r:.1f}" for r in per_scene)
    print(f"\nReference cap {caps[0]}, full trials/s per scene (seeds 0..{args.scenes - 1}): {rates}; "
          f"median {np.median(per_scene):.1f}, min {min(per_scene):.1f}")


if __name__ == "__main__":
    main()
