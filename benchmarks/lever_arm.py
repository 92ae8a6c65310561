"""The lever arm of labelled grasps and the lever-weighted choice (`PlannerConfig.lever_weight`), run by hand.

    python benchmarks/lever_arm.py DIR [DIR ...] [--model RUN_DIR] [--weights 0 0.5 1 2 4 8] [--out arms.npz]

For each labelled directory (and all of them pooled): per scene, whether the grasp the planner would
execute among its Stage-1 samples succeeds, with each lever weight (0: the highest eval_prob, E-RNet's
top grasp as `sgjax score-data` counts it); and the success of the samples E-RNet passes by their lever
arm; and the fitted superquadric's centre as evidence (`train.lever.fit_table`). How both are
measured: `train/lever.py` (each scene is rebuilt and observed again, ~0.2 s per scene). --out writes
the per-sample columns of all directories.
"""

from __future__ import annotations

import argparse

import numpy as np

from sgjax.utils.files import atomic_write
from train.dataset import DatasetError
from train.lever import COLUMNS, fit_table, lever_directory, table


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("directories", nargs="+", help="labelled directories (sgjax label --out)")
    parser.add_argument("--model", help="E-RNet run directory (default: the shipped one)")
    parser.add_argument("--weights", type=float, nargs="+", default=[0.0, 0.5, 1.0, 2.0, 4.0, 8.0])
    parser.add_argument("--threshold", type=float, default=0.7)
    parser.add_argument("--out", help="write the per-sample columns here (.npz)")
    args = parser.parse_args()
    parts = []
    try:
        for directory in args.directories:
            parts.append(lever_directory(directory, args.model))
            tables = f"{table(parts[-1], args.weights, args.threshold)}\n\n{fit_table(parts[-1])}"
            print(f"\n### {directory}\n\n{tables}", flush=True)
    except (DatasetError, FileNotFoundError) as exc:
        raise SystemExit(str(exc)) from None
    pooled = {k: np.concatenate([p[k] for p in parts]) for k in COLUMNS}
    if len(parts) > 1:
        tables = f"{table(pooled, args.weights, args.threshold)}\n\n{fit_table(pooled)}"
        print(f"\n### all {len(parts)} directories\n\n{tables}")
    if args.out:
        atomic_write(args.out, lambda tmp: np.savez(tmp, **pooled))


if __name__ == "__main__":
    main()
