"""Planning time per grasp in the decluttering harness: this code against a reference commit (run by hand).

    python -m benchmarks.bench_harness_plan --reference COMMIT [--setting seen-10] [--scenes 0-5]
                                            [--method supergrasp] [--rounds 1]

`benchmarks.bench_plan` times one plan of a scene's first view; a decluttering run plans again after every
attempt, on a scene that changes a little each time (one object fewer, a neighbour nudged), which is
where the planner's Stage-1 memory saves its time. This script runs the benchmark's scenes
(`eval.declutter.run_scene`, seed 0, the method's defaults) with each code in its own process
(alternating, `--rounds` each), and prints per code the mean / median Stage-1, Stage-2 and total
planning time of the plans that compiled nothing, how many Stage-1 results came from the memory, and
the outcome (grasps, successes, objects left), then the ratios current / reference. The outcomes
need not be the same: a remembered result is one of an earlier view. The load average is printed:
compare the numbers of one run only.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile

KEYS = ("stage1_s", "stage2_s", "total_s")


def scene_indices(text: str) -> list[int]:
    """"0-5" or "0,3,7" -> scene indices. Not `eval.benchmark.scene_indices`: the worker also runs under a
    reference commit's tree, which may predate it."""
    out: list[int] = []
    for part in text.split(","):
        lo, _, hi = part.partition("-")
        out.extend(range(int(lo), int(hi or lo) + 1))
    return out


def worker(setting: str, scenes: list[int], method_name: str, out_path: str) -> None:
    """Run the scenes with the sgjax importable here; write every attempt's timing and outcome (JSON)."""
    import sgjax
    from envs.objects import load_object_set
    from eval.declutter import get_setting, run_scene
    from eval.methods import make_method

    s = get_setting(setting)
    objects = load_object_set(s.object_set)
    method = make_method(method_name)
    rows, scenes_out = [], []
    for index in scenes:
        log = run_scene(method, objects, s.n_objects, 0, index, setting=setting).log
        scenes_out.append({"index": index, "objects": int(log["objects"]), "remaining": log["remaining"]})
        for a in log["attempts"]:
            rows.append({"scene": index, "success": a["success"], "compiled": bool(a["info"].get("compiled")),
                         "reused": int(a["info"].get("reused", 0)), **{k: a["timing"][k] for k in KEYS}})
    with open(out_path, "w") as f:
        json.dump({"sgjax": os.path.dirname(os.path.dirname(sgjax.__file__)), "attempts": rows, "scenes": scenes_out}, f)


def run_worker(tree: str, args, out: str) -> dict:
    cmd = [sys.executable, os.path.abspath(__file__), "--worker", out, "--setting", args.setting, "--scenes", args.scenes,
           "--method", args.method]
    env = dict(os.environ, PYTHONPATH=tree + os.pathsep + os.environ.get("PYTHONPATH", ""))
    subprocess.run(cmd, check=True, env=env, cwd=tree)
    with open(out) as f:
        return json.load(f)


def summary(runs: list[dict]) -> dict:
    """Rounds of one code -> means and medians over the plans that compiled nothing, and the outcome."""
    plans = [a for r in runs for a in r["attempts"] if not a["compiled"]]
    first = runs[0]
    return {
        "plans": len(plans),
        **{k: (statistics.mean(a[k] for a in plans), statistics.median(a[k] for a in plans)) for k in KEYS},
        "reused": statistics.mean(a["reused"] for a in plans),
        "attempts": len(first["attempts"]),
        "successes": sum(a["success"] for a in first["attempts"]),
        "objects": sum(s["objects"] for s in first["scenes"]),
        "left": sum(s["remaining"] for s in first["scenes"]),
    }


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--reference", help="also run this commit's code on the same scenes")
    parser.add_argument("--setting", default="seen-10")
    parser.add_argument("--scenes", default="0-5", help="scene indices of seed 0: 0-5 or 0,3,7")
    parser.add_argument("--method", default="supergrasp")
    parser.add_argument("--rounds", type=int, default=1, help="processes per code, alternating")
    parser.add_argument("--worker", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:
        worker(args.setting, scene_indices(args.scenes), args.method, args.worker)
        return
    from benchmarks.common import REPO, reference_tree  # not in the worker: a reference tree may predate it

    trees = {"current": REPO}
    if args.reference:
        trees = {f"reference {args.reference}": reference_tree(args.reference), "current": REPO}
    runs: dict[str, list[dict]] = {tag: [] for tag in trees}
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(args.rounds):
            for tag, tree in trees.items():
                runs[tag].append(run_worker(tree, args, os.path.join(tmp, f"{tag.split()[0]}-{r}.json")))
    for tag, tree in trees.items():
        if os.path.realpath(runs[tag][0]["sgjax"]) != os.path.realpath(tree):
            raise SystemExit(f"{tag}: sgjax was imported from {runs[tag][0]['sgjax']}, not {tree}")
    rows = {tag: summary(r) for tag, r in runs.items()}
    print(f"{args.method} on {args.setting}, scenes {args.scenes} (seed 0); load average {os.getloadavg()[0]:.1f}; "
          f"{args.rounds} process(es) per code; plans that compiled nothing; mean / median seconds\n")
    print("| code | plans | Stage 1 (s) | Stage 2 (s) | total (s) | objects from memory per plan | grasps | successes | objects left |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|")
    for tag, row in rows.items():
        cells = " | ".join(f"{row[k][0]:.3f} / {row[k][1]:.3f}" for k in KEYS)
        print(f"| {tag} | {row['plans']} | {cells} | {row['reused']:.1f} | {row['attempts']} | {row['successes']} | "
              f"{row['left']} of {row['objects']} |")
    if args.reference:
        ref, cur = rows[f"reference {args.reference}"], rows["current"]
        ratios = " | ".join(f"{cur[k][0] / ref[k][0]:.2f}" for k in KEYS)
        print(f"\nratio current / reference of the means: Stage 1 | Stage 2 | total = {ratios}")


if __name__ == "__main__":
    main()
