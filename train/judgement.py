"""How well a grasp scorer judges: ranking, calibration and decisions on labelled samples (plain NumPy).

Computed by `sgjax train` on the held-out scenes and the held-out objects after every epoch, and by
`sgjax score-data` for any checkpoint on any labelled directory:

  auc                 ROC AUC of the evaluation score against the label (rank statistic, ties halved)
  auc_per_source      the same within each candidate source (`train.sources.SOURCES`)
  per_source          every metric here within each candidate source: {name: {samples, auc, ece, ...}}
  ece                 expected calibration error over `bins` equal-width score bins
  reliability         per bin: [mean score, success rate, samples] (the reliability plot's points)
  collision_score     mean score of grasps whose trial collided (pre-grasp or approach)
  refine_auc          ROC AUC of each refinement head against its variant's label
  top1_success        per scene, the Stage-1 grasp with the highest score: the share that succeed
  random_success      per scene, a Stage-1 grasp picked at random: the expected share that succeed
  top1_scenes, top1_per_scene   the scenes behind both, and the mean Stage-1 samples competing per scene
  top1_outcomes       (with `outcome`) per scene, the top Stage-1 grasp's trial outcome: {name: scenes}
                      (`envs.outcome.Outcome` names, lower case), so a miss reads as a drop or a collision
  mean_score / positive_rate: the scorer's mean against the actual success rate
  auc_interval, top1_interval   (with `resamples` > 0) 95 % intervals of auc and top1_success by
                      resampling scenes with replacement (samples of a scene are not independent)
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence

import numpy as np

from envs.outcome import Outcome

COLLISIONS = (Outcome.COLLISION_PREGRASP, Outcome.COLLISION_APPROACH)


def roc_auc(score: np.ndarray, label: np.ndarray) -> float | None:
    """ROC AUC of scores [N] for binary labels [N] (Mann-Whitney U with average ranks); None when a
    class is missing."""
    score = np.asarray(score, np.float64)
    label = np.asarray(label).astype(bool)
    n_pos, n_neg = int(label.sum()), int((~label).sum())
    if n_pos == 0 or n_neg == 0:
        return None
    order = np.argsort(score, kind="mergesort")
    ranks = np.empty(len(score), np.float64)
    sorted_scores = score[order]
    # Average ranks over ties (1-based).
    _, start, counts = np.unique(sorted_scores, return_index=True, return_counts=True)
    average = start + (counts + 1) / 2.0
    ranks[order] = np.repeat(average, counts)
    return float((ranks[label].sum() - n_pos * (n_pos + 1) / 2.0) / (n_pos * n_neg))


def reliability(score: np.ndarray, label: np.ndarray, bins: int = 10) -> tuple[float | None, list[list[float]]]:
    """(expected calibration error, [[mean score, success rate, count] per non-empty bin]) over `bins`
    equal-width bins of [0, 1]."""
    score = np.asarray(score, np.float64)
    label = np.asarray(label, np.float64)
    if len(score) == 0:
        return None, []
    which = np.minimum((score * bins).astype(int), bins - 1)
    table, error = [], 0.0
    for b in range(bins):
        rows = which == b
        if rows.any():
            mean, rate, n = float(score[rows].mean()), float(label[rows].mean()), int(rows.sum())
            table.append([mean, rate, n])
            error += n * abs(mean - rate)
    return error / len(score), table


def top_success(score: np.ndarray, label: np.ndarray, group: np.ndarray) -> float | None:
    """Per group (scene), whether the highest-scored sample succeeds: the share that do."""
    group = np.asarray(group)
    if len(group) == 0:
        return None
    return float(np.mean(np.asarray(label)[top_rows(score, group)].astype(bool)))


def top_rows(score: np.ndarray, group: np.ndarray) -> np.ndarray:
    """Per group, the row of its highest score (the first such row on ties), groups in sorted order:
    score, group [N] -> rows [G]."""
    group = np.asarray(group)
    # One sort instead of a pass per group (the scene-resampled intervals call this 1000 times): by
    # group, then score descending, then position, so each group's first row is its argmax.
    order = np.lexsort((np.arange(len(group)), -np.asarray(score, np.float64), group))
    first = np.ones(len(order), bool)
    first[1:] = group[order][1:] != group[order][:-1]
    return order[first]


def top_outcomes(score: np.ndarray, outcome: np.ndarray, group: np.ndarray) -> dict[str, int]:
    """Per group (scene), the trial outcome of the highest-scored sample: {outcome name: groups} in
    `Outcome` order (names, not codes, so the dict survives a JSON round trip unchanged). Whether the
    scorer's misses are drops or collisions decides what would fix them. outcome [N]: Outcome codes."""
    if len(np.asarray(group)) == 0:
        return {}
    codes, counts = np.unique(np.asarray(outcome)[top_rows(score, group)], return_counts=True)
    return {Outcome(int(c)).name.lower(): int(n) for c, n in zip(codes, counts)}


def random_success(label: np.ndarray, group: np.ndarray) -> float | None:
    """Per group (scene), the chance that a uniformly random sample succeeds: its success rate,
    averaged over the groups (the baseline `top_success` should beat)."""
    group = np.asarray(group)
    if len(group) == 0:
        return None
    label = np.asarray(label).astype(bool)
    return float(np.mean([label[group == g].mean() for g in np.unique(group)]))


