"""Why a method's grasps fail, from its benchmark logs: replay each scene's grasps in simulation, with our
gripper and with a Panda hand (issue 22: which contacts, which phase, and would a Panda fail too).

    python -m benchmarks.replay_failures RESULTS_DIR --method contact-graspnet --setting seen-10
                                         [--seed 0] [--scenes 0-29] [--other panda|none] [--out DIR]

RESULTS_DIR is a `sgjax declutter --out` folder. Each scene log is replayed (`eval.replay.replay_scene`:
the logged grasps in order, from the same scene, no planner); per attempt the replay records the
replayed outcome, what the gripper touched in the phase that decided a failure, and the outcome of the
same grasp with the other hand (`sgjax.geometry.gripper.PANDA_HAND`: fingertips where ours were, the same
opening). Results go to OUT/<method>/<setting>/seed<seed>/scene_XXX.json (resumable: scenes already
there are read back). Prints: failed attempts by logged outcome and by what they touched; our outcome
against the other hand's for the same grasps.
"""

from __future__ import annotations

import argparse
import collections
import dataclasses
import json
from pathlib import Path

import numpy as np

from eval import declutter
from eval.benchmark import scene_indices
from eval.counterfactual import scene_logs
from eval.replay import ReplayedAttempt, collision_cause, replay_scene
from sgjax.geometry.gripper import PANDA_HAND
from sgjax.utils.files import atomic_write_text

OTHERS = {"panda": PANDA_HAND, "none": None}


def replay_logs(logs: list[tuple[dict, list]], other_name: str, out: Path) -> list[ReplayedAttempt]:
    """Replay each (log, its objects) (or read its replay back from `out`); all attempts, scene after scene."""
    attempts = []
    for log, objects in logs:
        path = out / f"scene_{int(log['scene_index']):03d}.json"
        if path.exists():
            saved = json.loads(path.read_text())
            attempts += [ReplayedAttempt(**a) for a in saved["attempts"]]
            continue
        replayed = replay_scene(log, objects, other=OTHERS[other_name])
        text = json.dumps({"scene_index": log["scene_index"], "other": other_name,
                           "attempts": [dataclasses.asdict(a) for a in replayed]})
        atomic_write_text(path, text)
        attempts += replayed
        print(f"scene {log['scene_index']}: {len(replayed)} attempts, "
              f"{sum(a.reproduced for a in replayed)} reproduced", flush=True)
    return attempts


def print_tables(attempts: list[ReplayedAttempt], other_name: str) -> None:
    simulated = [a for a in attempts if a.outcome != declutter.NO_OBJECT]
    reproduced = [a for a in simulated if a.reproduced]
    print(f"\n{len(attempts)} attempts, {len(simulated)} simulated, {len(reproduced)} reproduced the logged outcome")
    failed = [a for a in reproduced if a.outcome != "success"]
    print("\n| logged outcome | n | what decided it (phase: touched) | what it touched was in the observation |")
    print("|---|---:|---|---|")
    for outcome in sorted({a.outcome for a in failed}):
        rows = [a for a in failed if a.outcome == outcome]
        causes = collections.Counter(
            collision_cause(a) if outcome.startswith("collision") else
            f"{a.contacts['phase']}: target by {', '.join(sorted(set(a.contacts['objects'].get(str(a.target), 'nothing').split('+'))))}"
            for a in rows)
        seen = ""
        if outcome.startswith("collision"):
            hit_neighbour = [a for a in rows if "neighbour" in collision_cause(a)]
            hit_table = [a for a in rows if "table" in collision_cause(a)]
            seen = (f"neighbour points in the swept hand: {sum(a.seen_neighbour > 0 for a in hit_neighbour)} of "
                    f"{len(hit_neighbour)}; table points: {sum(a.seen_table > 0 for a in hit_table)} of {len(hit_table)}")
        print(f"| {outcome} | {len(rows)} | {'; '.join(f'{c} {n}' for c, n in causes.most_common())} | {seen} |")
    print("\nHow deep the grasps held the target (its centre of mass behind the fingertips after closing, cm; "
          "median and quartiles):\n")
    print("| outcome | n | depth |")
    print("|---|---:|---|")
    for outcome in sorted({a.outcome for a in reproduced if not a.outcome.startswith("collision")}):
        depth = 100 * np.array([a.com_depth for a in reproduced if a.outcome == outcome])
        q = np.percentile(depth, [25, 50, 75])
        print(f"| {outcome} | {len(depth)} | {q[1]:.1f} ({q[0]:.1f}-{q[2]:.1f}) |")
    if other_name == "none":
        return
    others = sorted({a.other_outcome for a in reproduced})
    print(f"\nThe same grasps with the {other_name} hand (rows: ours, columns: {other_name}):\n")
    print("| ours \\ " + other_name + " | " + " | ".join(others) + " | n |")
    print("|---|" + "---:|" * (len(others) + 1))
    for outcome in sorted({a.outcome for a in reproduced}):
        row = collections.Counter(a.other_outcome for a in reproduced if a.outcome == outcome)
        print(f"| {outcome} | " + " | ".join(str(row.get(o, 0)) for o in others) + f" | {sum(row.values())} |")
    causes = collections.Counter(collision_cause(a, other=True) for a in reproduced if a.other_outcome.startswith("collision"))
    print(f"\n{other_name} collisions by what they touched: " + "; ".join(f"{c} {n}" for c, n in causes.most_common()))
    ok = sum(a.outcome == "success" for a in reproduced), sum(a.other_outcome == "success" for a in reproduced)
    print(f"success: ours {ok[0]} / {len(reproduced)}, {other_name} {ok[1]} / {len(reproduced)}")


def log_arguments(description: str) -> argparse.ArgumentParser:
    """The arguments that name a benchmark run's scene logs (RESULTS_DIR, --method, --setting, --seed,
    --scenes): shared by the scripts that read them back (`read_logs`)."""
    parser = argparse.ArgumentParser(description=description, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("results", type=Path, help="a `sgjax declutter --out` folder")
    parser.add_argument("--method", required=True)
    parser.add_argument("--setting", required=True)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--scenes", default="0-29", help="indices: 0-29, 3, 0,4,7")
    return parser


def read_logs(args: argparse.Namespace) -> list[tuple[dict, list]]:
    """The scene logs `log_arguments` names (those that exist), each with the objects its run used
    (`eval.counterfactual.scene_logs`); SystemExit when there are none."""
    folder = args.results / "logs" / args.method / args.setting / f"seed{args.seed}"
    try:
        logs = [(log, objects) for _, _, log, objects in scene_logs([folder], scenes=set(scene_indices(args.scenes)))]
    except FileNotFoundError:
        logs = []
    if not logs:
        raise SystemExit(f"no scene logs under {folder} for scenes {args.scenes}")
    return logs


def main() -> None:
    parser = log_arguments(__doc__)
    parser.add_argument("--other", choices=sorted(OTHERS), default="panda")
    parser.add_argument("--out", type=Path, default=Path("replay_out"))
    args = parser.parse_args()
    logs = read_logs(args)
    out = args.out / args.method / args.setting / f"seed{args.seed}"
    out.mkdir(parents=True, exist_ok=True)
    attempts = replay_logs(logs, args.other, out)
    print_tables(attempts, args.other)


if __name__ == "__main__":
    main()
