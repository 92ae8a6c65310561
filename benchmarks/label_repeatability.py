"""How repeatable a labelled directory's outcomes are: each sample's grasp replayed on its rebuilt scene,
as recorded and moved by a millimetre or a degree (run by hand).

    python benchmarks/label_repeatability.py DIR [--scenes 1744:1944] [--sources stage1] [--moves 4]
        [--shift 0.001] [--turn 1.0] [--out samples.npz]

What it measures and why: `train/repeatability.py`. Prints one markdown row per source and, over the
scenes, how often some Stage-1 grasp of a scene stays successful under every move (the ceiling of "the
top-scored grasp succeeds" at that robustness).
--out writes the per-sample outcomes (rows in the directory's sample order, valid samples of the chosen
scenes and sources) for joins with `sgjax score-data`'s inputs.
"""

from __future__ import annotations

import argparse

import numpy as np

from sgjax.utils.files import atomic_write
from train.dataset import DatasetError
from train.repeatability import replay_directory, table


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("directory", help="a labelled directory (sgjax label --out)")
    parser.add_argument("--scenes", help="FIRST:LAST scene indices (default: all)")
    parser.add_argument("--sources", default="stage1", help="comma-separated candidate sources (default stage1)")
    parser.add_argument("--moves", type=int, default=4)
    parser.add_argument("--shift", type=float, default=0.001, help="metres")
    parser.add_argument("--turn", type=float, default=1.0, help="degrees")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", help="write the per-sample outcomes here (.npz)")
    args = parser.parse_args()
    scenes = None
    if args.scenes:
        first, last = (int(x) for x in args.scenes.split(":"))
        scenes = (first, last)
    try:
        replayed = replay_directory(args.directory, scenes, tuple(args.sources.split(",")), args.moves, args.shift,
                                    args.turn, args.seed)
    except (DatasetError, FileNotFoundError) as exc:
        raise SystemExit(str(exc)) from None
    if args.out:
        atomic_write(args.out, lambda tmp: np.savez(tmp, **replayed))
    print(table(replayed, args.moves, args.shift, args.turn))


if __name__ == "__main__":
    main()
