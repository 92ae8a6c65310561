"""What the planner's choice left on the table: a benchmark scene replayed from its log, and at every
state the planner's finalists simulated, not only the grasp it executed.

The harness is deterministic (`eval.declutter`), so a SuperGrasp scene log can be replayed state by
state (`eval.replay.LoggedStates`), and at each state the same planner (same seed, same Stage-1 memory, same failed
poses to avoid) plans again and chooses the logged grasp. Its robust choice (`PlannerConfig.robust`)
judges the best-evaluated candidates, the finalists; here each of them is executed from that state in
one batched trial. That answers, on identical states and without the noise of diverging episodes,
(a) how often some finalist would have succeeded (what a better choice could reach), and (b) how another
rule over the finalists' scores would have done (`rule_successes`). The episode goes on as logged.

The same walk over the logged states (`LoggedStates`) measures a change of the planner itself
(`replay_alternative`): another planner plans every state too, and its grasp, where it differs, is
executed from that state.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path

import numpy as np

from eval import declutter
from eval.benchmark import resolve_objects
from eval.declutter import NO_OBJECT, DeclutterConfig, rigid_pose
from eval.replay import LoggedState, LoggedStates
from eval.report import is_scene_log
from sgjax.policy import uncompared
from sgjax.utils.files import atomic_write_text


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


def _finalists(state: LoggedState) -> list[dict]:
    """The judged candidates of the state's plan (robust_score finite) with the object each would lift."""
    plan = state.plan
    scores = plan.scores
    out = []
    for index in np.flatnonzero(np.isfinite(scores["robust_score"])):
        cands = plan.candidates[int(scores["object"][index])]
        row = int(scores["object_candidate"][index])
        # As the harness executes a pose: float64, the rotation re-orthonormalised.
        pose, width = rigid_pose(cands.poses[row], "supergrasp"), float(cands.widths[row])
        out.append({"index": int(index), "pose": pose, "width": width, "target": state.lifted(pose, width),
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
    replay = LoggedStates(log, objects, method, config)
    states: list[ChoiceState] = []
    for state in replay:
        if state.target is None:
            continue
        rows = _finalists(state) if "robust_score" in state.plan.scores else []
        simulated = [r for r in rows if r["target"] is not None]
        outcomes = state.simulate(simulated)
        if not state.reproduced:
            continue  # the replay stops there (`LoggedStates`)
        for row, outcome in zip(simulated, outcomes):
            row["outcome"] = outcome
        if len(rows) >= 2 and any(r["chosen"] for r in simulated):  # compared, the executed grasp among them
            finalists = tuple(Finalist(**{k2: v for k2, v in r.items() if k2 not in ("pose", "width", "outcome")},
                                       outcome=r.get("outcome", NO_OBJECT)) for r in rows)
            states.append(ChoiceState(state.attempt, state.record["outcome"], int(state.scene.present.sum()), finalists))
    return states, replay.reproduced


def plan_kind(plan, threshold: float) -> str:
    """How a plan's grasp was chosen: "compared" (an evaluated grasp among two or more passing candidates),
    "lone" or "refined" (`sgjax.policy.uncompared`), "none" (no grasp); ", second plan" added when it came
    from the second plan (`Plan.fallback`)."""
    if not plan.ok:
        return "none"
    return (uncompared(plan, threshold) or "compared") + (", second plan" if plan.fallback else "")


@dataclasses.dataclass(frozen=True)
class AlternativeState:
    """A logged state (one with a trial) where another planner planned too: the attempt index, the logged
    grasp's outcome and how it was chosen (`plan_kind`), the alternative's, and whether the alternative
    chose the logged grasp itself (then its outcome is the logged one)."""

    attempt: int
    logged: str
    logged_kind: str
    outcome: str
    kind: str
    same: bool


def replay_alternative(log: dict, objects: Sequence, method, alternative,
                       config: DeclutterConfig | None = None) -> tuple[list[AlternativeState], bool]:
    """Replay scene log `log` with `method` (the planner that made it) and let `alternative` (another
    SuperGrasp planner method, e.g. with another `PlannerConfig`) plan every logged state too, with the
    same seed and failed poses and its own Stage-1 memory; its grasp is executed from that state when it
    differs from the logged one (outcome "none" when it plans none, "no_object" when nothing lies between
    its fingers) and the episode goes on as logged. So a change of the planner is measured on identical
    states, one decision at a time, without the divergence of whole episodes (what it does to later
    states, e.g. fewer objects left, only a benchmark run shows).

    Returns (states, reproduced) as `replay_choices`. Raises ValueError for methods without `full_plan`."""
    if not hasattr(alternative, "full_plan") or getattr(alternative, "config", None) is None:
        raise ValueError("replay_alternative needs a SuperGrasp planner method as the alternative (its full_plan)")
    replay = LoggedStates(log, objects, method, config)
    threshold = alternative.config.eval_threshold
    alternative.begin_scene()
    states: list[AlternativeState] = []
    for state in replay:
        other = alternative.full_plan(state.obs.points, state.obs.point_labels, state.viewpoint, state.seed, state.avoid)
        if state.target is None:
            continue
        logged_pose = np.asarray(state.record["pose"], np.float64)
        pose = None if other.pose is None else rigid_pose(other.pose, "supergrasp")
        same = pose is not None and np.allclose(pose, logged_pose, atol=1e-9)
        target = None if pose is None or same else state.lifted(pose, float(other.width))
        rows = [] if target is None else [{"pose": pose, "width": float(other.width), "target": target}]
        outcomes = state.simulate(rows)
        if not state.reproduced:
            continue  # the replay stops there
        outcome = state.record["outcome"] if same else "none" if pose is None else outcomes[0] if rows else NO_OBJECT
        states.append(AlternativeState(state.attempt, state.record["outcome"], plan_kind(state.plan, threshold), outcome,
                                       plan_kind(other, threshold), bool(same)))
    return states, replay.reproduced


def scene_logs(folders: Sequence, objects: str | None = None, scenes=None) -> Iterator[tuple[Path, Path, dict, Sequence]]:
    """Every scene log of `folders` (a run's `logs/supergrasp/<setting>/seed<k>` folders), in order:
    (folder, log path, log, its objects). objects: an object set or mesh folder instead of the log's
    (resolved once per name); scenes: the scene indices to give (None: all). Raises FileNotFoundError
    for a folder without scene logs."""
    assets: dict = {}
    found = [(folder, sorted(p for p in folder.glob("scene_*.json") if is_scene_log(p))) for folder in map(Path, folders)]
    for folder, paths in found:
        if not paths:
            raise FileNotFoundError(f"{folder}: no scene_*.json logs (give a run's logs/supergrasp/<setting>/seed<k> folder)")
    for folder, paths in found:
        for path in paths:
            log = json.loads(path.read_text())
            if scenes is not None and int(log["scene_index"]) not in scenes:
                continue
            name = objects or log["object_set"]["name"]
            if name not in assets:
                setting = declutter.Setting(log["setting"], int(log["n_objects"]), log["object_set"]["name"])
                assets[name] = resolve_objects(setting, objects)[0]
            yield folder, path, log, assets[name]


def replay_logs(folders: Sequence, out, replay: Callable, objects: str | None = None, scenes=None,
                decode: Callable = lambda d: d) -> Iterator[tuple[str, list, bool]]:
    """Replay every scene log of `folders` (`scene_logs`) with `replay(log, objects) -> (states,
    reproduced)` (states: dataclasses), resumably: each scene's result goes to
    out/<setting>/<seed folder>/scene_XXX.json (written atomically) and is read back from there on a
    later run, its states through `decode(dict)`. objects, scenes: as `scene_logs`. Yields (name,
    states, reproduced) per scene."""
    for folder, path, log, assets in scene_logs(folders, objects, scenes):
        dest = Path(out) / folder.parent.name / folder.name / path.name
        if dest.exists():
            saved = json.loads(dest.read_text())
            yield f"{folder.name}/{path.name}", [decode(d) for d in saved["states"]], saved["reproduced"]
            continue
        states, reproduced = replay(log, assets)
        dest.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_text(dest, json.dumps({"scene_index": log["scene_index"], "reproduced": reproduced,
                                            "states": [dataclasses.asdict(st) for st in states]}))
        yield f"{folder.name}/{path.name}", states, reproduced


# A rule ranks a state's finalists: finalist -> key, the highest executed (ties: the better evaluated,
# then the earlier row, as `sgjax.policy.robust_choice` breaks them).
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
