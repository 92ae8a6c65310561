"""A real frame's front end on simulated frames: its speed and how well it finds the objects (run by
hand; prints two markdown tables).

    python -m benchmarks.bench_perception [--setting seen-10] [--seed 12] [--scenes 6]
                                          [--sensors exact,kinect,realsense,stereo] [--repeats 10]

Frames: the benchmark's scenes of `setting` (scene seeds as `eval.declutter.scene_seed`, with the
table's surroundings) seen by the default 640x480 camera through each sensor model (`envs.sensors`).

Speed: median wall milliseconds (`median_ms`; on an idle machine) of back-projection, the table fit, the segmentation, and
`sgjax.perception.Frame.from_depth` as a whole, over the frames and `repeats` calls each.

Segmentation, against the exact render's instance masks, for every object with at least 50 pixels in
view: "clean" (one cluster holds >= 80 % of its pixels and is >= 80 % this object), "merged" (its
largest cluster is mostly other objects), "split" (its largest cluster is pure but holds < 80 % of it),
"lost" (most of its pixels in no object); "spurious": clusters that are mostly not an object.
"""

from __future__ import annotations

import argparse
import time

import numpy as np


def frames(setting: str, seed: int, scenes: int, sensor: str) -> list:
    """The sensed frames of the benchmark's first `scenes` scenes, as the harness makes them through a sensor."""
    from envs import sensors
    from eval.benchmark import resolve_objects
    from eval.declutter import DeclutterConfig, get_setting, make_benchmark_scene

    chosen = get_setting(setting)
    assets = resolve_objects(chosen)[0]
    config = DeclutterConfig(sensor=sensor, masks="clusters")  # through a sensor: the surroundings in the scene
    return [sensors.sense(make_benchmark_scene(assets, chosen.n_objects, seed, index, config), config.camera, sensor,
                          seed=index) for index in range(scenes)]


def grade(frame, truth: np.ndarray) -> np.ndarray:
    """[clean, merged, split, lost, spurious] of one frame against truth [N] (object index per point)."""
    counts = np.zeros(5, int)
    for obj in np.unique(truth[truth >= 0]):
        mine = truth == obj
        if mine.sum() < 50:
            continue
        found, sizes = np.unique(frame.labels[mine], return_counts=True)
        best = found[np.argmax(sizes)]
        if best <= 0:
            counts[3] += 1
        elif np.mean(truth[frame.labels == best] == obj) < 0.8:
            counts[1] += 1
        else:
            counts[0 if sizes.max() >= 0.8 * mine.sum() else 2] += 1
    counts[4] = sum(np.mean(truth[frame.labels == i] < 0) > 0.5 for i in frame.object_ids)
    return counts


def median_ms(fn, repeats: int) -> float:
    """Median wall milliseconds of fn() over `repeats` calls (run it on an idle machine: CPU time would
    count BLAS's threads twice over)."""
    runs = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        runs.append(time.perf_counter() - start)
    return 1000.0 * float(np.median(runs))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--setting", default="seen-10")
    parser.add_argument("--seed", type=int, default=12, help="scene seed (default 12: no benchmark row uses it)")
    parser.add_argument("--scenes", type=int, default=6)
    parser.add_argument("--sensors", default="exact,kinect,realsense,stereo")
    parser.add_argument("--repeats", type=int, default=10)
    args = parser.parse_args()

    from envs import sensors
    from envs.camera import CameraConfig
    from sgjax.perception import Frame, Intrinsics, back_project, fit_table, segment_objects
    from sgjax.perception.segment import segment_with_joined
    from sgjax.utils.threads import one_blas_thread

    camera = CameraConfig()  # the harness's

    speed, quality = [], []
    for sensor in args.sensors.split(","):
        parts, grades = [], np.zeros(5, int)
        for sensed in frames(args.setting, args.seed, args.scenes, sensor):
            obs = sensed.truth
            h, w = sensed.depth.shape
            K = Intrinsics.from_matrix(camera.pixel_intrinsic, w, h)
            points, pixels = back_project(sensed.depth, K)
            table = fit_table(points)
            with one_blas_thread():  # the parts as Frame.from_depth runs them
                parts.append([
                    median_ms(lambda: back_project(sensed.depth, K), args.repeats),
                    median_ms(lambda: fit_table(points), args.repeats),
                    median_ms(lambda: segment_objects(points, pixels, (h, w), table, np.zeros(3), 1.0 / K.fx),
                              args.repeats),
                    # What Frame.from_depth runs: the labels and the joined hypothesis from one pass.
                    median_ms(lambda: segment_with_joined(points, pixels, (h, w), table, np.zeros(3), 1.0 / K.fx),
                              args.repeats),
                ])
            parts[-1].append(median_ms(lambda: Frame.from_depth(sensed.depth, K), args.repeats))
            frame = sensors.front_end(sensed, camera, "clusters")
            grades += grade(frame, obs.labels[frame.pixels[:, 0], frame.pixels[:, 1]])
        speed.append((sensor, *np.median(parts, axis=0)))
        quality.append((sensor, *grades))

    print(f"Front end on {args.setting} frames (seed {args.seed}, {args.scenes} scenes, 640x480), median wall ms:\n")
    print("| sensor | back-projection | table | segmentation | segmentation + joined | Frame.from_depth |")
    print("|---|---:|---:|---:|---:|---:|")
    for sensor, *t in speed:
        print(f"| {sensor} | " + " | ".join(f"{v:.1f}" for v in t) + " |")
    print("\nObjects found, against the exact render's masks:\n")
    print("| sensor | objects | clean | merged | split | lost | spurious clusters |")
    print("|---|---:|---:|---:|---:|---:|---:|")
    for sensor, *g in quality:
        print(f"| {sensor} | {sum(g[:4])} | " + " | ".join(str(v) for v in g) + " |")


if __name__ == "__main__":
    main()
