"""Where a set of benchmark cells' failures come from, read off their scene logs (no simulation).

    python -m benchmarks.log_breakdown DIR [DIR ...] [--bars 0.7 0.72 0.75 0.8]

Each DIR is searched for scene logs (`scene_<index>.json` at any depth, e.g. a `sgjax declutter --out`
folder or one of its logs/<method>/<setting>/seed<k> folders); all of them are pooled. Prints GSR / TSR /
GA, then the attempts and their success by how SuperGrasp chose the grasp (`eval.metrics.how_chosen`:
first or second plan, evaluated or refined, on the fit or transferred, judged by the robust choice or
alone), by the executed grasp's score (is it calibrated?) and by its approach's tilt from straight down,
each with the failures by outcome; and, per bar, the metrics had each scene stopped at its first grasp
scored at or below the bar (`eval.metrics.stopped_at`: what a stricter bar on the executed grasp buys in
GSR and costs in TSR, exactly, from the same logs).
"""

from __future__ import annotations

import argparse
from collections.abc import Callable, Hashable, Mapping
from pathlib import Path

from eval import metrics
from eval.report import logs_under, markdown_table, percent


def read_logs(folders: list[Path]) -> list[dict]:
    """Every scene log under `folders` (`eval.report.logs_under`); SystemExit naming a folder without any."""
    logs = []
    for folder in folders:
        found = logs_under(folder)
        if not found:
            raise SystemExit(f"{folder}: no scene_<index>.json logs")
        logs += found
    return logs


def breakdown_table(logs: list[Mapping], key: Callable[[Mapping], Hashable], title: str, order=None) -> str:
    """Attempts, successes and failures by outcome per key(attempt) (`metrics.outcomes_by`), as markdown."""
    groups = metrics.outcomes_by(logs, key)
    failures = sorted({o for c in groups.values() for o in c if o != "success"})
    rows = []
    by_size = sorted(groups, key=lambda k: -sum(groups[k].values()))
    # The given order first, then any group it does not name (no attempt is ever left out).
    for k in [k for k in order or [] if k in groups] + [k for k in by_size if k not in (order or [])]:
        c = groups[k]
        n = sum(c.values())
        rows.append([k, n, c["success"], percent(c["success"] / n), *(c[o] for o in failures)])
    return markdown_table([title, "attempts", "succeed", "rate", *failures], rows)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("folders", nargs="+", type=Path, help="folders holding scene logs (searched recursively)")
    parser.add_argument("--bars", type=float, nargs="+", default=[0.7, 0.72, 0.75, 0.8],
                        help="stop each scene at its first grasp scored at or below the bar")
    args = parser.parse_args()
    logs = read_logs(args.folders)
    s = metrics.summarize(logs)
    print(f"{s.scenes} scenes, {s.objects} objects: GSR {percent(s.gsr)} / TSR {percent(s.tsr)} / GA {s.ga}\n")
    print(breakdown_table(logs, metrics.how_chosen, "how the grasp was chosen") + "\n")
    score_order = [f"{lo:g}-{hi:g}" for lo, hi in zip(metrics.SCORE_EDGES[:-1], metrics.SCORE_EDGES[1:])]
    print(breakdown_table(logs, lambda a: metrics.bin_label(a.get("score"), metrics.SCORE_EDGES),
                          "executed grasp's score", score_order) + "\n")
    tilt_order = [f"{lo:g}-{hi:g}" for lo, hi in zip(metrics.TILT_EDGES[:-1], metrics.TILT_EDGES[1:])]
    tilt = lambda a: metrics.bin_label(None if a.get("pose") is None else metrics.approach_tilt(a["pose"]), metrics.TILT_EDGES)
    print(breakdown_table(logs, tilt, "approach tilt from straight down (deg)", tilt_order) + "\n")
    rows = []
    for bar in args.bars:
        b = metrics.stopped_at(logs, bar)
        rows.append([f"{bar:g}", percent(b.gsr), percent(b.tsr), b.ga])
    print("Each scene stopped at its first grasp scored at or below the bar:\n")
    print(markdown_table(["bar", "GSR", "TSR", "GA"], rows))


if __name__ == "__main__":
    main()
