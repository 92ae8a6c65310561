"""Compare training runs by their held-out judgement (run by hand; prints a markdown table).

    python -m benchmarks.judgement_table RUN_DIR [RUN_DIR ...] [--epoch N]

Reads each run's metrics.json (`sgjax train`) and prints, for its last epoch (or --epoch N), the
held-out scenes' AUC overall and per candidate source, calibration error, the mean score of collided
grasps, the refinement heads' AUC, the top-scored Stage-1 grasp's success per scene, and the held-out
objects' AUC (`train/judgement.py` defines each).
"""

from __future__ import annotations

import argparse
import json
import os

from train.sources import SOURCES


def _f(v) -> str:
    return "–" if v is None else f"{v:.3f}"


def row(run_dir: str, epoch: int | None) -> str:
    with open(os.path.join(run_dir, "metrics.json")) as fh:
        history = json.load(fh)["history"]
    record = history[-1] if epoch is None else next(r for r in history if r["epoch"] == epoch)
    held = (record.get("held_out") or {}).get("judgement") or {}
    objects = (record.get("held_out_objects") or {}).get("judgement") or {}
    per_source = held.get("auc_per_source") or {}
    refine = held.get("refine_auc")
    return " | ".join(
        [
            os.path.basename(os.path.normpath(run_dir)),
            str(record["epoch"]),
            str(held.get("samples", "–")),
            _f(held.get("auc")),
            " / ".join(_f(per_source.get(s)) for s in SOURCES),
            _f(held.get("ece")),
            _f(held.get("collision_score")),
            " / ".join(_f(v) for v in refine) if refine else "–",
            _f(held.get("top1_success", held.get("top_success"))),  # runs before 2026-12-02: top_success
            f"{_f(objects.get('auc'))} ({objects.get('samples', 0)})",
        ]
    )


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("runs", nargs="+")
    parser.add_argument("--epoch", type=int, default=None)
    args = parser.parse_args()
    print(
        "| run | epoch | held-out samples | AUC | AUC " + " / ".join(SOURCES)
        + " | ECE | collisions' mean score | refine AUC | top Stage-1 grasp succeeds | held-out objects AUC (samples) |"
    )
    print("|---|---:|---:|---:|---|---:|---:|---|---:|---|")
    for run in args.runs:
        print("| " + row(run, args.epoch) + " |")


if __name__ == "__main__":
    main()
