"""Does the GPD-style sampler's fixed budget hold the baselines back in dense scenes? (by hand)

    python -m benchmarks.gpd_budget [--method gpd+s2] [--setting seen-20] [--scenes 10] [--seed 0]
                                    [--scales 1 2] [--out gpd_budget_out]

The GPD-style generator draws `GPDConfig.num_samples` x `num_angles` candidates per scene (896 by
default) whether 10 or 20 objects lie there, and the networks score at most `max_candidates` (512) of
them. This runs a baseline with both multiplied by each scale on the same scenes (resumable: one out
directory per scale) and prints GSR / TSR / GA per scale: if doubling the budget on the 20-object
setting does not move the numbers beyond their noise, the fixed budget does not matter.
"""

from __future__ import annotations

import argparse
import dataclasses

from envs.scene import stage2_scene_cloud
from eval.baselines import BaselineConfig
from eval.benchmark import run_benchmark
from eval.report import markdown_table, percent


def scaled_config(scale: int) -> BaselineConfig:
    """The registry's baseline config (workspace-cropped cloud) with the sampling budget times `scale`."""
    base = BaselineConfig(scene_cloud=stage2_scene_cloud())
    gpd = dataclasses.replace(base.gpd, num_samples=base.gpd.num_samples * scale)
    return dataclasses.replace(base, gpd=gpd, max_candidates=base.max_candidates * scale)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--method", default="gpd+s2", choices=("gpd+s2", "pointnetgpd"))
    parser.add_argument("--setting", default="seen-20")
    parser.add_argument("--scenes", type=int, default=10)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--scales", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--out", default="gpd_budget_out")
    args = parser.parse_args()

    rows = []
    for scale in args.scales:
        config = scaled_config(scale)
        result = run_benchmark(args.method, setting=args.setting, scenes=args.scenes, seed=args.seed,
                               out=f"{args.out}/scale-{scale}", method_options={"config": config}, progress=False)
        s, t = result.summary, result.timing["total_s"]
        samples = config.gpd.num_samples * config.gpd.num_angles
        rows.append([f"x{scale}", str(samples), str(config.max_candidates), percent(s.gsr), percent(s.tsr), str(s.ga),
                     f"{t[0]:.2f}"])
        print(f"scale {scale}: GSR {percent(s.gsr)} TSR {percent(s.tsr)} GA {s.ga}", flush=True)
    print(f"\n{args.method} on {args.setting}, seed {args.seed}, N = {args.scenes}")
    print(markdown_table(["budget", "samples", "scored slots", "GSR", "TSR", "GA", "planning per grasp (s)"], rows))


if __name__ == "__main__":
    main()
