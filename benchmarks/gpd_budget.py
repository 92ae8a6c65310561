"""Does the GPD-style sampler's budget hold the baselines back in dense scenes? (by hand)

    python -m benchmarks.gpd_budget [--method gpd+s2] [--setting seen-20] [--scenes 12] [--seed 0]
                                    [--budgets fixed scaled] [--out gpd_budget_out]

The GPD-style generator draws `GPDConfig.num_samples` x `num_angles` candidates (896 by default) and the
networks score at most `max_candidates` (512) of them. `fixed`: that budget whether 10 or 20 objects
lie there (`objects_per_budget=0`, the rule before 2026-12-05); `scaled`: the default, both times
ceil(objects in view / 10). Runs a baseline with each on the same scenes (resumable: one out directory
per budget) and prints GSR / TSR / GA per budget.
"""

from __future__ import annotations

import argparse
import dataclasses

from envs.scene import stage2_scene_cloud
from eval.baselines import BaselineConfig
from sgjax.samplers.gpd import GPDConfig
from eval.benchmark import run_benchmark
from eval.report import markdown_table, percent


BUDGETS = {"fixed": 0, "scaled": GPDConfig.objects_per_budget}


def budget_config(budget: str) -> BaselineConfig:
    """The registry's baseline config (workspace-cropped cloud) with the fixed or the scaled budget."""
    base = BaselineConfig(scene_cloud=stage2_scene_cloud())
    return dataclasses.replace(base, gpd=dataclasses.replace(base.gpd, objects_per_budget=BUDGETS[budget]))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--method", default="gpd+s2", choices=("gpd+s2", "pointnetgpd"))
    parser.add_argument("--setting", default="seen-20")
    parser.add_argument("--scenes", type=int, default=12)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--budgets", nargs="+", default=list(BUDGETS), choices=list(BUDGETS))
    parser.add_argument("--out", default="gpd_budget_out")
    args = parser.parse_args()

    rows = []
    for budget in args.budgets:
        config = budget_config(budget)
        result = run_benchmark(args.method, setting=args.setting, scenes=args.scenes, seed=args.seed,
                               out=f"{args.out}/{budget}", method_options={"config": config}, progress=False)
        s, t = result.summary, result.timing["total_s"]
        rows.append([budget, percent(s.gsr), percent(s.tsr), str(s.ga), f"{t[0]:.2f}"])
        print(f"{budget}: GSR {percent(s.gsr)} TSR {percent(s.tsr)} GA {s.ga}", flush=True)
    print(f"\n{args.method} on {args.setting}, seed {args.seed}, N = {args.scenes}")
    print(markdown_table(["budget", "GSR", "TSR", "GA", "planning per grasp (s)"], rows))


if __name__ == "__main__":
    main()
