"""Does a scorer judge a grasp and its finger-swapped twin alike, and does averaging the two help?
(run by hand; prints a markdown table).

    python benchmarks/swap_fingers.py --data DIR [DIR ...] --models shipped RUN_DIR [...]

A parallel-jaw grasp turned 180 degrees about its approach axis is the same physical grasp
(`sgjax.geometry.gripper.swap_fingers_local`). For each model (E-RNet; "shipped": the default
checkpoint) every valid sample of the labelled directories is scored as labelled, as its twin, and by
the mean of both probabilities, and judged as `sgjax score-data` judges (`train.judgement.judge`: AUC
overall and on GPD-style samples, calibration error, the top-scored Stage-1 grasp's success per scene).
Runs trained with `sgjax train --swap-fingers` saw both halves.
"""

from __future__ import annotations

import argparse

import jax
import numpy as np
from flax import nnx

from sgjax.geometry.gripper import swap_fingers_local
from sgjax.stage2.ernet import as_model
from train import dataset, trainer


def judged(model, samples: dict) -> dict[str, dict]:
    """{"as labelled" | "swapped" | "mean of both": judgement} of one model on the samples."""
    graphdef, params = nnx.split(model)
    _, _, eval_step = trainer.make_steps(graphdef, trainer.TrainConfig(model=model.config))
    key = jax.random.key(0)  # score-data's downsampling key: the same crops for every model
    twin = {**samples, "region": np.asarray(swap_fingers_local(samples["region"]))}
    plain = trainer.score_samples(eval_step, params, samples, 128, key)[1]
    swapped = trainer.score_samples(eval_step, params, twin, 128, key)[1]
    mean = {**plain, "prob": 0.5 * (plain["prob"] + swapped["prob"]),
            "refine_prob": 0.5 * (plain["refine_prob"] + swapped["refine_prob"])}
    return {name: trainer.judge_samples(per, samples)
            for name, per in (("as labelled", plain), ("swapped", swapped), ("mean of both", mean))}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", nargs="+", required=True, help="labelled directories (`sgjax label --out`)")
    parser.add_argument("--models", nargs="+", default=["shipped"], help="'shipped' or `sgjax train` run directories")
    args = parser.parse_args()
    print(f"samples: {', '.join(args.data)}\n")
    print("| model | scored | n | AUC | AUC gpd | ECE | top Stage-1 grasp succeeds |")
    print("|---|---|---:|---:|---:|---:|---:|")
    crops: dict[str, dict] = {}
    for name in args.models:
        model = as_model(None if name == "shipped" else name)
        crop = model.config.crop
        if crop not in crops:
            samples = dataset.read_shards(args.data, crop)
            crops[crop] = dataset.select(samples, np.flatnonzero(samples["valid"]))
        for scored, j in judged(model, crops[crop]).items():
            gpd = (j.get("per_source") or {}).get("gpd") or {}
            print(f"| {name} | {scored} | {j['samples']} | {j['auc']:.4f} | {gpd.get('auc', float('nan')):.4f} | "
                  f"{j['ece']:.4f} | {j['top1_success']:.4f} |", flush=True)


if __name__ == "__main__":
    main()