def scene_interval(
    metric: Callable[[np.ndarray, np.ndarray, np.ndarray], float | None],
    score: np.ndarray,
    label: np.ndarray,
    scene: np.ndarray,
    resamples: int = 1000,
    seed: int = 0,
    level: float = 0.95,
) -> list[float] | None:
    """[lo, hi]: the central `level` interval of metric(score, label, group) over `resamples` draws of
    the scenes with replacement (a scene drawn twice enters as two groups); None without scenes or when
    the metric is undefined in most draws. score, label, scene [N]."""
    scene = np.asarray(scene)
    ids, group = np.unique(scene, return_inverse=True)
    if len(ids) == 0 or resamples < 1:
        return None
    # Rows sorted by scene: scene g is rows[start[g] : start[g] + count[g]].
    rows = np.argsort(group, kind="stable")
    count = np.bincount(group, minlength=len(ids))
    start = np.concatenate([[0], np.cumsum(count)[:-1]])
    rng = np.random.default_rng(seed)
    values = []
    for _ in range(resamples):
        drawn = rng.integers(0, len(ids), len(ids))
        sizes = count[drawn]
        relabelled = np.repeat(np.arange(len(drawn)), sizes)
        offset = np.arange(sizes.sum()) - np.repeat(np.cumsum(sizes) - sizes, sizes)
        index = rows[np.repeat(start[drawn], sizes) + offset]
        value = metric(score[index], label[index], relabelled)
        if value is not None:
            values.append(value)
    if len(values) < resamples / 2:
        return None
    tail = 50.0 * (1.0 - level)
    return [float(np.percentile(values, tail)), float(np.percentile(values, 100.0 - tail))]


def judge(
    score: np.ndarray,
    label: np.ndarray,
    *,
    source: np.ndarray | None = None,
    outcome: np.ndarray | None = None,
    scene: np.ndarray | None = None,
    refine_score: np.ndarray | None = None,
    refine_label: np.ndarray | None = None,
    source_names: Sequence[str] = (),
    top_source: int | None = 0,
    bins: int = 10,
    resamples: int = 0,
) -> dict:
    """Every metric of the module docstring for scores [N] against labels [N]; the optional columns
    ([N] each, refine_* [N, K]) enable their metrics. top_source: the source whose grasps compete per
    scene in top1_success and random_success (0: Stage 1 as planned; None: all). per_source judges each
    source's samples alone (its own grasps competing per scene). resamples > 0 (needs `scene`): also the
    scene-resampled intervals auc_interval and top1_interval (`scene_interval`)."""
    score = np.asarray(score, np.float64)
    label = np.asarray(label).astype(bool)
    ece, table = reliability(score, label, bins)
    out: dict = {
        "samples": int(len(score)),
        "auc": roc_auc(score, label),
        "ece": ece,
        "reliability": table,
        "mean_score": float(score.mean()) if len(score) else None,
        "positive_rate": float(label.mean()) if len(score) else None,
    }
    if source is not None:
        source = np.asarray(source)
        names = list(source_names) or [str(s) for s in range(int(source.max(initial=-1)) + 1)]

        def part(rows, column):
            return None if column is None else np.asarray(column)[rows]

        per_source = {
            names[s]: judge(score[rows], label[rows], outcome=part(rows, outcome), scene=part(rows, scene),
                            refine_score=part(rows, refine_score), refine_label=part(rows, refine_label),
                            top_source=None, bins=bins, resamples=resamples)
            for s in np.unique(source) if s < len(names) for rows in [source == s]
        }
        # The compact views the training curves and tables read, taken from the per-source judgement.
        out["auc_per_source"] = {name: m["auc"] for name, m in per_source.items()}
        out["samples_per_source"] = {name: m["samples"] for name, m in per_source.items()}
        out["per_source"] = per_source
    if outcome is not None:
        collided = np.isin(np.asarray(outcome), COLLISIONS)
        out["collision_score"] = float(score[collided].mean()) if collided.any() else None
    if scene is not None:
        rows = np.ones(len(score), bool) if top_source is None or source is None else source == top_source
        top_score, top_label, top_scene = score[rows], label[rows], np.asarray(scene)[rows]
        out["top1_success"] = top_success(top_score, top_label, top_scene)
        out["random_success"] = random_success(top_label, top_scene)
        # How many grasps compete per scene: the top pick's success rises with it (docs/stage2.md).
        competing = np.unique(top_scene, return_counts=True)[1]
        out["top1_scenes"] = int(len(competing))
        out["top1_per_scene"] = float(competing.mean()) if len(competing) else None
        if outcome is not None:
            out["top1_outcomes"] = top_outcomes(top_score, np.asarray(outcome)[rows], top_scene)
        if resamples > 0:
            out["auc_interval"] = scene_interval(lambda s, y, g: roc_auc(s, y), score, label, scene, resamples)
            out["top1_interval"] = scene_interval(top_success, top_score, top_label, top_scene, resamples)
    if refine_score is not None and refine_label is not None:
        refine_score, refine_label = np.asarray(refine_score), np.asarray(refine_label)
        out["refine_auc"] = [roc_auc(refine_score[:, k], refine_label[:, k]) for k in range(refine_score.shape[1])]
    return out


def summary_line(metrics: Mapping) -> str:
    """One line of the headline numbers."""

    def f(v):
        return "n/a" if v is None else f"{v:.3f}"

    parts = [f"AUC {f(metrics.get('auc'))}", f"ECE {f(metrics.get('ece'))}"]
    if "auc_per_source" in metrics:
        parts.append("per source " + " ".join(f"{k} {f(v)}" for k, v in metrics["auc_per_source"].items()))
    if "collision_score" in metrics:
        parts.append(f"collisions scored {f(metrics['collision_score'])}")
    if "refine_auc" in metrics:
        parts.append("refine AUC " + "/".join(f(v) for v in metrics["refine_auc"]))
    if "top1_success" in metrics:
        parts.append(f"top Stage-1 grasp succeeds {f(metrics['top1_success'])} (random {f(metrics.get('random_success'))})")
    return ", ".join(parts)
