"""Refinements judged by the refine head alone (the paper's rule) vs re-scored at their refined pose
(`PlannerConfig.refine_rescore`), on a labelled directory no checkpoint was trained on.

    python benchmarks/refine_rescore.py $SGJAX_CACHE/labels/mix-v6 [--model RUN_DIR] [--threshold 0.7]

Prints a table (`train.refine_rescore.table`): on the samples the planner would refine (evaluation <= the
threshold), each score's AUC against the simulated refinement outcomes and the success of the refinements
it passes."""

from __future__ import annotations

import argparse
import sys

from train import dataset
from train.refine_rescore import rescore_directory, table


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("data", help="a labelled directory (sgjax label --out)")
    parser.add_argument("--model", default=None, help="a `sgjax train` run directory (default: the shipped checkpoint)")
    parser.add_argument("--threshold", type=float, default=0.7, help="the policy's bar (default 0.7)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    args = parser.parse_args(argv)
    try:
        columns = rescore_directory(args.data, args.model, progress=not args.quiet)
    except dataset.DatasetError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(f"{args.data}: {len(columns['label'])} valid samples, model {args.model or 'shipped'}\n")
    print(table(columns, args.threshold))
    return 0


if __name__ == "__main__":
    sys.exit(main())
