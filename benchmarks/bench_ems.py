"""EMS speed and accuracy on CPU (run by hand; prints a markdown table).

    python -m benchmarks.bench_ems [--clouds 1024] [--repeats 3]

Speed: fits per second for batch sizes 1, 64 and 1024 of 800-point single-view clouds, after
compilation (reported separately). Accuracy: relative semi-axis error (frames matched, see
`sgjax.geometry.superquadric.relative_scale_error`) on random superquadrics of graspable size seen by one
camera, 800 points, 1 mm noise.
"""

from __future__ import annotations

import argparse

import jax
import numpy as np

from benchmarks.common import time_jitted
from sgjax.stage1 import ems
from sgjax.geometry import pointcloud, synthetic
from sgjax.geometry.superquadric import relative_scale_error


def make_set(n: int, seed: int = 0, outliers: float = 0.0):
    rng = np.random.default_rng(seed)
    truths, clouds = [], []
    for _ in range(n):
        sq = synthetic.random_superquadric(rng)
        truths.append(sq)
        clouds.append(synthetic.single_view_cloud(sq, 800, noise_std=0.001, outlier_ratio=outliers, seed=rng))
    return truths, clouds


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--clouds", type=int, default=1024)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()

    truths, clouds = make_set(args.clouds)
    points, mask = pointcloud.pad_clouds(clouds, n_points=800)
    print(f"jax {jax.__version__}, devices {jax.devices()}, {args.clouds} clouds of 800 points\n")
    print("| batch | compile (s) | time per call (ms) | fits/s |")
    print("|---:|---:|---:|---:|")
    result = None
    for b in (1, 64, 1024):
        if b > args.clouds:
            continue
        compile_s, run_s, out = time_jitted(lambda: ems.fit_superquadrics(points[:b], mask[:b]), args.repeats)
        if b == min(1024, args.clouds):
            result = out
        print(f"| {b} | {compile_s:.1f} | {run_s * 1e3:.1f} | {b / run_s:.0f} |")
    if result is None:
        result = ems.fit_superquadrics(points, mask)

    rows = []
    for name, outl in (("single view, 1 mm noise", 0.0), ("single view, 1 mm noise, 20 % outliers", 0.2)):
        if outl:
            truths_o, clouds_o = make_set(min(args.clouds, 256), seed=1, outliers=outl)
            p, m = pointcloud.pad_clouds(clouds_o, n_points=800)
            res, tr = ems.fit_superquadrics(p, m), truths_o
        else:
            res, tr = result, truths
        n = len(tr)
        err = np.array([relative_scale_error(res[i].superquadric, tr[i]) for i in range(n)])
        eps = np.array([np.abs(np.asarray(res.epsilon[i]) - np.asarray(tr[i].epsilon)).mean() for i in range(n)])
        rows.append((name, n, np.median(err), np.percentile(err, 90), np.median(eps), np.mean(np.asarray(res.valid))))
    print("\n| set | clouds | median rel. scale error | p90 rel. scale error | median eps error | valid |")
    print("|---|---:|---:|---:|---:|---:|")
    for name, n, med, p90, eps, valid in rows:
        print(f"| {name} | {n} | {med * 100:.2f} % | {p90 * 100:.1f} % | {eps:.3f} | {valid * 100:.0f} % |")


if __name__ == "__main__":
    main()
