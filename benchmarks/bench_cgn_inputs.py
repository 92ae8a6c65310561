"""Contact-GraspNet's input cloud, measured in the decluttering benchmark (by hand; needs its environment).

    python benchmarks/bench_cgn_inputs.py [--inputs crop-grid crop whole] [--opening full] [--setting seen-10]
                                          [--scenes 5] [--seed 0] [--out bench_cgn_inputs]

Runs `contact-graspnet` once per input choice, each into OUT/<input>-<opening> (a changed config is refused
in an existing out directory), on the same scenes (same seed), then prints per choice GSR / TSR / GA,
the attempts' outcomes (the phase each failure happened in), how the scenes ended and why plans found
no grasp. Resumable: rerun the same command to continue.

    crop-grid  the benchmark's workspace (+ 5 cm) on a 3 mm grid, like SuperGrasp's Stage-2 cloud
    crop       the same crop, every rendered point (then a seeded 20,000-point subsample)
    whole      the whole rendered cloud, table and all, as CGN's training scenes (20,000-point subsample)
"""

from __future__ import annotations

import argparse
import collections
import json
from pathlib import Path

from envs.scene import stage2_scene_cloud
from eval.benchmark import run_benchmark
from eval.contact_graspnet import CGNConfig
from eval.report import percent


def input_config(name: str, opening: str = "full", backoff: float = 0.0) -> CGNConfig:
    """The CGNConfig of an input choice (crop-grid | crop | whole) and opening rule (full | predicted)."""
    cloud = stage2_scene_cloud()
    choices = {
        "crop-grid": CGNConfig(voxel=cloud.voxel, scene_bounds=cloud.bounds, opening=opening, table_backoff=backoff),
        "crop": CGNConfig(voxel=0.0, scene_bounds=cloud.bounds, opening=opening, table_backoff=backoff),
        "whole": CGNConfig(voxel=0.0, scene_bounds=None, opening=opening, table_backoff=backoff),
    }
    if name not in choices:
        raise ValueError(f"unknown input {name!r}; expected one of {', '.join(choices)}")
    return choices[name]


def summarise(out: Path) -> dict:
    """Outcomes, scene ends and no-grasp reasons over the logs under `out`."""
    outcomes, ends, reasons, points = collections.Counter(), collections.Counter(), collections.Counter(), []
    for path in sorted(out.glob("logs/**/scene_*.json")):
        log = json.loads(path.read_text())
        ends[log["end"]] += 1
        if log.get("final_reason"):
            reasons[log["final_reason"].split(" (")[0][:90]] += 1
        for attempt in log["attempts"]:
            outcomes[attempt["outcome"]] += 1
            points.append(attempt["info"].get("points", 0))
    return {"outcomes": dict(outcomes), "ends": dict(ends), "no_grasp": dict(reasons),
            "mean_points": round(sum(points) / max(1, len(points)))}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--inputs", nargs="+", default=["crop-grid", "crop", "whole"])
    parser.add_argument("--opening", default="full", choices=("full", "predicted"))
    parser.add_argument("--backoff", type=float, default=0.0, help="CGNConfig.table_backoff (m)")
    parser.add_argument("--setting", default="seen-10")
    parser.add_argument("--scenes", type=int, default=5)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default="bench_cgn_inputs")
    args = parser.parse_args()
    for name in args.inputs:
        out = Path(args.out) / (f"{name}-{args.opening}" + (f"-backoff{args.backoff:g}" if args.backoff else ""))
        result = run_benchmark("contact-graspnet", setting=args.setting, scenes=args.scenes, seed=args.seed, out=out,
                               method_options={"config": input_config(name, args.opening, args.backoff)}, progress=False)
        s = result.summary
        print(f"{name}, opening {args.opening}, backoff {args.backoff:g}: GSR {percent(s.gsr)}  TSR {percent(s.tsr)}  GA {s.ga}  ({s.successes} successes, "
              f"{s.objects} objects, {s.cleared} of {s.scenes} scenes cleared)", flush=True)
        print("  " + json.dumps(summarise(out)), flush=True)


if __name__ == "__main__":
    main()
