"""Benchmark output: per-scene JSON logs, Table I / Table III style tables, pictures of scenes.

Layout of an output directory (everything written atomically, so an interrupted run leaves no half
file and a rerun with the same directory continues where it stopped):

    OUT/logs/<method>/<setting>/seed<S>/scene_<iii>.json   one log per finished scene
    OUT/pictures/<method>/<setting>/seed<S>/scene_<iii>.png the first scenes, with the executed grasps
    OUT/results.csv, OUT/results.md                         every log under OUT, merged (Table I)
    OUT/timing.csv                                          per-grasp planning time (Table III)

results.md holds both tables. They are recomputed from all logs in OUT each time, so runs of other
methods, settings or seeds into the same OUT add rows and columns.
"""

from __future__ import annotations

import csv
import io
import json
import math
import os
import re
from collections import defaultdict
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path

import numpy as np

from eval import metrics
from sgjax.utils.files import atomic_write, atomic_write_text
from sgjax.geometry.gripper import GripperSpec

LOGS = "logs"
PICTURES = "pictures"
PAPER_SETTINGS = ("seen-10", "seen-20", "unseen-10", "real-similar", "real-novel")  # Table I, then Table II


# ---------------------------------------------------------------------------------------------------
# Logs.


def run_dir(out: str | os.PathLike, kind: str, method: str, setting: str, seed: int) -> Path:
    """OUT/<kind>/<method>/<setting>/seed<S> (kind: "logs" or "pictures")."""
    return Path(out) / kind / method / setting / f"seed{int(seed)}"


def scene_log_path(out: str | os.PathLike, method: str, setting: str, seed: int, index: int) -> Path:
    return run_dir(out, LOGS, method, setting, seed) / f"scene_{int(index):03d}.json"


def picture_path(out: str | os.PathLike, method: str, setting: str, seed: int, index: int) -> Path:
    return run_dir(out, PICTURES, method, setting, seed) / f"scene_{int(index):03d}.png"


