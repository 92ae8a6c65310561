"""A change of the planner measured on identical states: replay SuperGrasp benchmark scenes with the
default planner and let a variant plan every logged state too (`eval.counterfactual.replay_alternative`);
where it chooses another grasp, that grasp is executed from the same state. Paired per state, so a change
that touches few decisions shows without the noise of whole episodes (a 10-scene cell moves by ±5 points
by its scenes alone); what it does to later states only a benchmark run shows.

    python benchmarks/planner_counterfactual.py LOG_DIR [LOG_DIR ...] --variant NAME [--objects SET]
                                                [--out DIR] [--scenes 0-9] [--judge RUN_DIR]

LOG_DIR: as for benchmarks/choice_counterfactual.py (today's default planner on this machine). NAME: a
variant of benchmarks/filter_ablation.py. Per scene the states go to OUT/<variant>/<setting>/<seed
folder>/scene_XXX.json (resumable). Prints, by how the logged grasp was chosen (`plan_kind`): states,
logged successes, the variant's successes on the same states, the states where it chose another grasp,
and where it chose none.
"""

from __future__ import annotations

import argparse
from collections import Counter
from pathlib import Path

from filter_ablation import variant_config  # benchmarks/ is on sys.path when run as a script
from eval.benchmark import scene_indices
from eval.counterfactual import AlternativeState, replay_alternative, replay_logs
from eval.methods import make_method


def table(states: list[AlternativeState]) -> str:
    """Markdown: per logged kind (and all), states, successes logged / variant, differing, none."""
    kinds = sorted(Counter(s.logged_kind for s in states).items(), key=lambda kv: -kv[1])
    lines = ["| logged grasp chosen | states | logged succeed | variant succeeds | variant differs | variant plans none |",
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
    parser.add_argument("--variant", required=True, help="a variant of benchmarks/filter_ablation.py")
    parser.add_argument("--objects", help="object set or mesh folder instead of the setting's")
    parser.add_argument("--out", default="planner_counterfactual_out")
    parser.add_argument("--scenes", help="scene indices, e.g. 0-9 (default: every log in the folder)")
    parser.add_argument("--judge", metavar="RUN_DIR", help="the variant's finalists judged by this network (`Planner(judge=)`)")
    args = parser.parse_args()

    method = make_method("supergrasp")
    alternative = make_method("supergrasp", config=variant_config(args.variant), judge=args.judge)
    label = args.variant if not args.judge else f"{args.variant}+judge-{Path(args.judge).name}"
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
