"""Contact-GraspNet's widths on benchmark scenes (by hand; needs its environment): signed or not, big enough?

    python benchmarks/bench_cgn_widths.py [--setting seen-10] [--scenes 3] [--seed 0]

On the first observation of each scene, takes cgn-pytorch's confident grasps (> 0.5) whose contact is an
object point and reports: how many have a negative signed width w (the hand on the contact's -x side);
on which side of the contact the object lies (its observed points' centroid along x), against the side
the hand is placed on, by sign(w) and by relu(w) (what `cgn_pytorch.inference()` reports); |w|; and in
how many a finger box of our gripper (sgjax.geometry.gripper: the fingers at the opening's faces, over the
closing region's y and z ranges) holds observed points of the target, opening min(|w| + 5 mm, stroke)
(NVlabs' rule) or the full stroke.
"""

from __future__ import annotations

import argparse

import numpy as np

from envs.camera import observe
from envs.scene import stage2_scene_cloud
from eval.benchmark import resolve_objects
from eval.contact_graspnet import CGNConfig, ContactGraspNetMethod, cgn_to_sgjax
from eval.declutter import DeclutterConfig, get_setting, make_benchmark_scene
from sgjax.geometry import pointcloud


def finger_hit(pose: np.ndarray, opening: float, points: np.ndarray, spec) -> bool:
    """Whether a finger box of the hand (pose [4, 4], opening) holds any of points [N, 3]."""
    local = (points - pose[:3, 3]) @ pose[:3, :3]
    slab = (np.abs(local[:, 1]) <= spec.finger_width / 2) & (local[:, 2] >= 0) & (local[:, 2] <= spec.finger_length)
    x = np.abs(local[slab, 0])
    return bool(((x >= opening / 2) & (x <= opening / 2 + spec.finger_thickness)).any())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--setting", default="seen-10")
    parser.add_argument("--scenes", type=int, default=3)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    config = DeclutterConfig()
    setting = get_setting(args.setting)
    assets, _, _ = resolve_objects(setting, None, False)
    cloud_config = stage2_scene_cloud()
    cgn = CGNConfig(voxel=cloud_config.voxel, scene_bounds=cloud_config.bounds)
    spec = cgn.spec
    method = ContactGraspNetMethod(cgn)
    rows = []
    try:
        for index in range(args.scenes):
            scene = make_benchmark_scene(assets, setting.n_objects, args.seed, index, config)
            obs = observe(scene, config.camera, seed=args.seed)
            points, labels = np.asarray(obs.points, np.float64), np.asarray(obs.point_labels)
            finite = np.isfinite(points).all(axis=1)
            points, labels = points[finite], labels[finite]
            cloud, mask, cloud_labels = pointcloud.scene_cloud(points, cgn.max_points, cgn.voxel, labels,
                                                               cgn.scene_bounds, args.seed)
            cloud, cloud_labels = cloud[mask].astype(np.float64), cloud_labels[mask]
            raw = method.predict(cloud, cloud_labels >= 0, seed=args.seed)
            poses, opening = cgn_to_sgjax(raw["grasps"], raw["contacts"], raw["widths"], np.zeros(3), spec)
            for k in np.flatnonzero((raw["confidence"] > 0.5) & raw["on_object"]):
                target = cloud_labels[np.argmin(np.linalg.norm(cloud - raw["contacts"][k], axis=1))]
                obj = points[labels == target]
                side = float((obj.mean(axis=0) - raw["contacts"][k]) @ poses[k, :3, 0])
                w = raw["widths"][k]
                rows.append((w, side, finger_hit(poses[k], opening[k], obj, spec),
                             finger_hit(poses[k], spec.max_opening, obj, spec)))
    finally:
        method.close()
    w, side, hit_predicted, hit_full = (np.array(c, float) for c in zip(*rows))
    print(f"{args.setting} scenes 0-{args.scenes - 1}: {len(w)} confident grasps on objects")
    print(f"  w < 0 (hand on the contact's -x side): {np.mean(w < 0):.0%}")
    print(f"  object on the hand's side of the contact: by sign(w) {np.mean(np.sign(w) == np.sign(side)):.0%}, "
          f"by relu(w) (the hand on +x) {np.mean(side > 0):.0%}")
    print(f"  |w| percentiles 10/25/50/75/90 (cm): {np.round(100 * np.percentile(np.abs(w), [10, 25, 50, 75, 90]), 1)}")
    print(f"  a finger box holds target points: opening min(|w| + 5 mm, stroke) {hit_predicted.mean():.0%}, "
          f"full stroke {hit_full.mean():.0%}")


if __name__ == "__main__":
    main()
