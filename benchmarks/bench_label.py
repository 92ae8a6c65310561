"""Where labelling time goes: per-scene stages of `sgjax label` from its shard records (run by hand).

    python -m benchmarks.bench_label DIR [DIR ...]        # labelled directories (sgjax label --out)
    python -m benchmarks.bench_label --run N [--objects seen] [--out DIR]   # label N scenes first

Each shard's .json records per scene the seconds of: making the scene and rendering it ("scene"),
the candidates of every source ("candidates": Stage 1 twice and the GPD-style sampler), the grasp
trials ("trials") and the Stage-2 cloud ("cloud"). Prints one markdown row per directory: mean
seconds per stage per scene (the first scene, which compiles, left out), trials per scene, trials/s of
the simulation alone and end to end. Compare runs made in one sitting, as these machines are shared.
"""

from __future__ import annotations

import argparse
import glob
import json
import os
import tempfile

import numpy as np

STAGES = ("scene", "candidates", "trials", "cloud")


def stage_table(directory: str) -> dict:
    rows = []
    for path in sorted(glob.glob(os.path.join(directory, "scenes-*.json"))):
        with open(path) as fh:
            for scene in json.load(fh)["scenes"]:
                if scene.get("seconds") and scene["trials"]:
                    rows.append((scene["scene"], scene["trials"], [scene["seconds"].get(k, 0.0) for k in STAGES]))
    rows = [r for r in rows if r[0] != 0]  # scene 0 pays the compilation
    if not rows:
        raise SystemExit(f"{directory}: no timed scenes with trials (label some first)")
    trials = np.array([r[1] for r in rows], np.float64)
    seconds = np.array([r[2] for r in rows], np.float64)
    return {
        "scenes": len(rows),
        "stages": seconds.mean(0),
        "trials": trials.mean(),
        "sim_rate": trials.sum() / seconds[:, STAGES.index("trials")].sum(),
        "rate": trials.sum() / seconds.sum(),
    }


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("dirs", nargs="*")
    parser.add_argument("--run", type=int, default=0, help="label this many scenes into --out first")
    parser.add_argument("--objects", default="seen")
    parser.add_argument("--out", default=None)
    args = parser.parse_args()
    dirs = list(args.dirs)
    if args.run:
        from train import label

        out = args.out or tempfile.mkdtemp(prefix="bench_label-")
        label.label(out, args.run, label.LabelConfig(object_set=args.objects), progress=True)
        dirs.append(out)
    print("| directory | scenes | " + " | ".join(f"{s} s" for s in STAGES) + " | trials / scene | sim trials/s | end-to-end trials/s |")
    print("|---|---:|" + "---:|" * (len(STAGES) + 3))
    for d in dirs:
        t = stage_table(d)
        stages = " | ".join(f"{v:.2f}" for v in t["stages"])
        print(f"| {d} | {t['scenes']} | {stages} | {t['trials']:.0f} | {t['sim_rate']:.1f} | {t['rate']:.1f} |")


if __name__ == "__main__":
    main()
