"""`sgjax plan --depth` as a whole process, as a user runs it on one frame (run by hand; prints a
markdown table).

    python -m benchmarks.bench_plan_frame [--repeats 5] [--against COMMIT] [--all-objects]

The frame is `sgjax example-frame`'s (written once to $SGJAX_CACHE/bench/example-frame). Each run is a
fresh `python -m sgjax_cli plan --depth ... --json` on a warm cache (one run first warms it and is not
counted): wall seconds from the process's start to its exit, beside the JSON's own timing (the front
end, loading the database and the network, planning). With --against, the same command from that
commit's tree (`benchmarks.common.reference_tree`) runs alternately with this tree's, so that both meet
the same load: compare the ratio, not the seconds, on a shared machine.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time

import numpy as np

from benchmarks.common import REPO, reference_tree


def example_frame() -> str:
    """The example frame's directory (written once by `sgjax example-frame`)."""
    from sgjax.utils.cache import cache_dir

    path = os.path.join(cache_dir(), "bench", "example-frame")
    if not os.path.isfile(os.path.join(path, "intrinsics.json")):
        subprocess.run([sys.executable, "-m", "sgjax_cli", "example-frame", path], check=True, cwd=REPO,
                       capture_output=True)
    return path


def run_once(tree: str, frame: str, extra: list[str]) -> dict:
    """One `sgjax plan --depth` process from `tree` -> its JSON timing plus "wall_s" and "grasps"."""
    command = [sys.executable, "-m", "sgjax_cli", "plan", "--depth", os.path.join(frame, "depth.png"),
               "--intrinsics", os.path.join(frame, "intrinsics.json"), "--json", *extra]
    env = {**os.environ, "PYTHONPATH": tree}
    start = time.perf_counter()
    done = subprocess.run(command, cwd=tree, env=env, capture_output=True, text=True, check=True)
    wall = time.perf_counter() - start
    out = json.loads(done.stdout[done.stdout.index("{"):])
    return {**out["timing"], "wall_s": wall, "grasps": len(out["grasps"])}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=5, help="counted runs per tree")
    parser.add_argument("--against", help="a commit to time alternately with this tree")
    parser.add_argument("--all-objects", action="store_true", help="plan every object (`--all-objects`)")
    args = parser.parse_args(argv)
    frame = example_frame()
    extra = ["--all-objects"] if args.all_objects else []
    trees = {"this tree": REPO}
    if args.against:
        trees[args.against] = reference_tree(args.against)
    for tree in trees.values():
        run_once(tree, frame, extra)  # warms the compilation cache
    runs: dict[str, list[dict]] = {name: [] for name in trees}
    for _ in range(args.repeats):
        for name, tree in trees.items():
            runs[name].append(run_once(tree, frame, extra))
    keys = ["wall_s", "perception_s", "setup_s", "plan_s", "stage1_s", "stage2_s"]
    print("| tree | " + " | ".join(k.removesuffix("_s") + " (s)" for k in keys) + " | grasps |")
    print("|---|" + "---|" * (len(keys) + 1))
    medians = {}
    for name, rows in runs.items():
        medians[name] = {k: float(np.median([r[k] for r in rows])) for k in keys}
        print(f"| {name} | " + " | ".join(f"{medians[name][k]:.2f}" for k in keys) + f" | {rows[-1]['grasps']} |")
    if args.against:
        ratio = medians["this tree"]["wall_s"] / medians[args.against]["wall_s"]
        print(f"\nthis tree / {args.against}: {ratio:.2f}x wall (medians of {args.repeats} alternating runs)")


if __name__ == "__main__":
    main()
