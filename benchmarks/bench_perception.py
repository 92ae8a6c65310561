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

With --against COMMIT, that commit's tree (`benchmarks.common.reference_tree`) runs `Frame.from_depth` on
the same frames in a worker process, in the camera frame and with the extrinsics: the table gains its
median ms and the ratio, and the script says on how many of those segmentations both trees give
identical labels and joined hypotheses (a change meant to be faster only must keep them all). Its
timings meet the load of their own moment: compare on an idle machine, or rerun and compare ratios.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time

import numpy as np

# The reference tree's worker (`--against`): it imports only `sgjax` (an older tree may lack `benchmarks`).
# argv: frames.npz (count, depth_<i>, extrinsic_<i>, fx, fy, cx, cy, width, height), repeats, out.npz.
_WORKER = """
import sys, time
import numpy as np
from sgjax.perception import Frame, Intrinsics
data = np.load(sys.argv[1])
K = Intrinsics.from_matrix(np.array([[data["fx"], 0, data["cx"]], [0, data["fy"], data["cy"]], [0, 0, 1.0]]),
                           int(data["width"]), int(data["height"]))
out = {}
for i in range(int(data["count"])):
    depth = data[f"depth_{i}"]
    for world, extrinsic in ((0, None), (1, data[f"extrinsic_{i}"])):
        frame = Frame.from_depth(depth, K, extrinsics=extrinsic)
        out[f"labels_{i}_{world}"], out[f"joined_{i}_{world}"] = frame.labels, frame.joined_labels
    runs = []
    for _ in range(int(sys.argv[2])):
        start = time.perf_counter()
        Frame.from_depth(depth, K)
        runs.append(time.perf_counter() - start)
    out[f"ms_{i}"] = 1000.0 * np.median(runs)
np.savez(sys.argv[3], **out)
"""


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


def reference_run(commit: str, depths: list, extrinsics: list, K, repeats: int) -> dict:
    """`_WORKER` in `commit`'s tree on depth images [H, W] (with their camera-to-world extrinsics [4, 4])
    -> its arrays: labels_<i>_<0|1>, joined_<i>_<0|1> (camera frame, world frame) and ms_<i>."""
    from benchmarks.common import reference_tree

    tree = reference_tree(commit)
    with tempfile.TemporaryDirectory() as tmp:
        arrays = {f"depth_{i}": d for i, d in enumerate(depths)} | {f"extrinsic_{i}": e for i, e in enumerate(extrinsics)}
        np.savez(os.path.join(tmp, "frames.npz"), count=len(depths), fx=K.fx, fy=K.fy, cx=K.cx, cy=K.cy, width=K.width,
                 height=K.height, **arrays)
        env = dict(os.environ, PYTHONPATH=tree + os.pathsep + os.environ.get("PYTHONPATH", ""))
        subprocess.run([sys.executable, "-c", _WORKER, os.path.join(tmp, "frames.npz"), str(repeats),
                        os.path.join(tmp, "out.npz")], check=True, cwd=tree, env=env)
        with np.load(os.path.join(tmp, "out.npz")) as out:
            return dict(out)


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
    parser.add_argument("--against", metavar="COMMIT", help="also run this commit's front end: its ms, the ratio, "
                        "and whether both give identical labels")
    args = parser.parse_args()

    from envs import sensors
    from envs.camera import CameraConfig
    from sgjax.perception import Frame, Intrinsics, back_project, fit_table, segment_objects
    from sgjax.perception.segment import segment_with_joined
    from sgjax.utils.threads import one_blas_thread

    camera = CameraConfig()  # the harness's

    speed, quality = [], []
    same, compared = 0, 0
    for sensor in args.sensors.split(","):
        parts, grades = [], np.zeros(5, int)
        sensed_frames = frames(args.setting, args.seed, args.scenes, sensor)
        if args.against:
            h, w = sensed_frames[0].depth.shape
            reference = reference_run(args.against, [f.depth for f in sensed_frames],
                                      [f.truth.extrinsic for f in sensed_frames],
                                      Intrinsics.from_matrix(camera.pixel_intrinsic, w, h), args.repeats)
        for index, sensed in enumerate(sensed_frames):
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
            if args.against:
                parts[-1] += [reference[f"ms_{index}"], parts[-1][-1] / reference[f"ms_{index}"]]
                for world, extrinsic in ((0, None), (1, obs.extrinsic)):
                    mine = Frame.from_depth(sensed.depth, K, extrinsics=extrinsic)
                    same += bool(np.array_equal(mine.labels, reference[f"labels_{index}_{world}"])
                                 and np.array_equal(mine.joined_labels, reference[f"joined_{index}_{world}"]))
                    compared += 1
            frame = sensors.front_end(sensed, camera, "clusters")
            grades += grade(frame, obs.labels[frame.pixels[:, 0], frame.pixels[:, 1]])
        speed.append((sensor, *np.median(parts, axis=0)))
        quality.append((sensor, *grades))

    print(f"Front end on {args.setting} frames (seed {args.seed}, {args.scenes} scenes, 640x480), median wall ms:\n")
    against = f" | {args.against} | ratio" if args.against else ""
    print("| sensor | back-projection | table | segmentation | segmentation + joined | Frame.from_depth" + against + " |")
    print("|---|---:|---:|---:|---:|---:" + ("|---:|---:" if args.against else "") + "|")
    for sensor, *t in speed:
        print(f"| {sensor} | " + " | ".join(f"{v:.2f}" if k == 7 else f"{v:.1f}" for k, v in enumerate(t, 1)) + " |")
    if args.against:
        print(f"\nIdentical labels and joined hypotheses to {args.against}'s: {same} of {compared} segmentations "
              "(each frame in the camera frame and with its extrinsics).")
    print("\nObjects found, against the exact render's masks:\n")
    print("| sensor | objects | clean | merged | split | lost | spurious clusters |")
    print("|---|---:|---:|---:|---:|---:|---:|")
    for sensor, *g in quality:
        print(f"| {sensor} | {sum(g[:4])} | " + " | ".join(str(v) for v in g) + " |")


if __name__ == "__main__":
    main()