def _write_text(path: Path, text: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(path, text)


def write_scene_log(path: str | os.PathLike, log: Mapping) -> None:
    """Write one scene log as JSON (atomically)."""
    _write_text(Path(path), json.dumps(log, indent=1))


def read_scene_log(path: str | os.PathLike) -> dict | None:
    """The scene log at `path`, or None if there is none."""
    try:
        return json.loads(Path(path).read_text())
    except FileNotFoundError:
        return None
    except (OSError, ValueError) as exc:
        raise ValueError(f"unreadable scene log {path}: {exc}") from exc


def read_logs(out: str | os.PathLike) -> list[dict]:
    """Every scene log under OUT/logs, in path order."""
    return logs_under(Path(out) / LOGS)


def is_scene_log(path: str | os.PathLike) -> bool:
    """Whether `path` names a scene log, scene_<index>.json (not, e.g., other JSON beside it)."""
    return re.fullmatch(r"scene_\d+\.json", Path(path).name) is not None


def logs_under(folder: str | os.PathLike) -> list[dict]:
    """Every scene log (`is_scene_log`) below `folder`, at any depth, in path order ([] if none)."""
    root = Path(folder)
    if not root.is_dir():
        return []
    return [read_scene_log(p) for p in sorted(root.rglob("scene_*.json")) if is_scene_log(p)]


# ---------------------------------------------------------------------------------------------------
# Tables.


def _group(logs: Iterable[Mapping]) -> dict[tuple[str, str, int], list[Mapping]]:
    groups: dict[tuple[str, str, int], list[Mapping]] = defaultdict(list)
    for log in logs:
        groups[(log["method"], log["setting"], int(log["seed"]))].append(log)
    return groups


def _method_order(names: Iterable[str]) -> list[str]:
    from eval.methods import METHODS
    from eval.protocol import split_preset

    order = list(METHODS)
    base = lambda n: split_preset(n)[0]  # "supergrasp@paper" sits beside "supergrasp"
    return sorted(set(names), key=lambda n: (order.index(base(n)) if base(n) in order else len(order), n))


def _setting_order(names: Iterable[str]) -> list[str]:
    def key(name: str):  # "seen-10@realsense+clusters" (seen through a sensor) sits beside "seen-10"
        base, _, view = name.partition("@")
        return (PAPER_SETTINGS.index(base) if base in PAPER_SETTINGS else len(PAPER_SETTINGS), base, view)

    return sorted(set(names), key=key)


def result_rows(logs: Iterable[Mapping]) -> list[dict]:
    """One row per (method, setting, seed): metrics and per-grasp timing means (seconds)."""
    rows = []
    for (method, setting, seed), group in _group(logs).items():
        summary = metrics.summarize(group)
        timing = metrics.timing_summary(group)
        row = {"method": method, "setting": setting, "seed": seed, **summary.as_dict(), **_objects_columns(group)}
        for key, (mean, std, _) in timing.items():
            row[f"{key}_mean"], row[f"{key}_std"] = mean, std
        for name, interval in metrics.scene_intervals(group).items():
            row[f"{name}_lo"], row[f"{name}_hi"] = interval if interval else (None, None)
        rows.append(row)
    methods, settings = _method_order(r["method"] for r in rows), _setting_order(r["setting"] for r in rows)
    rows.sort(key=lambda r: (methods.index(r["method"]), settings.index(r["setting"]), r["seed"]))
    return rows


def _objects_columns(group: Iterable[Mapping]) -> dict:
    """The object set a group of scenes ran on: {"object_set", "objects_n", "objects_hash", "skipped"}
    ("?" for logs written before sets were recorded; "mixed" if the scenes disagree)."""
    identities = {json.dumps(log.get("object_set"), sort_keys=True) for log in group}
    if len(identities) > 1:
        return {"object_set": "mixed", "objects_n": "mixed", "objects_hash": "mixed", "skipped": ""}
    identity = json.loads(identities.pop()) if identities else None
    if not identity:
        return {"object_set": "?", "objects_n": "?", "objects_hash": "?", "skipped": ""}
    return {
        "object_set": identity["name"],
        "objects_n": identity["size"],
        "objects_hash": identity["hash"],
        "skipped": " ".join(identity.get("skipped", [])),
    }


def objects_markdown(rows: list[dict]) -> str:
    """One line per setting: the object set its scenes came from (name, size, hash, skipped meshes)."""
    lines = []
    for setting in _setting_order(r["setting"] for r in rows):
        seen = {(r["object_set"], r["objects_n"], r["objects_hash"], r["skipped"]) for r in rows if r["setting"] == setting}
        for name, size, digest, skipped in sorted(seen, key=str):
            note = f"; **skipped: {skipped}**" if skipped else ""
            lines.append(f"- {setting}: object set `{name}`, {size} objects, names hash `{digest}`{note}")
    return "\n".join(lines)


def numerics_markdown(logs: Iterable[Mapping]) -> str:
    """One line per setting and numerics label (`eval.numerics.numerics_label`) with its scene count;
    logs written before the label was recorded count as "not recorded"."""
    counts: dict[tuple[str, str], int] = defaultdict(int)
    for log in logs:
        counts[(log["setting"], log.get("numerics") or "not recorded")] += 1
    return "\n".join(f"- {setting}: {label} ({n} scenes)" for (setting, label), n in sorted(counts.items())) or "- no scenes"


def percent(value: float | None) -> str:
    return "–" if value is None or (isinstance(value, float) and math.isnan(value)) else f"{100 * value:.2f}%"


def markdown_table(head: Sequence[str], rows: Iterable[Sequence]) -> str:
    """A markdown table: the header cells head, then one line per row of cells (str() of each)."""
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    return "\n".join(lines + ["| " + " | ".join(str(c) for c in row) + " |" for row in rows])


def table_i_markdown(rows: list[dict]) -> str:
    """Table I: methods x settings -> GSR, TSR, GA and the number of scenes N."""
    columns = []
    for row in rows:
        if (row["setting"], row["seed"]) not in columns:
            columns.append((row["setting"], row["seed"]))
    settings = _setting_order(s for s, _ in columns)
    columns.sort(key=lambda c: (settings.index(c[0]), c[1]))
    several = {s for s in settings if sum(c[0] == s for c in columns) > 1}
    labels = [f"{s} (seed {seed})" if s in several else s for s, seed in columns]
    by_key = {(r["method"], r["setting"], r["seed"]): r for r in rows}
    head = ["Method"] + [f"{label} {m}" for label in labels for m in ("GSR", "TSR", "GA", "N")]
    body = []
    for method in _method_order(r["method"] for r in rows):
        cells = [method]
        for setting, seed in columns:
            r = by_key.get((method, setting, seed))
            cells += ["", "", "", ""] if r is None else [percent(r["GSR"]), percent(r["TSR"]), str(r["GA"]), str(r["scenes"])]
        body.append(cells)
    return markdown_table(head, body)


def intervals_markdown(rows: list[dict]) -> str:
    """GSR and TSR of each cell with its 95 % interval by resampling scenes (`metrics.scene_intervals`)."""
    def cell(r, name):
        if r.get(f"{name}_lo") is None:
            return percent(r[name])
        return f"{percent(r[name])} ({100 * r[f'{name}_lo']:.1f}–{100 * r[f'{name}_hi']:.1f})"

    body = [[r["method"], r["setting"], str(r["seed"]), cell(r, "GSR"), cell(r, "TSR"), str(r["scenes"])] for r in rows]
    return markdown_table(["Method", "Setting", "Seed", "GSR (95 % interval)", "TSR (95 % interval)", "N"], body)


def timing_rows(logs: Iterable[Mapping]) -> list[dict]:
    """Table III rows: per method, Stage-1 / Stage-2 / total planning seconds per executed grasp."""
    by_method: dict[str, list[Mapping]] = defaultdict(list)
    for log in logs:
        by_method[log["method"]].append(log)
    rows = []
    for method in _method_order(by_method):
        timing = metrics.timing_summary(by_method[method])
        row = {"method": method, "grasps": timing["total_s"][2]}
        for key, (mean, std, _) in timing.items():
            row[f"{key}_mean"], row[f"{key}_std"] = mean, std
        rows.append(row)
    return rows


def failures_markdown(logs: Iterable[Mapping]) -> str:
    """Per (method, setting, seed): failed grasps by outcome, unfinished scenes by why they ended and the
    objects they left (`metrics.failure_breakdown`)."""
    lines = ["| Method | Setting | N | failed grasps (by outcome) | unfinished scenes: why (scenes, objects left) |",
             "|---|---|---|---|---|"]
    groups = _group(logs)
    methods, settings = _method_order(k[0] for k in groups), _setting_order(k[1] for k in groups)
    for key in sorted(groups, key=lambda k: (methods.index(k[0]), settings.index(k[1]), k[2])):
        b = metrics.failure_breakdown(groups[key])
        failed = ", ".join(f"{k} {v}" for k, v in b["failed"].most_common()) or "–"
        ends = "; ".join(f"{k} ({v}, {b['left'][k]})" for k, v in b["unfinished"].most_common()) or "–"
        lines.append(f"| {key[0]} | {key[1]} | {len(groups[key])} | {failed} | {ends} |")
    return "\n".join(lines)


def segments_markdown(logs: Iterable[Mapping]) -> str:
    """Per (method, setting, seed) run with segmented masks: its attempts by how the cluster planned on
    matched the objects (`metrics.segment_breakdown`), "attempts, GSR" each; "" when no run had them."""
    head = ["Method", "Setting", "N", *metrics.SEGMENT_GRADES]
    rows = []
    groups = _group(logs)
    methods, settings = _method_order(k[0] for k in groups), _setting_order(k[1] for k in groups)
    for key in sorted(groups, key=lambda k: (methods.index(k[0]), settings.index(k[1]), k[2])):
        b = metrics.segment_breakdown(groups[key])
        if b is not None:
            cells = [f"{n}, {percent(s / n if n else None)}" if n else "–" for n, s in b.values()]
            rows.append([key[0], key[1], len(groups[key]), *cells])
    return markdown_table(head, rows) if rows else ""


def object_outcomes_markdown(logs: Iterable[Mapping], top: int = 12) -> str:
    """Per setting, the `top` objects most often not grasped (then most failed on) over its cells, with
    per method (seeds pooled) "not grasped / in scenes, failed grasps" (`metrics.object_breakdown`);
    objects every method grasped every time without a failure are left out."""
    by_cell: dict[tuple[str, str], list[Mapping]] = defaultdict(list)
    for log in logs:
        by_cell[(log["setting"], log["method"])].append(log)
    sections = []
    for setting in _setting_order(k[0] for k in by_cell):
        methods = _method_order(m for s, m in by_cell if s == setting)
        counts = {m: metrics.object_breakdown(by_cell[(setting, m)]) for m in methods}
        names = {n for c in counts.values() for n, o in c.items() if o.not_grasped or o.failed}
        total = lambda n, key: sum(getattr(c[n], key) for c in counts.values() if n in c)
        order = sorted(names, key=lambda n: (-total(n, "not_grasped"), -total(n, "failures"), n))
        body = []
        for name in order[:top]:
            cells = []
            for m in methods:
                o = counts[m].get(name)
                cells.append("–" if o is None else f"{o.not_grasped} / {o.scenes}, {o.failures}")
            body.append([name, *cells])
        more = f" ({len(order) - top} more)" if len(order) > top else ""
        head = f"{setting}{more}: not grasped / in scenes, failed grasps"
        sections.append(f"{head}\n\n" + (markdown_table(["object", *methods], body) if body else "every object grasped, no failure"))
    return "\n\n".join(sections)


def harness_markdown(logs: Iterable[Mapping]) -> str:
    """Per method: the harness's own seconds per attempt (observe, trial, re-settle) beside the plan
    call's, and the wall seconds per scene (`metrics.harness_summary`)."""
    by_method: dict[str, list[Mapping]] = defaultdict(list)
    for log in logs:
        by_method[log["method"]].append(log)
    lines = ["| Method | observe (s) | plan (s) | trial (s) | re-settle (s) | per scene (s) | attempts |",
             "|---|---|---|---|---|---|---|"]
    for method in _method_order(by_method):
        h = metrics.harness_summary(by_method[method])
        cells = ["–" if math.isnan(h[k][0]) else f"{h[k][0]:.3f}" for k in ("observe_s", "plan_s", "trial_s", "settle_s")]
        scene = "–" if math.isnan(h["scene_s"][0]) else f"{h['scene_s'][0]:.1f}"
        lines.append(f"| {method} | " + " | ".join(cells) + f" | {scene} | {h['plan_s'][1]} |")
    return "\n".join(lines)


def _seconds(mean: float, std: float) -> str:
    return "–" if math.isnan(mean) else f"{mean:.3f} ± {std:.3f}"


def table_iii_markdown(rows: list[dict]) -> str:
    """Table III: per method, mean ± std seconds of Stage-1, Stage-2 and the whole plan per grasp."""
    lines = ["| Method | Stage-1 (s) | Stage-2 (s) | Total (s) | grasps |", "|---|---|---|---|---|"]
    for r in rows:
        cells = [_seconds(r[f"{k}_mean"], r[f"{k}_std"]) for k in metrics.TIMING_KEYS]
        lines.append(f"| {r['method']} | " + " | ".join(cells) + f" | {r['grasps']} |")
    return "\n".join(lines)


def _csv(rows: list[dict]) -> str:
    if not rows:
        return ""
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=list(rows[0]), lineterminator="\n")
    writer.writeheader()
    for row in rows:
        writer.writerow({k: "" if v is None else v for k, v in row.items()})
    return buffer.getvalue()


