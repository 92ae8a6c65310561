"""What the planner's choice left on the table: a benchmark scene replayed from its log, and at every
state the planner's finalists simulated, not only the grasp it executed.

The harness is deterministic (`eval.declutter`), so a SuperGrasp scene log can be replayed state by
state (`eval.replay`), and at each state the same planner (same seed, same Stage-1 memory, same failed
poses to avoid) plans again and chooses the logged grasp. Its robust choice (`PlannerConfig.robust`)
judges the best-evaluated candidates, the finalists; here each of them is executed from that state in
one batched trial. That answers, on identical states and without the noise of diverging episodes,
(a) how often some finalist would have succeeded (what a better choice could reach), and (b) how another
rule over the finalists' scores would have done (`rule_successes`). The episode goes on as logged.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence

import numpy as np

from envs import camera as camera_lib
from envs import scene as scene_lib
from envs import trial as trial_lib
from eval.declutter import NO_OBJECT, DeclutterConfig, closing_region_objects, plan_seed, rigid_pose
from eval.replay import logged_scene


@dataclasses.dataclass(frozen=True)
class Finalist:
    """One judged candidate at a state: its row in the plan's scores, the object the harness would lift
    (the most observed points in its closing region; None: none, not simulated), its eval_prob, robust
    score and the scores at its perturbed poses, whether it is a grasp on the fit itself, whether it is
    the one executed, and its simulated outcome from that state (`envs.trial.Outcome` name, lower case)."""

    index: int
    target: int | None
    eval_prob: float
    robust_score: float
    perturbed: tuple[float, ...]
    fit_grasp: bool
    chosen: bool
    outcome: str

    @property
    def success(self) -> bool:
        return self.outcome == "success"


@dataclasses.dataclass(frozen=True)
class ChoiceState:
    """A state of a replayed scene where the planner compared two or more finalists and executed one of
    them: the attempt index, the logged outcome of that grasp, the objects on the table and the finalists."""

    attempt: int
    logged: str
    objects: int
    finalists: tuple[Finalist, ...]


def _finalists(plan, obs, scene: scene_lib.Scene, spec) -> list[dict]:
    """The judged candidates of a plan (robust_score finite) with the object each would lift."""
    scores = plan.scores
    out = []
    for index in np.flatnonzero(np.isfinite(scores["robust_score"])):
        cands = plan.candidates[int(scores["object"][index])]
        row = int(scores["object_candidate"][index])
        # As the harness executes a pose: float64, the rotation re-orthonormalised.
        pose, width = rigid_pose(cands.poses[row], "supergrasp"), float(cands.widths[row])
        counts = {k: v for k, v in closing_region_objects(obs.points, obs.point_labels, pose, width, spec).items()
                  if scene.present[k]}
        out.append({"index": int(index), "pose": pose, "width": width,
                    "target": max(counts, key=lambda k: (counts[k], -k)) if counts else None,
                    "eval_prob": float(scores["eval_prob"][index]), "robust_score": float(scores["robust_score"][index]),
                    "perturbed": tuple(float(v) for v in scores["perturbed_score"][index]),
                    "fit_grasp": bool(cands.primitive_id[row] < 0), "chosen": plan.kind == "evaluated" and int(index) == int(plan.candidate_index)})
    return out


def replay_choices(log: dict, objects: Sequence, method, config: DeclutterConfig | None = None) -> tuple[list[ChoiceState], bool]:
    """Replay scene log `log` (a `supergrasp` run of `eval.declutter.run_scene` on `objects`) with
    `method` (the same planner, e.g. `eval.methods.make_method("supergrasp")`, with its robust choice),
    simulating every finalist at each state where the planner compared two or more.

    Returns (states, reproduced): reproduced is False when a plan chose another grasp than the log's
    or a replayed outcome differed (another planner, checkpoint or machine's numerics); the states up
    to there are returned. Raises ValueError for a method without `full_plan` or without the robust
    choice, or a log of other objects.
    """
    if not hasattr(method, "full_plan") or getattr(method, "config", None) is None or method.config.robust is None:
        raise ValueError("replay_choices needs a SuperGrasp planner method with PlannerConfig.robust (its finalists)")
    config = config or DeclutterConfig()
    spec = config.gripper
    scene = logged_scene(log, objects, config)
    method.begin_scene()
    s_seed = int(log["scene_seed"])
    viewpoint = np.asarray(config.camera.position, np.float64)
    failed: list[np.ndarray] = []
    states: list[ChoiceState] = []
    for record in log["attempts"]:
        k = int(record["attempt"])
        logged_pose = np.asarray(record["pose"], np.float64)
        obs = camera_lib.observe(scene, config.camera, seed=s_seed + k)
        avoid = np.asarray(failed, np.float64).reshape(-1, 4, 4)
        plan = method.full_plan(obs.points, obs.point_labels, viewpoint, plan_seed(s_seed, k), avoid)
        if plan.pose is None or not np.allclose(rigid_pose(plan.pose, "supergrasp"), logged_pose, atol=1e-9):
            return states, False
        if record["outcome"] == NO_OBJECT or record["target"] is None:
            failed.append(logged_pose)
            continue
        target = int(record["target"])
        rows = _finalists(plan, obs, scene, spec) if "robust_score" in plan.scores else []
        simulated = [r for r in rows if r["target"] is not None]
        chosen = [i for i, r in enumerate(simulated) if r["chosen"]]
        if not chosen:  # the executed grasp was not judged (a refined or lone candidate): simulate it alone
            simulated.append({"pose": logged_pose, "width": float(record["width"]), "target": target, "chosen": True})
        result = trial_lib.run_trials(scene, np.asarray([r["target"] for r in simulated]),
                                      np.stack([r["pose"] for r in simulated]), np.asarray([r["width"] for r in simulated]),
                                      backend=config.backend, config=config.trial, nthread=config.nthread)
        outcomes = [trial_lib.Outcome(int(o)).name.lower() for o in result.outcome]
        executed = next(i for i, r in enumerate(simulated) if r["chosen"])
        if outcomes[executed] != record["outcome"] or simulated[executed]["target"] != target:
            return states, False
        for row, outcome in zip(simulated, outcomes):
            row["outcome"] = outcome
        if len(rows) >= 2 and chosen:  # compared, and the executed grasp among them (not a refinement)
            finalists = tuple(Finalist(**{k2: v for k2, v in r.items() if k2 not in ("pose", "width", "outcome")},
                                       outcome=r.get("outcome", NO_OBJECT)) for r in rows)
            states.append(ChoiceState(k, record["outcome"], int(scene.present.sum()), finalists))
        if result.label[executed]:
            scene = scene_lib.remove_object(scene, target)
        else:
            failed.append(logged_pose)
            scene = scene_lib.after_trial(scene, result.final_qpos[executed])
    return states, True


# A rule ranks a state's finalists: finalist -> key, the highest executed (ties: the better evaluated,
# then the earlier row, as `sgjax.planner.robust_choice` breaks them).
RULES: dict[str, Callable[[Finalist], float]] = {
    "executed": lambda f: float(f.chosen),
    "highest evaluation (the paper)": lambda f: f.eval_prob,
    "robust mean (own + perturbed)": lambda f: f.robust_score,
    "lowest of own and perturbed": lambda f: min((f.eval_prob, *f.perturbed)),
    "mean of the perturbed": lambda f: float(np.mean(f.perturbed)),
}


def pick(state: ChoiceState, rule: Callable[[Finalist], float]) -> Finalist:
    """The finalist `rule` executes at `state`: the highest key; ties: the better evaluated, then the
    earlier row."""
    return max(state.finalists, key=lambda f: (rule(f), f.eval_prob, -f.index))


def rule_successes(states: Sequence[ChoiceState], rule: Callable[[Finalist], float]) -> int:
    """How many states' pick by `rule` (`pick`) succeeds."""
    return sum(pick(state, rule).success for state in states)


def oracle_successes(states: Sequence[ChoiceState]) -> int:
    """States where at least one finalist succeeds: what any rule over these finalists could reach."""
    return sum(any(f.success for f in state.finalists) for state in states)
