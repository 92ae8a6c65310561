"""Decluttering metrics exactly as the paper defines them (Sec. V-A), from per-scene logs.

Over N scenes:
  * GSR (grasp success rate) = successful grasps / grasp attempts;
  * TSR (task success rate)  = successful grasps / objects in the scenes;
  * GA  (grasp attempts)     = total attempts (each scene capped at its objects + 5 by the harness).
"Objects in a scene" are the objects on the table after the initial settle (objects that rolled out of
the workspace while the pile settled were never part of the task). Rates are ratios of totals over all
scenes (not means of per-scene rates); a rate with a zero denominator is None (no attempts / no objects).

A scene log is a mapping with "objects" (int) and "attempts" (a list of mappings with a bool
"success"), as `eval.declutter.run_scene` writes them. Pure functions, no I/O.
"""

from __future__ import annotations

import collections
import dataclasses
import re
from collections.abc import Callable, Hashable, Iterable, Mapping

import numpy as np

TIMING_KEYS = ("stage1_s", "stage2_s", "total_s")


@dataclasses.dataclass(frozen=True)
class Summary:
    """Totals and the paper's metrics over a set of scenes (rates in [0, 1], None if undefined)."""

    scenes: int
    objects: int
    successes: int
    attempts: int
    cleared: int  # scenes whose every object was grasped
    gsr: float | None
    tsr: float | None

    @property
    def ga(self) -> int:
        return self.attempts

    def as_dict(self) -> dict:
        """{"GSR", "TSR", "GA", "scenes", "objects", "successes", "attempts", "cleared"}."""
        return {
            "GSR": self.gsr,
            "TSR": self.tsr,
            "GA": self.ga,
            "scenes": self.scenes,
            "objects": self.objects,
            "successes": self.successes,
            "attempts": self.attempts,
            "cleared": self.cleared,
        }


def rate(numerator: int, denominator: int) -> float | None:
    """numerator / denominator, or None when the denominator is 0."""
    return None if denominator == 0 else numerator / denominator


def scene_counts(log: Mapping) -> tuple[int, int, int]:
    """(objects, successes, attempts) of one scene log; ValueError if the log is inconsistent."""
    objects = int(log["objects"])
    attempts = list(log["attempts"])
    successes = sum(bool(a["success"]) for a in attempts)
    if objects < 0 or successes > objects:
        raise ValueError(f"scene log with {objects} objects but {successes} successful grasps")
    return objects, successes, len(attempts)


def summarize(logs: Iterable[Mapping]) -> Summary:
    """GSR, TSR, GA and totals over scene logs (an empty iterable gives zeros and None rates)."""
    scenes = objects = successes = attempts = cleared = 0
    for log in logs:
        o, s, a = scene_counts(log)
        scenes += 1
        objects += o
        successes += s
        attempts += a
        cleared += int(s == o)
    return Summary(scenes, objects, successes, attempts, cleared, rate(successes, attempts), rate(successes, objects))


def scene_intervals(logs: Iterable[Mapping], resamples: int = 1000, seed: int = 0,
                    level: float = 0.95) -> dict[str, tuple[float, float] | None]:
    """{"GSR": (lo, hi), "TSR": (lo, hi)}: the central `level` intervals of GSR and TSR over `resamples`
    draws of the scenes with replacement (the scene is the unit: its attempts are not independent).
    A rate undefined in some draws (no attempts) is taken over the draws that define it; None when no
    draw does or there are no scenes. Deterministic for a seed."""
    counts = np.array([scene_counts(log) for log in logs], np.int64).reshape(-1, 3)  # objects, successes, attempts
    if len(counts) == 0 or resamples < 1:
        return {"GSR": None, "TSR": None}
    draws = np.random.default_rng(seed).integers(0, len(counts), (resamples, len(counts)))
    objects, successes, attempts = (counts[:, k][draws].sum(1) for k in range(3))
    tail = 50.0 * (1.0 - level)
    out = {}
    for name, denominator in (("GSR", attempts), ("TSR", objects)):
        defined = denominator > 0
        values = successes[defined] / denominator[defined]
        out[name] = (float(np.percentile(values, tail)), float(np.percentile(values, 100 - tail))) if len(values) else None
    return out


