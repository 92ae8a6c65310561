"""Would the neighbours' fitted superquadrics have stopped a method's failed grasps, and at what cost?
From its benchmark logs (run by hand; prints a markdown table).

    python benchmarks/neighbour_fits.py RESULTS_DIR --method supergrasp --setting seen-20
                                        [--seed 0] [--scenes 0-29] [--every 3] [--margins 0 0.002 0.005]
                                        [--closing]

Each scene log is replayed as `eval.replay` does (the logged grasps in order from the same scene; a
trial is simulated only for failed attempts, to leave the objects where they fell). Before each
collision, and before every `--every`-th other attempt, the benchmark's observation is rendered again,
every object with >= 50 points is fitted as Stage 1 fits it (EMS with the table footprint and the
viewpoint), and the logged hand (fingers and palm swept back 5 cm; with `--closing` also, in a second
set of columns, the closing region between the fingers) is tested against the other objects' fits grown
by each margin (`sgjax.stage1.neighbours.fit_hits` with `fit_pairs`' overlap rule: the planner's test).
Rows: the logged outcome (collisions split by the phase that decided them: "approach" or "close");
columns: how many of those attempts the test would have removed. For collisions it also says
whether the neighbour touched was seen at all. What `PlannerConfig.neighbour_fits` would remove among
failures against successes (docs/benchmark.md, "Neighbours' hidden sides").
"""

from __future__ import annotations

import collections
import os
import sys

import jax.numpy as jnp
import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from envs import camera as camera_lib  # noqa: E402
from envs import scene as scene_lib  # noqa: E402
from envs import trial as trial_lib  # noqa: E402
from eval import declutter  # noqa: E402
from sgjax.geometry import pointcloud  # noqa: E402
from sgjax.geometry.superquadric import Superquadric  # noqa: E402
from sgjax.stage1.ems import EMSConfig, fit_superquadrics  # noqa: E402
from sgjax.stage1.neighbours import NeighbourFitConfig, fit_hits, fit_pairs  # noqa: E402
from sgjax.stage1.pipeline import with_footprint  # noqa: E402

MIN_POINTS = 50


def fits_of(obs, view: np.ndarray) -> tuple[list[int], Superquadric, np.ndarray, list[np.ndarray]]:
    """Every object's superquadric fitted as Stage 1 fits it -> (labels, fits [O], valid [O], clouds)."""
    points, labels = np.asarray(obs.points), np.asarray(obs.point_labels)
    plane = pointcloud.table_plane(points, labels)
    ids = [int(i) for i in np.unique(labels[labels >= 0]) if (labels == i).sum() >= MIN_POINTS]
    clouds, mask = pointcloud.pad_clouds([points[labels == i] for i in ids], 1024, 0, n_points=1024)
    planes = np.broadcast_to(np.asarray(plane if plane is not None else (0, 0, 1, 1e3), np.float32), (len(ids), 4))
    ems_points, ems_mask = with_footprint(jnp.asarray(clouds), jnp.asarray(mask), jnp.asarray(planes))
    fit = fit_superquadrics(ems_points, ems_mask, EMSConfig(), np.broadcast_to(view.astype(np.float32), (len(ids), 3)))
    sq = Superquadric(*(np.asarray(x) for x in (fit.scale, fit.epsilon, fit.rotation, fit.translation)))
    return ids, sq, np.asarray(fit.valid), [points[labels == i] for i in ids]


def variants(margins, closing: bool) -> dict[str, NeighbourFitConfig]:
    """The tests compared, by column name."""
    out = {f"{1000 * m:g} mm": NeighbourFitConfig(margin=m) for m in margins}
    if closing:
        out.update({f"{1000 * m:g} mm + closing": NeighbourFitConfig(margin=m, closing=True) for m in margins})
    return out


def analyse(log: dict, objects, tests: dict, every: int, config: declutter.DeclutterConfig) -> list[dict]:
    spec, view = config.gripper, np.asarray(config.camera.position, np.float64)
    scene = declutter.make_benchmark_scene(objects, int(log["n_objects"]), int(log["seed"]), int(log["scene_index"]), config)
    rows = []
    for k, record in enumerate(log["attempts"]):
        if record["target"] is None:
            continue
        target, pose, width = int(record["target"]), np.asarray(record["pose"], np.float64), float(record["width"])
        collision = record["outcome"].startswith("collision")
        if collision or k % every == 0:
            obs = camera_lib.observe(scene, config.camera, seed=int(log["scene_seed"]) + k)
            ids, fits, valid, clouds = fits_of(obs, view)
            owner = ids.index(target) if target in ids else -1
            touched = [int(t) for t in record.get("contacts", {}).get("objects", {}) if int(t) != target] if collision else []
            hits = {name: bool(fit_hits(pose[None].astype(np.float32), np.array([width], np.float32),
                                        np.array([owner], np.int32), fits, valid, spec, test,
                                        config.trial.pregrasp_distance, (8,), fit_pairs(fits, valid, clouds, test))[0])
                    for name, test in tests.items()}
            outcome = record["outcome"]
            if collision and record.get("contacts", {}).get("phase") == "close":
                outcome += " (close)"
            rows.append({"scene": int(log["scene_index"]), "attempt": k, "outcome": outcome, "hits": hits,
                         "touched_seen": all(t in ids for t in touched) if touched else None})
        if record["success"]:
            scene = scene_lib.remove_object(scene, target)
        else:
            result = trial_lib.run_trials(scene, target, pose[None], np.array([width]), backend=config.backend,
                                          config=config.trial, nthread=config.nthread)
            replayed = trial_lib.Outcome(int(result.outcome[0])).name.lower()
            if replayed != record["outcome"]:
                print(f"scene {log['scene_index']} attempt {k}: replayed {replayed}, logged {record['outcome']}: "
                      "the rest of the scene is not replayed")
                break
            scene = scene_lib.after_trial(scene, result.final_qpos[0])
    return rows


def main() -> None:
    from benchmarks.replay_failures import log_arguments, read_logs

    parser = log_arguments(__doc__)
    parser.add_argument("--every", type=int, default=3, help="test every n-th attempt that did not collide")
    parser.add_argument("--margins", type=float, nargs="+", default=[0.0, 0.002, 0.005])
    parser.add_argument("--closing", action="store_true", help="also test the hand with its closing region")
    args = parser.parse_args()
    tests = variants(args.margins, args.closing)
    logs = read_logs(args)
    config, rows = declutter.DeclutterConfig(), []
    for log, objects in logs:
        rows += analyse(log, objects, tests, args.every, config)
        print(f"scene {log['scene_index']}: {len(rows)} attempts tested so far", flush=True)
    print(f"\n{args.method} {args.setting} seed {args.seed}: attempts whose logged hand meets another object's "
          f"fit (every collision, every {args.every}th other attempt)\n")
    print("| logged outcome | tested | " + " | ".join(f"meets a fit, {name}" for name in tests) + " |")
    print("|---|---:|" + "---:|" * len(tests))
    by = collections.defaultdict(list)
    for r in rows:
        by[r["outcome"]].append(r)
    for outcome, group in sorted(by.items()):
        print(f"| {outcome} | {len(group)} | " + " | ".join(str(sum(r["hits"][name] for r in group)) for name in tests) + " |")
    unseen = sum(r["touched_seen"] is False for r in rows)
    print(f"\ncollisions with a neighbour that had fewer than {MIN_POINTS} observed points (no fit): {unseen}")


if __name__ == "__main__":
    main()
