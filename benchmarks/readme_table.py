"""A results directory's rows as README's tables print them (run by hand; prints a markdown table).

    python -m benchmarks.readme_table DIR [--settings S,S,...] [--methods M,M,...]

Reads DIR/results.csv and DIR/timing.csv (what `sgjax declutter` / `sgjax table-i` / `sgjax table-ii`
write) and prints one row per method (in --methods order, default: as they first appear): "GSR / TSR /
GA" per setting (likewise --settings; the cell's scene count after it when the cells' counts differ)
and the method's mean planning time per executed grasp. README's Table I and
Table II (simulated) are this script's output for the report's directories.
"""

from __future__ import annotations

import argparse
import csv
import os

from eval.report import markdown_table


def read_csv(path: str) -> list[dict[str, str]]:
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def table(out: str, settings: list[str] | None = None, methods: list[str] | None = None) -> str:
    """The markdown table of `out`'s results (module doc)."""
    rows = read_csv(os.path.join(out, "results.csv"))
    timing = {r["method"]: float(r["total_s_mean"]) for r in read_csv(os.path.join(out, "timing.csv"))}
    settings = settings or list(dict.fromkeys(r["setting"] for r in rows))
    methods = methods or list(dict.fromkeys(r["method"] for r in rows))
    cells = {(r["method"], r["setting"]): r for r in rows}
    counted = len({r["scenes"] for r in rows}) > 1
    body = []
    for method in methods:
        shown = []
        for setting in settings:
            r = cells.get((method, setting))
            shown.append("" if r is None else
                         f"{100 * float(r['GSR']):.2f} % / {100 * float(r['TSR']):.2f} % / {int(r['GA'])}"
                         + (f" (N = {r['scenes']})" if counted else ""))
        body.append([method, *shown, f"{timing.get(method, float('nan')):.2f}"])
    return markdown_table(["Method", *settings, "planning per grasp (s)"], body)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("out", help="a results directory (results.csv, timing.csv)")
    parser.add_argument("--settings", default=None, help="settings to show, in order (default: all)")
    parser.add_argument("--methods", default=None, help="methods to show, in order (default: all)")
    args = parser.parse_args()
    split = lambda value: None if value is None else value.split(",")
    print(table(args.out, split(args.settings), split(args.methods)))


if __name__ == "__main__":
    main()
