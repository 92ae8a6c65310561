"""The decision policy of SuperGrasp (paper Sec. IV-E, "During inference") as pure functions over the
scored candidates, and this project's additions to it. `sgjax.planner.Planner` applies them in order:

  1. `decide` / `select_grasp`: the paper's rule. The best-evaluated candidate when its eval_prob exceeds
     the evaluation threshold; else the best refinement when its score exceeds the refine threshold;
     else none.
  2. `robust_scores` / `robust_choice`: among the best passing candidates, the one whose score holds up
     when E-RNet judges it again at slightly perturbed poses (`PlannerConfig.robust`).
  3. `rescored_refinements`: when no evaluation passes, the refine head's best proposals are judged again
     at their refined pose and score the geometric mean of both heads (`PlannerConfig.refine_rescore`).
  4. `collision_free`: a refined pose that meets an obstacle or the table is left out and the rule decides
     again.

Candidates reach the policy in fixed-size, padded batches (`padded_batch`, `padded_refinements`,
`stage2_subset` chooses which when there are too many), so nothing recompiles per call.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from sgjax.geometry import gripper
from sgjax.geometry.gripper import GripperSpec
from sgjax.stage2 import ernet

KIND_NONE, KIND_EVALUATED, KIND_REFINED = 0, 1, 2
KIND_NAMES = {KIND_NONE: None, KIND_EVALUATED: "evaluated", KIND_REFINED: "refined"}
PERTURBATIONS = 5  # poses per candidate from `gripper.perturbed_poses`


def check_thresholds(config) -> None:
    """Raise ValueError unless config.eval_threshold and config.refine_threshold lie in [0, 1)."""
    for name in ("eval_threshold", "refine_threshold"):
        if not 0.0 <= getattr(config, name) < 1.0:
            raise ValueError(f"{name} must be in [0, 1), got {getattr(config, name)}")


def decide(eval_prob, refine_prob, valid, eval_threshold=0.7, refine_threshold=0.7, use_refinement=True):
    """The paper's decision over M scored candidates; pure jnp and jittable (thresholds may be traced).

    eval_prob [M], refine_prob [M, K], valid bool[M] (invalid candidates are never chosen; NaN scores
    count as invalid) -> (index int32, kind int32 (0 none, 1 evaluated, 2 refined), variant int32,
    score float32), each a scalar. Execute the best-evaluated candidate when its score exceeds
    `eval_threshold`; else, if `use_refinement` and the best refinement score over all candidates and
    variants exceeds `refine_threshold`, refine that candidate with that variant; else none. Index and
    variant are -1 where they do not apply; for "none" the score is the best valid eval prob (0 if none).
    Ties go to the lowest index.
    """
    eval_prob = jnp.asarray(eval_prob, jnp.float32)
    refine_prob = jnp.asarray(refine_prob, jnp.float32)
    valid = jnp.asarray(valid, bool)
    if eval_prob.ndim != 1 or refine_prob.ndim != 2 or refine_prob.shape[0] != eval_prob.shape[0]:
        raise ValueError(f"need eval_prob [M] and refine_prob [M, K], got {eval_prob.shape} and {refine_prob.shape}")
    if valid.shape != eval_prob.shape:
        raise ValueError(f"valid must have shape {eval_prob.shape}, got {valid.shape}")
    m, k = refine_prob.shape
    minus_one = jnp.int32(-1)
    if m == 0:
        return minus_one, jnp.int32(KIND_NONE), minus_one, jnp.float32(0.0)
    valid = valid & jnp.isfinite(eval_prob) & jnp.all(jnp.isfinite(refine_prob), -1)
    e = jnp.where(valid, eval_prob, -jnp.inf)
    best = jnp.argmax(e).astype(jnp.int32)
    best_eval = e[best]
    take_eval = best_eval > eval_threshold
    if k:
        r = jnp.where(valid[:, None], refine_prob, -jnp.inf).reshape(-1)
        flat = jnp.argmax(r).astype(jnp.int32)
        take_refine = ~take_eval & jnp.asarray(use_refinement, bool) & (r[flat] > refine_threshold)
        refine_index, refine_variant, refine_score = flat // k, flat % k, r[flat]
    else:
        take_refine, refine_index, refine_variant, refine_score = jnp.bool_(False), minus_one, minus_one, jnp.float32(0)
    kind = jnp.where(take_eval, KIND_EVALUATED, jnp.where(take_refine, KIND_REFINED, KIND_NONE)).astype(jnp.int32)
    index = jnp.where(take_eval, best, jnp.where(take_refine, refine_index, minus_one))
    variant = jnp.where(take_refine, refine_variant, minus_one)
    score = jnp.where(take_refine, refine_score, jnp.where(jnp.isfinite(best_eval), best_eval, 0.0))
    return index, kind, variant, score.astype(jnp.float32)


def rescored_refinement(refine_prob, judged):
    """A refinement's score under `PlannerConfig.refine_rescore`: the geometric mean of the refine head's
    score and the evaluation head's score of the refined pose (each in [0, 1], any equal shapes): high
    only when both heads agree."""
    return np.sqrt(np.asarray(refine_prob, np.float32) * np.asarray(judged, np.float32))


decide_jit = jax.jit(decide)  # `decide` on host scores, compiled once per Stage-2 batch size


def refine_proposals(refine_prob, valid, count: int) -> tuple[np.ndarray, np.ndarray]:
    """The refine head's best `count` proposals: refine_prob [M, K], valid [M] -> (index [n], variant [n]),
    n <= count, best first (ties: lowest candidate, then variant), only valid candidates and scores > 0."""
    head = np.where(np.asarray(valid, bool)[:, None], np.asarray(refine_prob, np.float32), -1.0)
    k = head.shape[1]
    flat = np.argsort(-head.reshape(-1), kind="stable")[:count]
    flat = flat[head.reshape(-1)[flat] > 0]
    return flat // k, flat % k


def padded_batch(poses, widths, slots: int) -> tuple[np.ndarray, np.ndarray]:
    """Candidates poses [n, 4, 4], widths [n] padded to a Stage-2 batch of `slots` rows (identity poses,
    NaN widths: invalid for E-RNet, and masked) -> (poses [slots, 4, 4] f32, widths [slots] f32)."""
    n = len(widths)
    padded_poses = np.tile(np.eye(4, dtype=np.float32), (slots, 1, 1))
    padded_widths = np.full(slots, np.nan, np.float32)
    padded_poses[:n], padded_widths[:n] = poses, widths
    return padded_poses, padded_widths


def padded_refinements(poses, widths, index, variant, slots: int, spec: GripperSpec) -> tuple[np.ndarray, np.ndarray]:
    """The refined poses of proposals (index [n], variant [n]) of candidates poses [M, 4, 4], widths [M],
    padded to `slots` rows so that the Stage-2 call that judges them has a shape it already compiled
    (row 0 fills the padding, its width NaN: invalid for E-RNet) -> (poses [slots, 4, 4] f32, widths [slots] f32)."""
    n = len(index)
    pad_index, pad_variant = np.zeros(slots, np.int64), np.zeros(slots, np.int64)
    pad_index[:n], pad_variant[:n] = index, variant
    refined = np.asarray(gripper.refined_pose(np.asarray(poses)[pad_index], pad_variant, spec), np.float32)
    return refined, np.where(np.arange(slots) < n, np.asarray(widths)[pad_index], np.nan).astype(np.float32)


def rescored_refinements(refine_prob, valid, count: int, judge) -> np.ndarray:
    """The refinements' scores under `PlannerConfig.refine_rescore`: the refine head's best `count`
    proposals each judged at its refined pose, `judge(index [n], variant [n])` -> the evaluation head's
    score there [n] (0 where it cannot judge), combined by `rescored_refinement` -> [M, K] (0 where not
    re-scored). Shared by the planner and the `gpd+s2` baseline: one Stage-2 policy for any candidates."""
    refine_prob = np.asarray(refine_prob, np.float32)
    index, variant = refine_proposals(refine_prob, valid, count)
    score = np.zeros_like(refine_prob)
    if len(index):
        score[index, variant] = rescored_refinement(refine_prob[index, variant], judge(index, variant))
    return score


def collision_free(choice: dict, eval_prob, refine_score, valid, collides, decide_again) -> tuple[dict, int]:
    """The policy's choice with every refined pose it would execute checked first: while the choice is a
    refinement, `collides(index)` -> (hits bool [K], poses [K, 4, 4], moved bool [K]) tests all the
    variants of candidate `index` (poses: as they would be executed; moved: those that differ from the
    plain refined pose, e.g. backed off the table); a chosen variant that hits is left out (its score
    set to 0, which no threshold in [0, 1) passes) and `decide_again(eval_prob, refine_score, valid)`
    decides once more. -> (choice with "pose" the refined pose to execute: the tested one where moved
    or where the choice has none, else the choice's own; refined poses left out)."""
    refine_score = np.array(refine_score, np.float32)
    rejected = 0
    while int(choice["kind"]) == KIND_REFINED:
        index, variant = int(choice["index"]), int(choice["variant"])
        hits, poses, moved = collides(index)
        if not hits[variant]:
            keep = choice.get("pose") is not None and not moved[variant]
            return {**choice, "pose": choice["pose"] if keep else poses[variant]}, rejected
        rejected += 1
        refine_score[index, hits] = 0.0
        choice = decide_again(eval_prob, refine_score, valid)
    return choice, rejected


def select_grasp(
    poses,
    widths,
    eval_prob,
    refine_prob,
    valid,
    eval_threshold=0.7,
    refine_threshold=0.7,
    use_refinement=True,
    spec: GripperSpec = ernet.DEFAULT_SPEC,
) -> dict[str, jax.Array]:
    """`decide`, then the pose to execute: poses [M, 4, 4], widths [M] and the scores of `decide` ->
    {"index", "kind", "variant", "score", "pose" [4, 4], "initial_pose" [4, 4], "width"}. "pose" is
    `gripper.refined_pose(poses[index], variant, spec)` when refined, poses[index] when evaluated
    (meaningless when kind is 0). Pure jnp, jittable."""
    index, kind, variant, score = decide(eval_prob, refine_prob, valid, eval_threshold, refine_threshold, use_refinement)
    poses = jnp.asarray(poses, jnp.float32)
    safe = jnp.maximum(index, 0)
    initial = poses[safe]
    refined = gripper.refined_pose(initial, jnp.maximum(variant, 0), spec)
    pose = jnp.where(kind == KIND_REFINED, refined, initial)
    return {
        "index": index,
        "kind": kind,
        "variant": variant,
        "score": score,
        "pose": pose,
        "initial_pose": initial,
        "width": jnp.asarray(widths, jnp.float32)[safe],
    }


def robust_scores(eval_prob, valid, threshold: float, top: int, judge) -> np.ndarray:
    """`PlannerConfig.robust`'s scores: the `top` best-evaluated valid candidates with eval_prob above
    `threshold` (eval_prob [M], valid [M]), each judged at its perturbed poses by `judge(index [t])` ->
    [t, P] (the evaluation head's scores there, 0 where it cannot judge) -> [M]: the mean of the
    candidate's own score and its P perturbed ones, NaN where not judged (all NaN when fewer than two
    candidates pass: then there is nothing to compare)."""
    e = np.asarray(eval_prob, np.float32)
    passing = np.flatnonzero(passing_mask(e, valid, threshold))
    index = passing[np.argsort(-e[passing], kind="stable")][:top]
    robust = np.full(len(e), np.nan, np.float32)
    if len(index) >= 2:
        judged = np.asarray(judge(index), np.float32)
        robust[index] = (e[index] + judged.sum(axis=1)) / (1 + judged.shape[1])
    return robust


def robust_choice(choice: dict, scores: dict) -> dict:
    """The evaluated choice made again on scores["robust_score"] [M] (`robust_scores`): the highest
    robust score (ties: the higher eval_prob, then the lowest index); the choice unchanged where no
    candidate was judged. -> choice, score its eval_prob."""
    robust = np.asarray(scores["robust_score"], np.float32)
    if not np.isfinite(robust).any():
        return choice
    e = np.asarray(scores["eval_prob"], np.float32)
    order = np.lexsort((np.arange(len(e)), -e, -np.where(np.isfinite(robust), robust, -np.inf)))
    index = int(order[0])
    return {**choice, "index": np.int32(index), "score": np.float32(e[index])}


def uncompared(plan, threshold: float) -> str | None:
    """How `plan`'s grasp was chosen without a comparison: "refined" (no evaluation passed), "lone" (an
    evaluated grasp, the only candidate whose eval_prob passes `threshold`), None (compared with other
    passing candidates, or no grasp)."""
    if plan.kind == "refined":
        return "refined"
    if plan.kind == "evaluated" and int(passing_mask(plan.scores["eval_prob"], plan.scores["valid"], threshold).sum()) < 2:
        return "lone"
    return None


def passing_mask(eval_prob, valid, threshold: float) -> np.ndarray:
    """The candidates whose evaluation passes: valid [M] with a finite eval_prob [M] above threshold -> bool [M]."""
    e = np.asarray(eval_prob)
    return np.asarray(valid, bool) & np.isfinite(e) & (e > threshold)


def stage2_subset(counts, budget: int) -> tuple[np.ndarray, np.ndarray]:
    """Which Stage-1 candidates Stage 2 scores: counts [B] (candidates per object, in match order) ->
    (object [M], row [M]), M = min(sum(counts), budget). All of them when they fit; otherwise
    round-robin over objects in match order (rank 0 of every object, then rank 1, ...), so every
    object keeps its best-matched candidates. Returned in (object, row) order."""
    obj = np.concatenate([np.full(n, i, np.int64) for i, n in enumerate(counts)] + [np.zeros(0, np.int64)])
    row = np.concatenate([np.arange(n, dtype=np.int64) for n in counts] + [np.zeros(0, np.int64)])
    if len(obj) > budget:
        keep = np.sort(np.lexsort((obj, row))[:budget])  # by row, then object
        obj, row = obj[keep], row[keep]
    return obj, row
