"""Which part of a gripper keeps Stage 1 from finding candidates in clutter? (by hand)

    python -m benchmarks.gripper_candidates [--setting real-similar] [--scenes 5] [--seed 0]
        [--change "palm_size=0.185,0.001,0.001" --change "finger_thickness=0.01 finger_width=0.02" ...]

Stage 1 only (the planner with `scorers.Stage1Order`), first plan of each scene of the setting (exact depth
and true masks: the geometry, not the sensor), on the database of the setting's gripper, with the filters of
that gripper as it is and with each change of its boxes: objects with a candidate, and filter (iv)'s
collisions. A change that leaves the count alone is not what removes the candidates.
"""

from __future__ import annotations

import argparse
import dataclasses

from benchmarks.common import first_views, stage1_only_planner
from eval.declutter import DeclutterConfig, apply_setting, get_setting
from eval.report import markdown_table
from sgjax.geometry.gripper import GripperSpec
from sgjax.stage1.database import DBConfig, load_database


def changed(spec: GripperSpec, change: str) -> GripperSpec:
    """`spec` with "field=value field=a,b,c ..." applied (tuples for comma lists)."""
    values = {}
    for item in change.split():
        field, _, text = item.partition("=")
        parts = [float(v) for v in text.split(",")]
        values[field] = tuple(parts) if len(parts) > 1 else parts[0]
    return dataclasses.replace(spec, **values)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--setting", default="real-similar")
    parser.add_argument("--scenes", type=int, default=5)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--change", action="append", default=[])
    args = parser.parse_args(argv)
    setting = get_setting(args.setting)
    config = dataclasses.replace(apply_setting(setting, DeclutterConfig()), sensor="exact", masks="truth")
    spec = config.gripper
    db = load_database(DBConfig.for_gripper(spec, False), progress=False)  # the gripper's own templates
    views = first_views(setting, config, args.scenes, args.seed)
    rows = []
    for name in ["as it is", *args.change]:
        planner = stage1_only_planner(spec if name == "as it is" else changed(spec, name), db)
        total = with_candidates = collisions = 0
        for points, labels in views:
            plan = planner.plan(points, labels, config.camera.position, seed=0)
            total += len(plan.candidates)
            with_candidates += sum(len(c) > 0 for c in plan.candidates)
            collisions += sum(c.counts.get("collision_scene", 0) for c in plan.candidates)
        rows.append([name, total, with_candidates, collisions])
    print(markdown_table(["filters' gripper", "objects", "with candidates", "(iv) collisions"], rows))


if __name__ == "__main__":
    main()
