"""Labelling speed per trial backend: `sgjax label`'s scenes end to end on the C engine and on MJX (by hand).

    python -m benchmarks.bench_label_backends [--backends cpu,mjx] [--scenes N] [--objects tiny|seen]
                                              [--size tiny|real] [--small-db] [--nthread 0]

Each backend labels the same scenes with `train.label.label_scene` (nothing is written). Every scene
is labelled twice: the first ("cold") pays whatever compiles for it (MJX compiles once per distinct set
of meshes and batch size; Stage 1 and the samplers once per process), the second ("warm") is the
steady state. Columns: trials per scene, cold and warm seconds, warm trials/s end to end and for the
trial stage alone, and (for backends other than cpu) the share of trials whose label equals the C
engine's on the same grasps.

--size real (default on a GPU): the labeller's own settings (5 objects, 2 targets, 8 grasps per
source: up to 256 trials per scene, one MJX batch). --size tiny (default on a CPU, where MJX runs at
~10-1000 world-steps/s): 3 tiny objects, 1 target, 1 Stage-1 and 1 GPD-style grasp (8 trials per
scene), so that MJX finishes in about half an hour. Compare runs made in one sitting: these machines are shared.
"""

from __future__ import annotations

import argparse
import dataclasses
import time

import numpy as np


def settings(size: str, objects: str):
    """The LabelConfig of a benchmark size (`real`: the labeller's defaults; `tiny`: 8 trials per scene)."""
    from train.label import LabelConfig

    if size == "real":  # the default held-out objects are seen-set members
        return LabelConfig(object_set=objects) if objects == "seen" else LabelConfig(object_set=objects, held_out_objects=())
    return LabelConfig(
        n_objects=3,
        targets_per_scene=1,
        per_source=(("stage1", 1), ("gpd", 1)),
        object_set=objects,
        held_out_objects=(),
    )


def bench_backend(backend: str, scenes: list[int], objects, labellers, config, nthread: int) -> list[dict]:
    """Label each scene twice on `backend` -> per scene {"trials", "cold", "warm", "warm_trials", "labels"}:
    wall seconds of the cold and the warm call, the warm call's trial-stage seconds, labels [S, 4]."""
    from train.label import label_scene

    rows = []
    for index in scenes:
        began = time.perf_counter()
        label_scene(index, objects, labellers, config, backend, nthread)
        cold = time.perf_counter() - began
        began = time.perf_counter()
        samples, _, stats = label_scene(index, objects, labellers, config, backend, nthread)
        warm = time.perf_counter() - began
        labels = np.concatenate([samples["label"][:, None], samples["refine_labels"]], axis=1)
        rows.append({
            "trials": stats["trials"], "cold": cold, "warm": warm,
            "warm_trials": stats.get("seconds", {}).get("trials", float("nan")), "labels": labels,
        })
    return rows


def main() -> None:
    import jax

    platform = jax.devices()[0].platform
    parser = argparse.ArgumentParser()
    parser.add_argument("--backends", default="cpu,mjx", help="comma-separated: cpu, mjx, mjx-jax, mjx-warp")
    parser.add_argument("--scenes", type=int, default=None, help="scenes per backend (default: 1 on a CPU, 4 on a GPU)")
    parser.add_argument("--objects", default="tiny", help="object set (tiny: convex shapes, no preparation)")
    parser.add_argument("--size", choices=("tiny", "real"), default=None, help="tiny (default on a CPU) or real (on a GPU)")
    parser.add_argument("--small-db", action="store_true", help="the small primitive database (quicker start)")
    parser.add_argument("--nthread", type=int, default=0, help="C-engine threads (0: all cores)")
    args = parser.parse_args()
    size = args.size or ("tiny" if platform == "cpu" else "real")
    n_scenes = args.scenes or (1 if platform == "cpu" else 4)

    from envs.objects import load_object_set
    from envs.trial import check_backend
    from sgjax.stage1.database import DBConfig, load_database
    from sgjax.stage1.pipeline import Stage1
    from train.label import Labellers, prepare_objects

    backends = [check_backend(b.strip()) for b in args.backends.split(",") if b.strip()]
    config = settings(size, args.objects)
    objects, _ = prepare_objects(config, load_object_set(args.objects, progress=True))
    stage1 = Stage1(load_database(DBConfig.small() if args.small_db else DBConfig()), config.stage1)
    labellers = Labellers.make(config, stage1)
    # Scenes with samples: a scene whose targets are hidden labels nothing and would time nothing.
    scenes, index = [], 0
    while len(scenes) < n_scenes and index < 50 * n_scenes:
        if label_count(index, objects, labellers, config):
            scenes.append(index)
        index += 1
    print(f"device {jax.devices()[0]} ({platform}); size {size}: {dataclasses.asdict(config)['per_source']}, "
          f"{config.n_objects} objects, {config.targets_per_scene} targets; scenes {scenes}\n")
    print("| backend | scenes | trials / scene | cold s / scene | warm s / scene | warm trials/s end to end | "
          "warm trials/s (trials only) | labels = cpu |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|")
    reference = None
    for backend in backends:
        rows = bench_backend(backend, scenes, objects, labellers, config, args.nthread)
        trials = sum(r["trials"] for r in rows)
        warm = sum(r["warm"] for r in rows)
        sim = sum(r["warm_trials"] for r in rows)
        labels = np.concatenate([r["labels"] for r in rows])
        if backend == "cpu":
            reference, agree = labels, "-"
        else:
            agree = f"{np.mean(labels == reference):.0%}" if reference is not None and reference.shape == labels.shape else "n/a"
        print(
            f"| {backend} | {len(rows)} | {trials / len(rows):.0f} | {sum(r['cold'] for r in rows) / len(rows):.1f} | "
            f"{warm / len(rows):.1f} | {trials / warm:.3g} | {trials / sim:.3g} | {agree} |",  # MJX on CPU: ~0.02
            flush=True,
        )


def label_count(index: int, objects, labellers, config) -> int:
    """How many samples scene `index` gives on the C engine (a probe: a second or so per scene)."""
    from train.label import label_scene

    samples, _, _ = label_scene(index, objects, labellers, config, "cpu", 0)
    return len(samples["label"])


if __name__ == "__main__":
    main()