def _segments_section(logs: Iterable[Mapping]) -> str:
    table = segments_markdown(logs)
    if not table:
        return ""
    return ("With segmented masks (`--masks clusters`), attempts by the cluster they were planned on, against the exact "
            "render's objects: clean (one object, >= 80 % of it), merged (< 80 % one object), split (< 80 % of its "
            "object), none (no cluster between the fingers); attempts, GSR:\n\n" f"{table}\n\n")


def write_tables(out: str | os.PathLike, machine: str = "") -> dict[str, Path]:
    """Recompute results.csv, timing.csv and results.md from every log under OUT -> their paths."""
    out = Path(out)
    logs = read_logs(out)
    rows, times = result_rows(logs), timing_rows(logs)
    paths = {"results.csv": out / "results.csv", "timing.csv": out / "timing.csv", "results.md": out / "results.md"}
    _write_text(paths["results.csv"], _csv(rows))
    _write_text(paths["timing.csv"], _csv(times))
    note = f" on {machine}" if machine else ""
    text = (
        "# Decluttering benchmark\n\n"
        "## Grasping performance (Table I style)\n\n"
        "GSR = successes / attempts, TSR = successes / objects, GA = total attempts, N = scenes "
        "(attempts per scene capped at objects + 5).\n\n"
        f"{table_i_markdown(rows)}\n\n"
        "Objects (a hash over the member names: equal hashes, equal objects):\n\n"
        f"{objects_markdown(rows)}\n\n"
        "95 % intervals by resampling the scenes of each cell (a scene's attempts are not independent; "
        "the same code and seeds on a CPU with other vector instructions moves a cell by about as much, "
        "docs/benchmark.md):\n\n"
        f"{intervals_markdown(rows)}\n\n"
        "Numerics (vector ISA and versions the rounding depends on: scenes repeat attempt for attempt "
        "only under equal lines; `eval/numerics.py`):\n\n"
        f"{numerics_markdown(logs)}\n\n"
        f"## Planning time per grasp (Table III style{note})\n\n"
        "Mean ± std over the executed grasps' plan calls (wall seconds; JIT compilation excluded: a "
        "warm-up call before the first scene, and plan calls that compiled are left out).\n\n"
        f"{table_iii_markdown(times)}\n\n"
        "## Failures\n\n"
        "Failed grasps by the phase that failed them, and the scenes that ended with objects left, by "
        "why (the attempt cap, or the method's reason for finding no grasp, numbers as N).\n\n"
        f"{failures_markdown(logs)}\n\n"
        "Objects by how often they were not grasped (left at the end, or fallen off the table) and failed "
        "on, seeds pooled:\n\n"
        f"{object_outcomes_markdown(logs)}\n\n"
        f"{_segments_section(logs)}"
        "## What a run costs\n\n"
        "Mean wall seconds per attempt of the harness's own steps (rendering the observation, the grasp "
        "trial, re-settling the scene after it; trial and re-settle over simulated attempts) beside the "
        "plan call (compilation included), and per scene. Scenes resumed from older logs lack the "
        "re-settle time.\n\n"
        f"{harness_markdown(logs)}\n"
    )
    _write_text(paths["results.md"], text)
    return paths


