"""Judges of the planner's finalists, compared offline on finalist shards (`sgjax label-finalists`).

    python benchmarks/finalist_judge.py SHARD_DIR [SHARD_DIR ...] [--judge RUN_DIR|paper|default ...]
                                        [--perturb SHIFT:DEG[,SHIFT:DEG ...]]

Every finalist of every state is scored by each judge at its own pose and at the robust choice's five
perturbed poses (`sgjax.planner.RobustChoice`: the same shift and angle), from the state's stored Stage-2
cloud, as the planner's judge would score them. Per judge the table gives how often its pick among a
state's finalists succeeds: by its own-pose score, and by its mean over the six poses (the planner's
rule); beside them the executed grasp (the logged choice) and the oracle (any finalist). Only states
where some finalists succeed and some fail ("mixed") can move the numbers; their count is printed. Ties
go to the better robust score of the logged plan, then the earlier finalist
(`train.finalists.finalist_choices`). --perturb: other perturbation sets than the robust choice's
(metres and degrees of `gripper.perturbed_poses`, five poses each; several sets pool their poses).
"""

from __future__ import annotations

import argparse
import glob
import os

import jax.numpy as jnp
import numpy as np
from flax import nnx

from sgjax.geometry import gripper
from sgjax.planner import RobustChoice
from sgjax.stage2 import ernet
from train.dataset import DEFAULT_SPEC, crop_samples, read_label_shard
from train.finalists import finalist_choices


def judge_scores(model, samples: dict, clouds: list, perturb: tuple[tuple[float, float], ...] | None = None,
                 batch: int = 64) -> tuple[np.ndarray, np.ndarray]:
    """-> (own-pose eval_prob [S], mean over the own and the perturbed poses [S]) of one shard's samples;
    perturb: (shift m, angle deg) sets of `gripper.perturbed_poses` (None: the robust choice's)."""
    if perturb is None:
        robust = RobustChoice()
        perturb = ((robust.shift, robust.angle_deg),)
    crop = model.config.crop
    poses = [np.asarray(gripper.perturbed_poses(jnp.asarray(samples["pose"]), shift, angle)) for shift, angle in perturb]
    k = 1 + 5 * len(perturb)
    every = np.concatenate([samples["pose"][:, None], *poses], axis=1).reshape(-1, 4, 4).astype(np.float32)
    expanded = {name: np.repeat(v, k, axis=0) for name, v in samples.items()}
    expanded["pose"] = every
    cropped = crop_samples(expanded, clouds, DEFAULT_SPEC, crop)
    graphdef, state = nnx.split(model)
    out = []
    for i in range(0, len(every), batch):
        part = slice(i, i + batch)
        region, mask, width = cropped["region"][part], cropped["region_mask"][part], cropped["width"][part]
        pad = batch - len(width)
        if pad:  # one compiled size
            region = np.concatenate([region, np.zeros((pad, *region.shape[1:]), region.dtype)])
            mask = np.concatenate([mask, np.zeros((pad, mask.shape[1]), bool)])
            width = np.concatenate([width, np.zeros(pad, width.dtype)])
        scores = ernet.score_regions(graphdef, state, region, mask, width, spec=DEFAULT_SPEC)
        out.append(np.asarray(scores.eval_prob)[: batch - pad])
    probs = np.concatenate(out).reshape(-1, k)
    return probs[:, 0], probs.mean(axis=1)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("shards", nargs="+", help="directories of finalist shards")
    parser.add_argument("--judge", nargs="+", default=["default"],
                        help="judges: 'default' (the shipped E-RNet), 'paper' (the shipped paper-size one) or run directories")
    parser.add_argument("--perturb", help="perturbation sets SHIFT:DEG[,SHIFT:DEG ...] (default: the robust choice's 0.005:10)")
    args = parser.parse_args()
    perturb = None
    if args.perturb:
        try:
            perturb = tuple((float(a), float(b)) for a, b in (item.split(":") for item in args.perturb.split(",")))
        except ValueError:
            raise SystemExit(f"--perturb {args.perturb!r}: give SHIFT:DEG pairs separated by commas, e.g. 0.005:10,0.01:20")
    paths = sorted(p for d in args.shards for p in glob.glob(os.path.join(d, "*.npz")))
    if not paths:
        raise SystemExit(f"no finalist shards in {args.shards}")
    print(f"{len(paths)} scene shard(s)")
    print("| judge | states | mixed | executed | own pose | mean of own + perturbed poses | oracle |\n|---|---:|---:|---:|---:|---:|---:|")
    for name in args.judge:
        model = ernet.as_judge(None if name == "default" else name) or ernet.as_model(None)
        rows_own, rows_mean = [], []
        for path in paths:
            samples, clouds = read_label_shard(path)
            own, mean = judge_scores(model, samples, clouds, perturb)
            rows_own += finalist_choices(path, own, samples)
            rows_mean += finalist_choices(path, mean, samples)
        states = len(rows_own)
        mixed = sum(c.any and not c.all for c in rows_own)
        pct = lambda k: f"{k} ({100 * k / states:.1f} %)"
        print(f"| {name} | {states} | {mixed} | {pct(sum(c.executed for c in rows_own))} | "
              f"{pct(sum(c.picked for c in rows_own))} | {pct(sum(c.picked for c in rows_mean))} | "
              f"{pct(sum(c.any for c in rows_own))} |", flush=True)


if __name__ == "__main__":
    main()
