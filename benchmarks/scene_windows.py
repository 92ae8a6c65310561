"""How many objects filter (iv)'s later windows reach and rescue (by hand)

    python -m benchmarks.scene_windows [--scenes 5] [--seed 0] [--settings seen-10 seen-20 real-similar]

Stage 1 only (the planner with `scorers.Stage1Order`, no refinement), on the first plan of each scene of
the given decluttering settings, each with its own gripper: per setting, the objects, those with a
candidate, those whose candidates (iv) tested beyond its first window of `FilterConfig.scene_slots`, and
those whose only clear candidates came from a later window (the first window all collided).
"""

from __future__ import annotations

import argparse

from benchmarks.common import first_views, stage1_only_planner
from eval.declutter import DeclutterConfig, apply_setting, get_setting
from eval.report import markdown_table


def count(setting: str, scenes: int, seed: int) -> list:
    """[setting, objects, with candidates, tested beyond the first window, rescued by a later window]."""
    spec_setting = get_setting(setting)
    config = apply_setting(spec_setting, DeclutterConfig())
    planner = stage1_only_planner(config.gripper)
    slots = planner.config.stage1.filter.scene_slots
    total = with_candidates = beyond = rescued = 0
    for points, labels in first_views(spec_setting, config, scenes, seed):
        plan = planner.plan(points, labels, config.camera.position, seed=0)
        for c in plan.candidates:
            tested_collided = c.counts.get("collision_scene", 0)
            total += 1
            with_candidates += len(c) > 0
            beyond += tested_collided + c.counts.get("kept", 0) > slots
            rescued += len(c) > 0 and tested_collided >= slots
    return [setting, total, with_candidates, beyond, rescued]


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", type=int, default=5)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--settings", nargs="+", default=["seen-10", "seen-20", "real-similar"])
    args = parser.parse_args(argv)
    rows = [count(s, args.scenes, args.seed) for s in args.settings]
    print(markdown_table(["setting", "objects", "with candidates", "tested beyond window 1", "rescued by a later window"],
                         rows))


if __name__ == "__main__":
    main()