# ---------------------------------------------------------------------------------------------------
# Pictures.


def finger_footprints(pose: np.ndarray, width: float, spec: GripperSpec) -> list[np.ndarray]:
    """The two fingers' outlines seen from above: convex hulls [V, 2] of their boxes' corners in x, y."""
    from scipy.spatial import ConvexHull

    t, half_y, length = spec.finger_thickness, 0.5 * spec.finger_width, spec.finger_length
    out = []
    for side in (-1.0, 1.0):
        xs = side * (0.5 * width + np.array([0.0, t]))
        corners = np.array([[x, y, z] for x in xs for y in (-half_y, half_y) for z in (0.0, length)])
        world = corners @ np.asarray(pose)[:3, :3].T + np.asarray(pose)[:3, 3]
        hull = ConvexHull(world[:, :2], qhull_options="QJ")
        out.append(world[hull.vertices, :2])
    return out


def draw_scene(path: str | os.PathLike, observation, log: Mapping, spec: GripperSpec | None = None,
               workspace: float = 0.5) -> None:
    """A PNG of a scene: the first observation's cloud seen from above, coloured by object, with every
    executed grasp drawn as a gripper outline (green: success, red: failure, numbered by attempt), and
    the camera's label image beside it. Written atomically."""
    from matplotlib import colormaps
    from matplotlib.figure import Figure  # no pyplot: the caller's backend is left alone

    from sgjax.draw import gripper_outline

    spec = spec or GripperSpec()
    points, labels = np.asarray(observation.points), np.asarray(observation.point_labels)
    half = 0.5 * workspace
    near = np.all(np.abs(points[:, :2]) <= half + 0.05, axis=1)
    table = near & (labels < 0)
    table_pts = points[table][:: max(1, int(table.sum()) // 4000)]
    obj = labels >= 0
    obj_idx = np.flatnonzero(obj)[:: max(1, int(obj.sum()) // 20000)]
    cmap = colormaps["tab20"]

    fig = Figure(figsize=(12, 5.6))
    axes = fig.subplots(1, 2)
    ax = axes[0]
    ax.scatter(table_pts[:, 0], table_pts[:, 1], s=0.3, c="0.85")
    ax.scatter(points[obj_idx, 0], points[obj_idx, 1], s=0.6, c=[cmap(int(k) % 20) for k in labels[obj_idx]])
    for attempt in log["attempts"]:
        colour = "tab:green" if attempt["success"] else "tab:red"
        pose = np.asarray(attempt["pose"])
        for footprint in finger_footprints(pose, attempt["width"], spec):
            ax.fill(footprint[:, 0], footprint[:, 1], facecolor="none", edgecolor=colour, linewidth=1.2)
        segments = gripper_outline(pose, attempt["width"], spec)
        for a, b in segments[2:4]:  # the bar between the fingers and the stem
            ax.plot([a[0], b[0]], [a[1], b[1]], color=colour, linewidth=1.2)
        ax.annotate(str(attempt["attempt"]), segments[1][1][:2], color=colour, fontsize=8)
    ax.plot([-half, half, half, -half, -half], [-half, -half, half, half, -half], color="0.5", linewidth=0.8)
    ax.set_xlim(-half - 0.02, half + 0.02)
    ax.set_ylim(-half - 0.02, half + 0.02)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    successes = sum(a["success"] for a in log["attempts"])
    ax.set_title(f"{log['method']} | {log['setting']} seed {log['seed']} scene {log['scene_index']}: "
                 f"{successes}/{log['objects']} objects, {len(log['attempts'])} attempts ({log['end']})", fontsize=9)
    image = np.asarray(observation.labels)
    shown = np.where(image >= 0, image % 20, np.nan)
    axes[1].imshow(np.where(image == -1, 0.85, np.nan), cmap="gray", vmin=0, vmax=1)
    axes[1].imshow(shown, cmap="tab20", vmin=0, vmax=19, interpolation="nearest")
    axes[1].set_title("camera view (object labels)", fontsize=9)
    axes[1].axis("off")
    fig.tight_layout()
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    atomic_write(path, lambda tmp: fig.savefig(tmp, dpi=110))