def timing_summary(logs: Iterable[Mapping]) -> dict[str, tuple[float, float, int]]:
    """Mean, standard deviation and count of each timing key over the executed grasps' plan calls,
    leaving out calls that compiled a program (`info["compiled"]`: e.g. a method's first use of a
    rarely needed part, such as the planner's fallback Stage 1): their time is compilation, not planning.

    -> {"stage1_s": (mean, std, n), "stage2_s": ..., "total_s": ...}; (nan, nan, 0) without attempts.
    """
    values: dict[str, list[float]] = {k: [] for k in TIMING_KEYS}
    for log in logs:
        for attempt in log["attempts"]:
            if (attempt.get("info") or {}).get("compiled"):
                continue
            timing = attempt.get("timing") or {}
            for key in TIMING_KEYS:
                if timing.get(key) is not None:
                    values[key].append(float(timing[key]))
    out = {}
    for key, v in values.items():
        arr = np.asarray(v, np.float64)
        out[key] = (float(arr.mean()), float(arr.std()), len(arr)) if len(arr) else (float("nan"), float("nan"), 0)
    return out


HARNESS_KEYS = ("observe_s", "trial_s", "settle_s")


def harness_summary(logs: Iterable[Mapping]) -> dict[str, tuple[float, int]]:
    """What the benchmark itself costs beside planning: mean seconds per attempt of observing
    (rendering the depth camera), the grasp trial and re-settling the scene after it, and of the plan
    call (compilation included: what a run costs), with how many attempts had each; and the mean wall
    seconds per scene ("scene_s", n = scenes). Keys a log lacks (older logs: "settle_s") are skipped.

    -> {"observe_s": (mean, n), "trial_s", "settle_s", "plan_s", "scene_s"}; (nan, 0) where none.
    """
    values: dict[str, list[float]] = {k: [] for k in (*HARNESS_KEYS, "plan_s", "scene_s")}
    for log in logs:
        if log.get("wall_s") is not None:
            values["scene_s"].append(float(log["wall_s"]))
        for attempt in log["attempts"]:
            for key in HARNESS_KEYS:
                if attempt.get(key) is not None and (key == "observe_s" or attempt.get("target") is not None):
                    values[key].append(float(attempt[key]))
            total = (attempt.get("timing") or {}).get("total_s")
            if total is not None:
                values["plan_s"].append(float(total))
    return {k: (float(np.mean(v)), len(v)) if v else (float("nan"), 0) for k, v in values.items()}


def why_unfinished(log: Mapping) -> str | None:
    """Why a scene ended with objects left: None when none are left, "attempt cap", or "no grasp: " and
    the first clause of the method's reason with its numbers as N (e.g. "no grasp: no candidates",
    "no grasp: best eval N <= N and best refine N <= N"), so that scenes ending alike count together."""
    if not log.get("remaining"):
        return None
    if log["end"] == "attempt_cap":
        return "attempt cap"
    reason = str(log.get("final_reason") or "no reason given").split(":")[0].strip()
    return "no grasp: " + re.sub(r"\d+(\.\d+)?", "N", reason)


def failure_breakdown(logs: Iterable[Mapping]) -> dict[str, collections.Counter]:
    """Failed attempts by outcome (the phase that failed them) and unfinished scenes by why they ended
    (`why_unfinished`), with the objects they left: {"failed": Counter, "unfinished": Counter, "left": Counter}."""
    out = {"failed": collections.Counter(), "unfinished": collections.Counter(), "left": collections.Counter()}
    for log in logs:
        out["failed"].update(a["outcome"] for a in log["attempts"] if not a["success"])
        why = why_unfinished(log)
        if why is not None:
            out["unfinished"][why] += 1
            out["left"][why] += int(log["remaining"])
    return out


SEGMENT_GRADES = ("clean", "merged", "split", "none")


def segment_breakdown(logs: Iterable[Mapping]) -> dict[str, tuple[int, int]] | None:
    """Attempts planned on segmented clusters, by how the cluster matched the objects (the attempt's
    "segment" grade, `eval.declutter.cluster_grade`; "none": no cluster's point between the fingers):
    {grade: (attempts, successes)} over SEGMENT_GRADES; None when no attempt was graded (true masks)."""
    out = {grade: [0, 0] for grade in SEGMENT_GRADES}
    graded = False
    for log in logs:
        for attempt in log["attempts"]:
            if "segment" not in attempt:
                continue
            graded = True
            grade = (attempt["segment"] or {"grade": "none"})["grade"]
            out[grade][0] += 1
            out[grade][1] += bool(attempt["success"])
    return {grade: (n, s) for grade, (n, s) in out.items()} if graded else None


