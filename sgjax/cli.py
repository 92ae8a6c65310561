"""The `sgjax` command: one entry point, one subcommand per job.

This module sits at the top of the house: it may import `envs`, `train` and `eval` lazily inside a
subcommand, while the library modules below it never import upward.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from typing import Sequence

from sgjax.files import atomic_write

EXAMPLE_SHAPES = {
    # name: (semi-axes in metres, (eps1, eps2))
    "box": ((0.04, 0.03, 0.06), (0.1, 0.1)),
    "cylinder": ((0.035, 0.035, 0.07), (0.1, 1.0)),
    "ellipsoid": ((0.05, 0.03, 0.04), (1.0, 1.0)),
    "rounded-box": ((0.06, 0.025, 0.03), (0.4, 0.5)),
}


def _fail(message: str, code: int = 2) -> int:
    print(f"sgjax: error: {message}", file=sys.stderr)
    return code


def _cmd_example(args: argparse.Namespace) -> int:
    import numpy as np

    from sgjax import synthetic
    from sgjax.rotations import random_rotation
    from sgjax.superquadric import Superquadric

    import jax

    scale, eps = EXAMPLE_SHAPES[args.shape]
    rng = np.random.default_rng(args.seed)
    rot = np.asarray(random_rotation(jax.random.key(args.seed)))
    sq = Superquadric.create(scale, eps, rot, rng.uniform(-0.1, 0.1, 3))
    cloud = synthetic.single_view_cloud(
        sq, args.points, noise_std=args.noise, outlier_ratio=args.outliers, seed=rng
    )
    out = args.out if args.out.endswith(".npy") else f"{args.out}.npy"  # as np.save would name it
    atomic_write(out, lambda tmp: np.save(tmp, cloud.astype(np.float32)))
    truth = {"scale": list(scale), "epsilon": list(eps), "rotation": rot.tolist(), "translation": np.asarray(sq.translation).tolist()}
    print(f"wrote {out}: single-view cloud of a {args.shape}, {len(cloud)} points")
    print("truth:", json.dumps({k: np.round(v, 4).tolist() for k, v in truth.items()}))
    return 0


def _cmd_fit(args: argparse.Namespace) -> int:
    import numpy as np

    from sgjax import ems, pointcloud
    from sgjax.superquadric import to_mesh

    clouds, names, code = [], [], 0
    for path in args.files:
        try:
            clouds.append(pointcloud.load_cloud(path))
            names.append(path)
        except pointcloud.CloudError as exc:
            code = _fail(str(exc))
    if not clouds:
        return code or _fail("no cloud to fit")
    points, mask = pointcloud.pad_clouds(clouds, max_points=args.max_points, seed=args.seed)
    result = ems.fit_superquadrics(points, mask)
    for i, name in enumerate(names):
        r = result[i]
        if not bool(r.valid):
            code = _fail(f"{name}: {pointcloud.describe_status(int(r.status))}")
            continue
        record = {
            "file": name,
            "scale": np.asarray(r.scale).tolist(),
            "epsilon": np.asarray(r.epsilon).tolist(),
            "rotation": np.asarray(r.rotation).tolist(),
            "translation": np.asarray(r.translation).tolist(),
            "inlier_ratio": float(r.inlier_ratio),
            "valid": bool(r.valid),
        }
        if args.json:
            print(json.dumps(record))
        else:
            a, e, t = (np.round(np.asarray(x, np.float64), 4) for x in (r.scale, r.epsilon, r.translation))
            print(f"{name}: scale {a.tolist()} m  eps {e.tolist()}  centre {t.tolist()} m  inliers {float(r.inlier_ratio):.2f}")
        if args.mesh:
            out = args.mesh
            if len(names) > 1:
                stem, ext = os.path.splitext(args.mesh)
                out = f"{stem}_{os.path.splitext(os.path.basename(name))[0]}{ext or '.ply'}"
            mesh = to_mesh(r.superquadric)
            atomic_write(out, mesh.export)
            if not args.json:
                print(f"  fitted surface written to {out}")
    return code


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="sgjax", description="SuperGrasp in JAX + MuJoCo")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("fit", help="fit superquadrics (EMS) to object point clouds")
    p.add_argument("files", nargs="+", help=".npy (N x 3, metres), .ply or .pcd clouds")
    p.add_argument("--json", action="store_true", help="one JSON object per line")
    p.add_argument("--mesh", metavar="OUT.ply", help="write the fitted surface as a mesh")
    p.add_argument(
        "--max-points", type=int, default=1024, help="clouds are downsampled to this many points first (default 1024)"
    )
    p.add_argument("--seed", type=int, default=0, help="seed of the downsampling")
    p.set_defaults(func=_cmd_fit)

    p = sub.add_parser("example", help="write a synthetic single-view cloud of a known superquadric")
    p.add_argument("out", help="output .npy path")
    p.add_argument("--shape", choices=sorted(EXAMPLE_SHAPES), default="box")
    p.add_argument("--points", type=int, default=800)
    p.add_argument("--noise", type=float, default=0.001, help="Gaussian noise std (m)")
    p.add_argument("--outliers", type=float, default=0.0, help="fraction of outlier points")
    p.add_argument("--seed", type=int, default=0)
    p.set_defaults(func=_cmd_example)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
