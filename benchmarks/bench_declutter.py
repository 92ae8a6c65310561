"""Decluttering benchmark across methods (by hand): Table I (GSR, TSR, GA) and Table III (time per grasp).

    python -m benchmarks.bench_declutter [--methods gpd oracle-topdown] [--setting seen-10] [--scenes 1]
                                         [--seed 0] [--out bench_declutter_out] [--objects DIR]
                                         [--n-objects N] [--model RUN_DIR] [--small-db]

Runs each method on the same scenes (same seed) through `eval.benchmark.run_benchmark` (resumable: the
out directory keeps the logs), then prints the merged tables of the out directory and, per method, the
harness's own costs per attempt (observation, trial simulation) and per scene. The paper runs 30 scenes
per setting; one scene is a smoke run. Methods that cannot run here are reported and skipped.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from eval import report
from eval.benchmark import machine_label, run_benchmark
from eval.methods import MethodUnavailable, check_method


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--methods", nargs="+", default=["gpd", "oracle-topdown"])
    parser.add_argument("--setting", default="seen-10")
    parser.add_argument("--scenes", type=int, default=1)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default="bench_declutter_out")
    parser.add_argument("--objects", help="object set or mesh folder instead of the setting's")
    parser.add_argument("--n-objects", type=int)
    parser.add_argument("--model", help="E-RNet run directory (supergrasp methods)")
    parser.add_argument("--small-db", action="store_true")
    args = parser.parse_args()

    for name in args.methods:
        options = {"model": args.model, "small_db": args.small_db} if name.startswith("supergrasp") else {}
        try:
            check_method(name, **options)
        except (ValueError, MethodUnavailable) as exc:
            print(f"skipping {name}: {exc}")
            continue
        start = time.perf_counter()
        try:
            result = run_benchmark(name, setting=args.setting, scenes=args.scenes, seed=args.seed, out=args.out,
                                   objects=args.objects, n_objects=args.n_objects, method_options=options)
        except (ValueError, FileNotFoundError) as exc:  # e.g. no E-RNet checkpoint for supergrasp
            print(f"skipping {name}: {exc}")
            continue
        wall = time.perf_counter() - start
        attempts = [a for log in result.logs for a in log["attempts"]]
        observe = np.array([a["observe_s"] for a in attempts]) if attempts else np.zeros(1)
        trial = np.array([a["trial_s"] for a in attempts if a["target"] is not None]) if attempts else np.zeros(1)
        s = result.summary
        print(f"{name} on {result.setting}: GSR {report.percent(s.gsr)} TSR {report.percent(s.tsr)} GA {s.ga} "
              f"({s.scenes} scenes, {s.objects} objects, {result.ran} run now, warm-up {result.warmup_s:.1f} s, "
              f"{wall:.1f} s wall)")
        print(f"  per attempt: observe {observe.mean():.3f} s, trial {trial.mean() if len(trial) else 0.0:.3f} s; "
              f"per scene {np.mean([log['wall_s'] for log in result.logs]):.1f} s")
    print()
    print(report.write_tables(args.out, machine_label())["results.md"].read_text())


if __name__ == "__main__":
    main()