@dataclasses.dataclass
class ObjectCounts:
    """One object's part in a set of scenes: in how many scenes' tasks it was (`scenes`, counted once per
    instance), how many times it was grasped, and its failed grasps by outcome."""

    scenes: int = 0
    grasped: int = 0
    failed: collections.Counter = dataclasses.field(default_factory=collections.Counter)

    @property
    def not_grasped(self) -> int:
        """Instances left at the end, or that fell off the table on the way (TSR counts neither)."""
        return self.scenes - self.grasped

    @property
    def failures(self) -> int:
        return sum(self.failed.values())

    @property
    def attempts(self) -> int:
        return self.grasped + self.failures


def object_breakdown(logs: Iterable[Mapping]) -> dict[str, ObjectCounts]:
    """Per object name (the log's "object_names", the task's objects after the initial settle, and each
    attempt's "target_name"): `ObjectCounts`. Attempts that touched no object count for none. Which
    objects a method leaves, and which it fails on: the cell's GSR and TSR by object."""
    out: dict[str, ObjectCounts] = collections.defaultdict(ObjectCounts)
    for log in logs:
        for name in log.get("object_names") or []:
            out[name].scenes += 1
        for attempt in log["attempts"]:
            name = attempt.get("target_name")
            if name is None:
                continue
            if attempt["success"]:
                out[name].grasped += 1
            else:
                out[name].failed[attempt["outcome"]] += 1
    return dict(out)


# ---------------------------------------------------------------------------------------------
# Where a cell's failures come from, by the executed grasp (`benchmarks/log_breakdown.py`).

SCORE_EDGES = (0.7, 0.8, 0.85, 0.9, 0.93, 0.95, 0.97, 1.0)
TILT_EDGES = (0.0, 10.0, 20.0, 30.0, 45.0, 90.0, 180.0)


def how_chosen(attempt: Mapping) -> str:
    """How SuperGrasp chose an attempt's grasp, from its log's "info" (`eval.supergrasp`): "first plan" or
    "second plan" (the first found no grasp), "evaluated" or "refined", "on the fit" (`sgjax.stage1.fit_grasps`)
    or "transferred", "robust choice" (judged among finalists) or "alone". Other methods: their "kind", or "-"."""
    info = attempt.get("info") or {}
    kind = info.get("kind")
    if kind not in ("evaluated", "refined"):
        return str(kind) if kind else "-"
    plan = "second plan" if info.get("fallback") else "first plan"
    source = "on the fit" if info.get("fit_grasp") else "transferred"
    judged = "robust choice" if "robust_rank" in info else "alone"
    return f"{plan}, {kind}, {source}, {judged}"


def bin_label(value: float | None, edges: Iterable[float]) -> str:
    """The interval of sorted `edges` that holds value, as "lo-hi" ((lo, hi], the first one [lo, hi]);
    "none" for a missing value, "< lo" / "> hi" outside the edges."""
    edges = list(edges)
    if value is None or not np.isfinite(value):
        return "none"
    if value < edges[0]:
        return f"< {edges[0]:g}"
    for lo, hi in zip(edges[:-1], edges[1:]):
        if value <= hi:
            return f"{lo:g}-{hi:g}"
    return f"> {edges[-1]:g}"


def approach_tilt(pose) -> float:
    """Degrees between a grasp's approach axis (the pose's z column, [4, 4] gripper -> world) and straight
    down (world -z): 0 for a top-down grasp, 90 for a horizontal one."""
    z = np.asarray(pose, np.float64)[:3, 2]
    return float(np.degrees(np.arccos(np.clip(-z[2] / np.linalg.norm(z), -1.0, 1.0))))


def outcomes_by(logs: Iterable[Mapping], key: Callable[[Mapping], Hashable]) -> dict[Hashable, collections.Counter]:
    """Every attempt's "outcome" counted by key(attempt) -> {key: Counter(outcome)}."""
    out: dict[Hashable, collections.Counter] = collections.defaultdict(collections.Counter)
    for log in logs:
        for attempt in log["attempts"]:
            out[key(attempt)][attempt["outcome"]] += 1
    return dict(out)


def stopped_at(logs: Iterable[Mapping], bar: float) -> Summary:
    """The metrics had every scene stopped at its first attempt whose logged score is <= bar (that
    attempt and all after it never made): a stop rule read off the logs, exact because the attempts before
    it are unchanged. An attempt without a score (no grasp) stops the scene too."""
    stopped = []
    for log in logs:
        attempts = []
        for attempt in log["attempts"]:
            score = attempt.get("score")
            if score is None or not score > bar:
                break
            attempts.append(attempt)
        stopped.append({**log, "attempts": attempts})
    return summarize(stopped)
