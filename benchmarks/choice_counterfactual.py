"""How good is the planner's choice among its finalists? Replay SuperGrasp benchmark scenes and simulate
every finalist at every state (`eval.counterfactual`), then score choice rules on the same states.

    python -m benchmarks.choice_counterfactual LOG_DIR [LOG_DIR ...] [--objects SET] [--out DIR]
                                               [--scenes 0-9]

LOG_DIR: a run's `logs/supergrasp/<setting>/seed<k>` folder (`sgjax declutter --method supergrasp`), made
by today's default planner and checkpoint on this machine (a replay whose plan differs from the log stops that scene, and says so). Per scene the
states go to OUT/<log folder's parent names>/scene_XXX.json (resumable). Prints: states, how often the
executed grasp succeeded, how often any finalist would have (the oracle), and each rule of
`eval.counterfactual.RULES` on the same states, with the states where it and the executed choice differ.
"""

from __future__ import annotations

import argparse

from eval.benchmark import scene_indices
from eval.counterfactual import (RULES, ChoiceState, Finalist, oracle_successes, pick, replay_choices, replay_logs,
                                 rule_successes)
from eval.methods import make_method


def decode(saved: dict) -> ChoiceState:
    return ChoiceState(saved["attempt"], saved["logged"], saved["objects"],
                       tuple(Finalist(**{**f, "perturbed": tuple(f["perturbed"])}) for f in saved["finalists"]))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("logs", nargs="+")
    parser.add_argument("--objects", help="object set or mesh folder instead of the setting's")
    parser.add_argument("--out", default="choice_counterfactual_out")
    parser.add_argument("--scenes", help="scene indices, e.g. 0-9 (default: every log in the folder)")
    args = parser.parse_args()

    method = make_method("supergrasp")
    states: list[ChoiceState] = []
    stopped = 0
    replay = lambda log, objects: replay_choices(log, objects, method)
    for name, scene_states, reproduced in replay_logs(args.logs, args.out, replay, args.objects,
                                                      set(scene_indices(args.scenes)) if args.scenes else None, decode):
        print(f"{name}: {len(scene_states)} states" + ("" if reproduced else " (stopped: differs from the log)"), flush=True)
        states += scene_states
        stopped += not reproduced
    n = len(states)
    if not n:
        raise SystemExit("no state with two or more finalists in these logs")
    finalists = [f for s in states for f in s.finalists]
    print(f"\n{n} states with >= 2 finalists ({stopped} scene(s) stopped early); finalists per state "
          f"{len(finalists) / n:.1f}, of which succeed {100 * sum(f.success for f in finalists) / len(finalists):.1f} %\n")
    print("| choice | successes | % | differs from executed |\n|---|---:|---:|---:|")
    oracle = oracle_successes(states)
    print(f"| any finalist (oracle) | {oracle} | {100 * oracle / n:.2f} | |")
    executed = [pick(s, RULES["executed"]) for s in states]
    for name, rule in RULES.items():
        k = rule_successes(states, rule)
        differs = sum(pick(s, rule) is not e for s, e in zip(states, executed))
        print(f"| {name} | {k} | {100 * k / n:.2f} | {differs} |")


if __name__ == "__main__":
    main()
