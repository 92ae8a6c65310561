"""How good is the planner's choice among its finalists? Replay SuperGrasp benchmark scenes and simulate
every finalist at every state (`eval.counterfactual`), then score choice rules on the same states.

    python benchmarks/choice_counterfactual.py LOG_DIR [LOG_DIR ...] [--objects SET] [--out DIR]
                                               [--scenes 0-9]

LOG_DIR: a run's `logs/supergrasp/<setting>/seed<k>` folder (`sgjax declutter` or
`benchmarks/filter_ablation.py --variants default`), made by today's default planner and checkpoint on
this machine (a replay whose plan differs from the log stops that scene, and says so). Per scene the
states go to OUT/<log folder's parent names>/scene_XXX.json (resumable). Prints: states, how often the
executed grasp succeeded, how often any finalist would have (the oracle), and each rule of
`eval.counterfactual.RULES` on the same states, with the states where it and the executed choice differ.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

from eval import declutter
from eval.benchmark import resolve_objects, scene_indices
from eval.counterfactual import RULES, ChoiceState, Finalist, oracle_successes, pick, replay_choices, rule_successes
from eval.methods import make_method
from sgjax.utils.files import atomic_write_text


def load_states(path: Path) -> tuple[list[ChoiceState], bool]:
    saved = json.loads(path.read_text())
    states = [ChoiceState(s["attempt"], s["logged"], s["objects"],
                          tuple(Finalist(**{**f, "perturbed": tuple(f["perturbed"])}) for f in s["finalists"]))
              for s in saved["states"]]
    return states, saved["reproduced"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("logs", nargs="+")
    parser.add_argument("--objects", help="object set or mesh folder instead of the setting's")
    parser.add_argument("--out", default="choice_counterfactual_out")
    parser.add_argument("--scenes", help="scene indices, e.g. 0-9 (default: every log in the folder)")
    args = parser.parse_args()

    wanted = set(scene_indices(args.scenes)) if args.scenes else None
    method = make_method("supergrasp")
    assets = {}
    states: list[ChoiceState] = []
    stopped = 0
    for folder in map(Path, args.logs):
        out = Path(args.out) / folder.parent.name / folder.name
        out.mkdir(parents=True, exist_ok=True)
        for path in sorted(folder.glob("scene_*.json")):
            log = json.loads(path.read_text())
            if wanted is not None and int(log["scene_index"]) not in wanted:
                continue
            dest = out / path.name
            if dest.exists():
                scene_states, reproduced = load_states(dest)
            else:
                name = args.objects or log["object_set"]["name"]
                if name not in assets:
                    setting = declutter.Setting(log["setting"], int(log["n_objects"]), log["object_set"]["name"])
                    assets[name] = resolve_objects(setting, args.objects)[0]
                scene_states, reproduced = replay_choices(log, assets[name], method)
                atomic_write_text(dest, json.dumps({"scene_index": log["scene_index"], "reproduced": reproduced,
                                                    "states": [dataclasses.asdict(s) for s in scene_states]}))
                print(f"{folder.name}/{path.name}: {len(scene_states)} states" + ("" if reproduced else " (stopped: differs from the log)"),
                      flush=True)
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
