"""A change of the planner measured on identical states: replay SuperGrasp benchmark scenes with the
default planner and let another configuration (a planner preset) plan every logged state too
(`eval.counterfactual.replay_alternative`); where it chooses another grasp, that grasp is executed from the
same state. Paired per state, so a change that touches few decisions shows without the noise of whole
episodes (a 10-scene cell moves by ±5 points by its scenes alone); what it does to later states only a
benchmark run shows.

    python -m benchmarks.planner_counterfactual LOG_DIR [LOG_DIR ...] --preset NAME [--objects SET]
                                                [--out DIR] [--scenes 0-9]

LOG_DIR: as for benchmarks.choice_counterfactual (today's default planner on this machine). NAME: a planner
preset (`sgjax.presets.names()`; a change to measure is registered there), with the benchmark's workspace
crop of the Stage-2 cloud. Per scene the states go to OUT/<preset>/<setting>/<seed folder>/scene_XXX.json
(resumable). Prints, by how the logged grasp was chosen (`plan_kind`): states, logged successes, the
preset's successes on the same states, the states where it chose another grasp, and where it chose none.
"""

from __future__ import annotations

import argparse
from collections import Counter
from pathlib import Path

from envs.scene import stage2_scene_cloud
from eval.benchmark import scene_indices
from eval.counterfactual import AlternativeState, replay_alternative, replay_logs
from eval.methods import make_method
from sgjax import presets


def table(states: list[AlternativeState]) -> str:
    """Markdown: per logged kind (and all), states, successes logged / by the preset, differing, none."""
    kinds = sorted(Counter(s.logged_kind for s in states).items(), key=lambda kv: -kv[1])
    lines = ["| logged grasp chosen | states | logged succeed | preset succeeds | preset differs | preset plans none |",
             "|---|---:|---:|---:|---:|---:|"]
    for kind, group in [*((k, [s for s in states if s.logged_kind == k]) for k, _ in kinds), ("all", states)]:
        n = len(group)
        logged = sum(s.logged == "success" for s in group)
        other = sum(s.outcome == "success" for s in group)
        lines.append(f"| {kind} | {n} | {logged} ({100 * logged / n:.1f} %) | {other} ({100 * other / n:.1f} %) | "
                     f"{sum(not s.same for s in group)} | {sum(s.outcome == 'none' for s in group)} |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("logs", nargs="+")
    parser.add_argument("--preset", required=True, choices=presets.names(), help="the planner preset to compare")
    parser.add_argument("--objects", help="object set or mesh folder instead of the setting's")
    parser.add_argument("--out", default="planner_counterfactual_out")
    parser.add_argument("--scenes", help="scene indices, e.g. 0-9 (default: every log in the folder)")
    args = parser.parse_args()

    method = make_method("supergrasp")
    alternative = make_method("supergrasp", config=presets.get(args.preset, scene_cloud=stage2_scene_cloud()))
    label = args.preset
    replay = lambda log, objects: replay_alternative(log, objects, method, alternative)
    states: list[AlternativeState] = []
    stopped = 0
    for name, scene_states, reproduced in replay_logs(args.logs, Path(args.out) / label, replay, args.objects,
                                                      set(scene_indices(args.scenes)) if args.scenes else None,
                                                      lambda d: AlternativeState(**d)):
        print(f"{name}: {len(scene_states)} states" + ("" if reproduced else " (stopped: differs from the log)"), flush=True)
        states += scene_states
        stopped += not reproduced
    if not states:
        raise SystemExit("no replayed state in these logs")
    print(f"\n{label} against the logged default on {len(states)} states ({stopped} scene(s) stopped early):\n")
    print(table(states))


if __name__ == "__main__":
    main()
