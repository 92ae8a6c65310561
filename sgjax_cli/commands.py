"""The `sgjax` command's subcommands: one entry point (`main`), one subcommand per job.

This package sits at the top of the house: it may import `envs`, `train` and `eval` (lazily, inside a
subcommand, so that `sgjax --help` stays fast), while the layers below it never import upward.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from collections.abc import Sequence

from sgjax.geometry.gripper_files import preset_names as gripper_presets
from sgjax.presets import names as preset_names
from sgjax.utils.files import atomic_write

SENSORS = ("exact", "kinect", "realsense", "stereo")  # envs.sensors.SENSORS (a test keeps them equal)
MASKS = ("truth", "clusters")  # eval.declutter.MASKS (the same test)
# envs.trial.BACKENDS, spelled out here so that the CLI imports no simulator before a command runs.
BACKEND_HELP = ("grasp trial engine: cpu (default; MuJoCo's C engine), mjx (MJX: its warp implementation on a GPU "
                "where warp-lang is installed, else its JAX one), mjx-jax, mjx-warp")
EXAMPLE_SHAPES = {
    # name: (semi-axes in metres, (eps1, eps2))
    "box": ((0.04, 0.02, 0.06), (0.1, 0.1)),  # graspable across its 4 cm side with an 8 cm stroke
    "cylinder": ((0.025, 0.025, 0.06), (0.1, 1.0)),
    "ellipsoid": ((0.05, 0.03, 0.04), (1.0, 1.0)),
    "rounded-box": ((0.06, 0.025, 0.03), (0.4, 0.5)),
}


def _fail(message: str, code: int = 2) -> int:
    print(f"sgjax: error: {message}", file=sys.stderr)
    return code


# ---------------------------------------------------------------------------------------------
# --gripper NAME|FILE: the gripper a command plans, labels, trains or benchmarks with.

GRIPPER_HELP = (f"the gripper: a preset ({', '.join(gripper_presets())}) or a .toml / .json gripper file "
                "(sgjax.geometry.gripper_files; default: the default gripper)")


def _add_gripper(p: argparse.ArgumentParser, help_text: str = GRIPPER_HELP) -> None:
    p.add_argument("--gripper", default=None, metavar="NAME|FILE", help=help_text)


def _gripper(args: argparse.Namespace):
    """The GripperSpec of --gripper (GripperSpec() when not given). Raises ValueError (the file's
    GripperFileError: one line naming the field, or listing the presets) prefixed with the option."""
    from sgjax.geometry.gripper import GripperSpec
    from sgjax.geometry.gripper_files import GripperFileError, load_gripper

    if args.gripper is None:
        return GripperSpec()
    try:
        return load_gripper(args.gripper)
    except GripperFileError as exc:
        raise ValueError(f"--gripper: {exc}") from None


def _database_ready(cfg) -> bool:
    from sgjax.stage1.database import default_path, shipped_path

    return default_path(cfg).is_file() or shipped_path(cfg).is_file()


def _note_database(cfg, small: bool = False) -> None:
    """A one-line note when the database of `cfg`, for a gripper other than the default one, is not
    built yet (only the default gripper's ships): the next load builds it into the cache, once."""
    import dataclasses

    from sgjax.geometry.gripper import GripperSpec
    from sgjax.stage1.database import default_path

    # The database holds the geometry only (DBConfig.key): a default-sized gripper with another force uses the default one.
    if dataclasses.asdict(cfg.spec) != dataclasses.asdict(GripperSpec()) and not _database_ready(cfg):
        took = "seconds" if small else "~3 min on 2 cores"
        print(f"sgjax: note: no primitive database for this gripper yet: building it into {default_path(cfg)} "
              f"(once, {took})", file=sys.stderr)


def _prepare_database(spec, small: bool = False) -> None:
    """Build the database of gripper `spec` into the cache if it is not there (with the note), so that
    what loads it later (a benchmark method, labelling) finds it."""
    from sgjax.stage1.database import DBConfig, build_database, default_path, save_database

    cfg = DBConfig.for_gripper(spec, small)
    if not _database_ready(cfg):
        _note_database(cfg, small)
        save_database(build_database(cfg, progress=False), default_path(cfg))


def _database(spec, small: bool = False, path: str | None = None, check: bool = False):
    """The primitive database for gripper `spec`: the file `path` (--db; with `check`, the --gripper
    given, ValueError when it was built for another gripper), else the cached / shipped one, built
    first when missing (with the note)."""
    import dataclasses

    from sgjax.stage1.database import DBConfig, load_database, load_database_file

    if path:
        db = load_database_file(path)
        built_for = json.loads(db.config_json).get("spec")
        if check and built_for is not None and built_for != json.loads(json.dumps(dataclasses.asdict(spec))):
            raise ValueError(f"--db {path} was built for another gripper ({built_for}) than --gripper's: "
                             "build one with `sgjax build-db --gripper ...` or leave --db out")
        return db
    cfg = DBConfig.for_gripper(spec, small)
    _note_database(cfg, small)
    return load_database(cfg)


class _warnings_as_notes:
    """Within it, the warning about a network checkpoint trained for another gripper than the one planned
    for (`sgjax.stage2.checkpoint.GripperMismatchWarning`) prints as one line, "sgjax: warning: ...", on
    stderr; other warnings print as Python prints them."""

    def __enter__(self):
        import warnings

        from sgjax.stage2.checkpoint import GripperMismatchWarning

        self._catch = warnings.catch_warnings()
        self._catch.__enter__()
        shown = warnings.showwarning

        def show(message, category, *rest, **options):
            if issubclass(category, GripperMismatchWarning):
                print(f"sgjax: warning: {message}", file=sys.stderr)
            else:
                shown(message, category, *rest, **options)

        warnings.showwarning = show
        return self

    def __exit__(self, *exc):
        return self._catch.__exit__(*exc)


def _cmd_example(args: argparse.Namespace) -> int:
    import numpy as np

    from sgjax.geometry import synthetic
    from sgjax.geometry.rotations import random_rotation
    from sgjax.geometry.superquadric import Superquadric

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

    from sgjax.stage1 import ems
    from sgjax.geometry import pointcloud
    from sgjax.geometry.superquadric import to_mesh

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


def _object_set_name(args: argparse.Namespace) -> str:
    return args.objects if args.objects is not None else args.set


def _cmd_objects_prepare(args: argparse.Namespace) -> int:
    from envs import objects

    name = _object_set_name(args)
    try:
        report = objects.prepare_object_set(
            name, workers=args.workers, progress=not args.quiet, retry_failed=args.retry_failed
        )
    except ValueError as exc:
        return _fail(str(exc))
    hulls = [len(a.hull_paths) for a in report.assets]
    print(
        f"object set {name!r}: {len(report.assets)} ready ({len(report.prepared)} prepared now, "
        f"{len(report.cached)} cached), {len(report.failures)} skipped"
    )
    if hulls:
        print(f"  convex pieces per object: mean {sum(hulls) / len(hulls):.1f}, max {max(hulls)}")
    for failure in report.failures:
        print(f"  skipped {failure.name}: {failure.reason}{' (recorded earlier)' if failure.cached else ''}")
    if report.failures:
        print(f"  failures recorded in {report.report_path}; --retry-failed tries them again")
    return 1 if report.failures else 0


def _cmd_objects_list(args: argparse.Namespace) -> int:
    import dataclasses

    from envs import objects

    name = _object_set_name(args)
    try:  # listing never prepares (slow); the tiny set is cheap enough to build on the spot
        report = objects.prepare_object_set(name, cached_only=name != "tiny")
    except ValueError as exc:
        return _fail(str(exc))
    for a in report.assets:
        if args.json:
            print(json.dumps(dataclasses.asdict(a)))
        else:
            size = " x ".join(f"{100 * e:5.1f}" for e in a.extents)
            print(f"{a.name:40s} {size} cm  {a.mass:6.3f} kg  {len(a.hull_paths):2d} hull(s)  [{a.source}]")
    if report.missing:
        print(
            f"{len(report.missing)} object(s) of {name!r} not prepared yet: run `sgjax objects prepare "
            f"{'--objects' if args.objects is not None else '--set'} {name}`",
            file=sys.stderr,
        )
    return 0


# `sgjax train`'s settings: their parser defaults are None so that --recipe can tell which were given;
# these are the values a run without --recipe takes.
TRAIN_DEFAULTS = {
    "epochs": 100, "batch_size": 128, "lr": 1e-3, "weight_decay": 3e-4, "decoupled_weight_decay": False,
    "lr_decay_epochs": 0, "held_out": 0.1, "devices": 1, "model": "light", "network": "ernet", "hand_points": 0,
    "seed": 0, "synthetic": 0,
}
TRAIN_OPTIONS = (("data", "--data"), ("init", "--init"), *((name, "--" + name.replace("_", "-")) for name in TRAIN_DEFAULTS))


def _cmd_train(args: argparse.Namespace) -> int:
    if args.recipe is not None or args.list_recipes:
        return _train_recipe(args)
    missing = [flag for flag in ("--data", "--out") if getattr(args, flag[2:]) is None]
    if missing:
        return _fail(f"train needs {' and '.join(missing)} (or --recipe NAME: a shipped checkpoint's recipe)")
    if args.tiny:
        return _fail("--tiny runs a recipe at test size: give --recipe NAME")
    for name, value in TRAIN_DEFAULTS.items():
        if getattr(args, name) is None:
            setattr(args, name, value)
    return _train_options(args)


def _train_options(args: argparse.Namespace) -> int:
    from sgjax.stage2.ernet import ERNetConfig
    from train import dataset, trainer

    network, run = ERNetConfig, trainer.train
    if args.network == "pointnetgpd":  # the baseline, on the same shards (train/train_pointnetgpd.py)
        from sgjax.stage2.pointnetgpd import PointNetGPDConfig
        from train import train_pointnetgpd

        network, run = PointNetGPDConfig, train_pointnetgpd.train

    hand = {"hand_points": args.hand_points} if args.hand_points else {}
    if hand and args.network != "ernet":
        return _fail("--hand-points is an E-RNet input; the PointNetGPD baseline sees its closing region only")
    try:
        given = _gripper(args) if args.gripper is not None else None
    except ValueError as exc:
        return _fail(str(exc))
    if args.synthetic:
        if len(args.data) > 1:
            return _fail("--synthetic writes to one --data directory")
        data = args.data[0]
        os.makedirs(data, exist_ok=True)
        if dataset.shard_paths(data):
            return _fail(f"--synthetic: {data} already holds shards")
        samples = dataset.synthetic_samples(args.synthetic, args.seed)
        print(f"wrote {args.synthetic} synthetic samples to {dataset.write_shard(os.path.join(data, 'synthetic_000'), samples)}")
    try:  # a bad combination (e.g. --batch-size not divisible by --devices) is a usage error, not a traceback
        spec = _training_gripper(args.data, given, args.gripper)
        if args.network == "ernet" and spec.num_refinements != network().n_refinements:
            hand["n_refinements"] = spec.num_refinements  # one refine output per refinement of the gripper
        if args.init is not None:
            _note_init_gripper(args.init, args.network, spec)
        config = trainer.TrainConfig(
            epochs=args.epochs,
            batch_size=args.batch_size,
            lr=args.lr,
            weight_decay=args.weight_decay,
            decoupled_weight_decay=args.decoupled_weight_decay,
            seed=args.seed,
            held_out_fraction=args.held_out,
            lr_decay_epochs=args.lr_decay_epochs,
            devices=args.devices,
            model={"paper": network.paper, "light": network.light, "tiny": network.tiny}[args.model](**hand),
            spec=spec,
        )
        result = run(args.data, args.out, config, progress=not args.quiet, init=args.init)  # one directory or several
    except (dataset.DatasetError, ValueError) as exc:
        return _fail(str(exc))
    except KeyboardInterrupt:
        print(f"\ninterrupted: rerun the same command to resume after the last finished epoch in {args.out}", file=sys.stderr)
        return 130
    print(f"done: {len(result.history)} epochs; checkpoints, metrics.json/.csv and curves.png in {result.run_dir}")
    return 0


def _training_gripper(data, given, option: str | None):
    """The gripper a training run is for: its labelled directories' (`train.label.data_gripper`: one
    gripper, the whole spec). ValueError when --gripper was `given` and is another gripper than the data's."""
    from sgjax.stage2.checkpoint import describe_gripper
    from train.label import data_gripper

    spec = data_gripper(data)
    if given is not None and given != spec:
        raise ValueError(f"--gripper {option} is not the gripper the labels in {', '.join(data)} were made for: "
                         f"they are for {describe_gripper(spec, given)}, --gripper is {describe_gripper(given, spec)} "
                         f"(label for your gripper with `sgjax label --gripper {option}`)")
    return spec


def _note_init_gripper(init: str, network: str, spec) -> None:
    """A one-line note when --init's checkpoint was trained for another gripper than this run's data."""
    from sgjax.stage2.checkpoint import checkpoint_gripper, describe_gripper

    try:
        trained = checkpoint_gripper(init)
    except (FileNotFoundError, ValueError):  # the trainer says what is wrong with the directory
        return
    if trained != spec:
        print(f"sgjax: note: --init {init} was trained for gripper {describe_gripper(trained, spec)}; this run trains "
              f"it on labels of gripper {describe_gripper(spec, trained)}", file=sys.stderr)


def _train_recipe(args: argparse.Namespace) -> int:
    """`sgjax train --recipe NAME|FILE [--out RUN] [--tiny]` and `sgjax train --list-recipes`."""
    from train import dataset
    from train import recipe as recipes

    given = [flag for name, flag in TRAIN_OPTIONS if getattr(args, name) is not None]
    if args.list_recipes:
        given += [flag for flag, value in (("--out", args.out), ("--tiny", args.tiny), ("--gripper", args.gripper)) if value]
        if given:
            return _fail(f"--list-recipes takes no other option, got {', '.join(given)}")
        return _list_recipes()
    if args.gripper is not None:
        given.append("--gripper")  # a recipe's label sets are the default gripper's
    if given:
        return _fail(f"--recipe sets the data and every training setting: drop {', '.join(given)} (or train from a "
                     "copy of the recipe file with them changed)")
    try:
        recipe = recipes.load_recipe(args.recipe)
    except (FileNotFoundError, ValueError) as exc:
        return _fail(str(exc))
    out = args.out or os.path.join("runs", recipe.name + (recipes.TINY_SUFFIX if args.tiny else ""))
    try:
        result = recipes.run_recipe(recipe, out, tiny=args.tiny, progress=not args.quiet)
    except (dataset.DatasetError, ValueError, FileNotFoundError, ImportError) as exc:
        return _fail(str(exc))
    except KeyboardInterrupt:
        print(f"\ninterrupted: rerun the same command to resume (labels and epochs done are kept) in {out}", file=sys.stderr)
        return 130
    print(f"done: recipe {recipe.name}{' (--tiny)' if args.tiny else ''}, {len(result.train.history)} epochs; "
          f"checkpoint {result.checkpoint} (its meta records the recipe and the commit)")
    if args.tiny:
        print("a --tiny run checks the recipe end to end; it is not a checkpoint to ship")
    else:
        print(f"to ship it as sgjax/models/{recipe.name} (the last epoch's params and meta, no optimiser state):")
        for line in recipes.ship_lines(out, recipe.name):
            print(f"  {line}")
    return 0


def _list_recipes() -> int:
    from train import recipe as recipes

    failed = 0
    for name in recipes.recipe_names():
        try:
            print(recipes.describe(recipes.load_recipe(name)))
        except (FileNotFoundError, ValueError) as exc:
            print(f"{name}: {exc}", file=sys.stderr)
            failed += 1
    return 1 if failed else 0


def _cmd_score_data(args: argparse.Namespace) -> int:
    from train import dataset, judgement, score_data

    try:
        result = score_data.score_directory(args.data, args.model, args.network, args.batch_size, args.held_out, args.seed,
                                            args.resamples)
    except (dataset.DatasetError, ValueError, FileNotFoundError) as exc:
        return _fail(str(exc))
    if args.json:
        print(json.dumps(result, indent=1))
        return 0
    print(f"{args.network} ({args.model or 'shipped default'}) on {', '.join(args.data)}:")
    print(f"  {judgement.summary_line(result)}\n")
    print(score_data.report_table(result))
    return 0


def _scene_range(scenes: str, first_scene: int | None) -> tuple[int, int]:
    """--scenes N | A:B (+ --first-scene S) -> (first scene, end); ValueError names a bad spelling."""
    first, colon, end = scenes.partition(":")
    if not (end if colon else first).strip().isdigit() or (colon and not first.strip().isdigit()):
        raise ValueError(f"--scenes must be N (scenes 0..N-1) or A:B (scenes A..B-1), got {scenes!r}")
    if colon and first_scene is not None:
        raise ValueError("give the first scene once: --scenes A:B or --first-scene A --scenes B")
    if colon:
        return int(first), int(end)
    return (first_scene or 0), int(first)


def _cmd_label(args: argparse.Namespace) -> int:
    from sgjax.geometry.gripper import GripperSpec
    from sgjax.stage1.database import DBConfig
    from sgjax.stage1.pipeline import Stage1
    from train import label
    from train.label_ray import WorkerFailures  # imports no ray: that waits for --ray
    from train.label import label_config

    try:
        spec = _gripper(args)
        first_scene, n_scenes = _scene_range(args.scenes, args.first_scene)
        shard = None if args.shard is None else label.parse_shard(args.shard)
        if args.ray is not None and shard is not None:
            raise ValueError("--shard splits the work between separate processes; --ray does it for you: give one of them")
        if args.ray is None and args.workers is not None:
            raise ValueError("--workers is the number of Ray workers: it needs --ray")
        if n_scenes <= first_scene:
            raise ValueError(f"no scenes to label: the first scene {first_scene} is not below --scenes {n_scenes}")
        config = label_config(  # shared with `sgjax train --recipe`, whose label sets resume directories made here
            objects=args.objects, seed=args.seed, camera=args.camera, n_objects=args.n_objects,
            targets_per_scene=args.targets_per_scene, per_source=args.per_source, held_out_objects=args.held_out_objects,
            note=lambda text: print(text, file=sys.stderr), gripper=spec,
        )
        if spec != GripperSpec():  # no shipped database for it: built into the cache first (with a note),
            label.check_out_dir(args.out, config)  # once the directory is known to take this config
            _prepare_database(spec, args.small_db)
        if args.ray is not None:
            from train.label_ray import label_ray

            run = label_ray(
                args.out, n_scenes, config, db=DBConfig.for_gripper(spec, args.small_db), address=args.ray or None,
                workers=args.workers, threads=args.threads or 1, backend=args.backend, first_scene=first_scene,
                progress=not args.quiet,
            )
            summary = run.summary
            print(run.lines()[0])
        else:
            stage1 = Stage1(_database(spec, small=True), config.stage1) if args.small_db else None
            summary = label.label(
                args.out, n_scenes, config, stage1=stage1, backend=args.backend, nthread=args.threads, progress=not args.quiet,
                first_scene=first_scene, shard=shard,
            )
    except (ValueError, FileNotFoundError, ImportError) as exc:
        return _fail(str(exc))
    except WorkerFailures as exc:  # too many Ray workers died; what they finished is kept
        return _fail(str(exc), code=1)
    except KeyboardInterrupt:
        print(f"\ninterrupted: rerun the same command to continue; finished shards in {args.out} are kept", file=sys.stderr)
        return 130
    print(f"labelled {args.out}:")
    for line in summary.lines():
        print(f"  {line}")
    return 0


def _cmd_build_db(args: argparse.Namespace) -> int:
    from sgjax.stage1.database import (
        DBConfig,
        build_database,
        default_path,
        load_database_file,
        save_database,
        ship_database,
    )

    try:
        spec = _gripper(args)
    except ValueError as exc:
        return _fail(str(exc))
    if args.ship and args.gripper is not None and spec != DBConfig().spec:
        return _fail("--ship: only the default gripper's database ships (others are built into the cache on first use)")
    cfg = DBConfig.for_gripper(spec, args.small)
    path = args.out or default_path(cfg)
    if os.path.isfile(path) and not args.force:
        db = load_database_file(path)
        print(f"primitive database already built: {path}")
    else:
        db = build_database(cfg, workers=args.workers)
        save_database(db, path)
        print(f"wrote {path}")
    if args.ship:  # refresh the copy that ships with the package (developers, after a BUILD_VERSION bump)
        if args.small:
            return _fail("--ship: only the default database ships")
        print(f"wrote {ship_database(db, cfg)}")
    print(json.dumps(db.summary()))
    return 0


def _cmd_candidates(args: argparse.Namespace) -> int:
    import numpy as np

    from sgjax.geometry.pointcloud import CloudError, load_cloud
    from sgjax.stage1.pipeline import Stage1, Stage1Config

    try:
        spec = _gripper(args)
        cloud = load_cloud(args.cloud)
        scene = load_cloud(args.scene) if args.scene else None
        db = _database(spec, args.small_db, args.db, check=args.gripper is not None)
        viewpoint = None if args.viewpoint is None else np.asarray(args.viewpoint, float)
        cands = Stage1(db, Stage1Config(spec=spec))(cloud, scene, viewpoint=viewpoint, seed=args.seed)
    except (CloudError, ValueError, FileNotFoundError) as exc:
        return _fail(str(exc))
    if args.json:
        print(cands.to_json(top=args.top))
    else:
        print(f"{args.cloud}: {len(cands)} candidates  (filters: {cands.counts})")
        if cands.reason:
            print(f"  no candidate: {cands.reason}")
        for i in range(min(args.top, len(cands))):
            pos = np.round(cands.poses[i, :3, 3], 4).tolist()
            app = np.round(cands.poses[i, :3, 2], 3).tolist()
            if cands.primitive_id[i] < 0:  # a grasp on the fit itself (Stage1Config.fit_grasps)
                source = "the fitted superquadric"
            else:
                p = db.primitive(int(cands.primitive_id[i]))
                source = f"{p.family} {np.round(p.dims, 3).tolist()} (s = {cands.match_score[i]:.3f})"
            print(f"  #{i}: width {cands.widths[i]:.4f} m  position {pos}  approach {app}  from {source}")
    if args.png:
        from sgjax.draw import draw_grasps

        draw_grasps(args.png, cloud, cands.poses, cands.widths, scene_points=scene, max_grasps=args.top,
                    title=f"{os.path.basename(args.cloud)}: {len(cands)} Stage-1 candidates")
        if not args.json:
            print(f"wrote {args.png}")
    return 0


FRAME_OPTIONS = (("depth", "--depth"), ("intrinsics", "--intrinsics"), ("depth_scale", "--depth-scale"),
                 ("extrinsics", "--extrinsics"), ("masks", "--masks"), ("workspace_mask", "--workspace-mask"),
                 ("all_objects", "--all-objects"), ("top", "--top"))
CLOUD_OPTIONS = (("mask", "--mask"), ("viewpoint", "--viewpoint"))
FORMS = "a scene cloud (sgjax plan CLOUD --mask MASK.npy) or a depth image (sgjax plan --depth D --intrinsics K)"


def _given(args: argparse.Namespace, options) -> list[str]:
    return [flag for name, flag in options if getattr(args, name) not in (None, False)]


def _cmd_plan(args: argparse.Namespace) -> int:
    """The two forms of `plan`: a scene cloud with a mask, or a depth frame; never a mix of them."""
    frame_given, cloud_given = _given(args, FRAME_OPTIONS), _given(args, CLOUD_OPTIONS)
    if args.cloud is not None and args.depth is not None:
        return _fail(f"give {FORMS}, not both")
    if args.cloud is None and args.depth is None:
        return _fail(f"nothing to plan on: give {FORMS}")
    if args.cloud is not None:
        if frame_given:
            return _fail(f"{', '.join(frame_given)}: only for a depth image (sgjax plan --depth D --intrinsics K), "
                         f"not for a scene cloud")
        if args.mask is None:
            return _fail("a scene cloud needs --mask MASK.npy (one entry per point: bool target or int object labels)")
        return _plan_cloud(args)
    if cloud_given:
        return _fail(f"{', '.join(cloud_given)}: only for a scene cloud (sgjax plan CLOUD --mask MASK.npy), not for a "
                     f"depth image (--masks takes instance ids per pixel)")
    if args.intrinsics is None:
        return _fail("--depth needs --intrinsics K (the camera's calibration: .json, .yaml/.yml or a 3x3 .npy)")
    return _plan_frame(args)


def _plan_cloud(args: argparse.Namespace) -> int:
    import numpy as np

    from sgjax.geometry.pointcloud import CloudError, load_cloud

    try:
        spec = _gripper(args)
        cloud = load_cloud(args.cloud)
        if not os.path.isfile(args.mask):
            raise CloudError(f"{args.mask}: no such file")
        try:
            mask = np.load(args.mask, allow_pickle=False)
        except (OSError, ValueError, EOFError) as exc:
            raise CloudError(f"{args.mask}: cannot read the mask ({type(exc).__name__}: {exc})") from None
        if mask.shape != (len(cloud),) or mask.dtype.kind not in "biu":
            raise CloudError(
                f"{args.mask}: the mask must be bool [N] (target) or int [N] (object labels) with N = {len(cloud)} "
                f"(the cloud's points), got {mask.dtype} {mask.shape}"
            )
        _prefetch_programs(args, spec, f"cloud {mask.dtype == bool}")
        db = _database(spec, args.small_db, args.db, check=args.gripper is not None)
        planner = _planner(args, spec, db, per_object=mask.dtype == bool)
        viewpoint = (0.0, 0.0, 0.0) if args.viewpoint is None else tuple(args.viewpoint)
        if mask.dtype == bool:
            plan = planner.plan_masked(cloud, mask, viewpoint, seed=args.seed)
        else:
            plan = planner.plan(cloud, mask, viewpoint, seed=args.seed)
    except (CloudError, ValueError, FileNotFoundError) as exc:
        return _fail(str(exc))
    t = plan.timing
    timing = f"stage 1 {t['stage1_s']:.3f} s, stage 2 {t['stage2_s']:.3f} s, total {t['total_s']:.3f} s"
    if t.get("compiled"):
        timing += " (includes compilation)"
    if args.json:
        print(json.dumps({**plan.to_dict(), "checkpoint": planner.checkpoint}))
    elif plan.kind is None:
        print(f"no grasp: {plan.reason}  ({plan.n_candidates} candidates)")
        print(f"  {timing}")
    else:
        pos, app = (np.round(plan.pose[:3, k], 4).tolist() for k in (3, 2))
        how = f"refined (variant {plan.refine_variant})" if plan.kind == "refined" else "evaluated"
        print(f"{how} grasp on object {plan.target}: score {plan.score:.3f}, candidate #{plan.candidate_index} "
              f"of {len(plan.scores['eval_prob'])} scored ({plan.n_candidates} from Stage 1)")
        print(f"  position {pos}  approach {app}  width {plan.width:.4f} m")
        print(f"  {timing}")
    if not args.json:
        print(f"  E-RNet checkpoint: {planner.checkpoint}")
    if args.png:
        from sgjax.draw import draw_grasps

        if mask.dtype == bool:
            target = cloud[mask]
        else:
            target = cloud[mask == plan.target] if plan.target is not None else cloud[mask >= 0]
        poses = None if plan.pose is None else plan.pose[None]
        widths = None if plan.pose is None else np.array([plan.width])
        title = f"{plan.kind} grasp, score {plan.score:.2f}" if plan.kind else f"no grasp: {plan.reason}"[:90]
        draw_grasps(args.png, target if len(target) else cloud, poses, widths, scene_points=cloud, title=title)
        if not args.json:
            print(f"wrote {args.png}")
    return 0 if plan.kind is not None else 1


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split()) or type(exc).__name__


def _read_file(path: str, what: str, read):
    """read(path); a file that cannot be read raises ValueError naming the path (FileNotFoundError as is)."""
    try:
        return read(path)
    except FileNotFoundError:
        raise
    except (ValueError, OSError, EOFError) as exc:
        message = _one_line(exc)
        if message.startswith(path):  # perception's readers name the file first
            raise ValueError(message) from None
        raise ValueError(f"{path}: cannot read the {what} ({message})") from None


NO_NETWORK = "none"  # `sgjax plan --model none`: Stage 1's order, no Stage-2 network
ONE_FRAME_STAGE1_SIZES = (4,)  # `sgjax plan`'s Stage-1 batch size (`PlannerConfig.stage1_batch_sizes`)
ONE_FRAME_STAGE2_SLOTS = 128  # and its smallest Stage-2 batch (`PlannerConfig.stage2_min_slots`)


def _planner(args: argparse.Namespace, spec, db, per_object: bool):
    """The planner of `sgjax plan`: --preset for --gripper's spec, with --model's E-RNet (None: the one
    shipped for the gripper) or, for `--model none`, no network (Stage 1's order, no refinement). A
    checkpoint trained for another gripper is warned about in one line. per_object: the process plans
    one object at a time (a target mask, --all-objects), not whole scenes."""
    import dataclasses

    from sgjax import presets
    from sgjax.planner import Planner, stage1_order_planner

    config = presets.get(args.preset, gripper=spec)
    if not per_object:
        # A process that plans a scene once loads one Stage-1 program (objects in chunks of 4, the last
        # padded) instead of one per chunk size, and Stage 2 scores in batches of at least 128, so that the
        # robust choice's re-score (<= 64 rows) runs in the first scoring's program when that took <= 128:
        # fewer programs to load, the same scores (docs/real-camera.md). Plans of one object run Stage 1
        # at batch 1, one program already (padded to 4 they took 1.1x as long).
        config = dataclasses.replace(config, stage1_batch_sizes=ONE_FRAME_STAGE1_SIZES,
                                     stage2_min_slots=ONE_FRAME_STAGE2_SLOTS)
    if args.model == NO_NETWORK:
        return stage1_order_planner(db, config)
    with _warnings_as_notes():  # the checkpoint trained for another gripper: one line
        return Planner(model=args.model, db=db, config=config)


def _prefetch_programs(args: argparse.Namespace, spec, form: str) -> None:
    """Start loading the programs that the last `sgjax plan` of this form and these settings called, on a
    second thread, while this one reads the input and restores the network (`exported.prefetch`: ~1 s
    less on 2 cores, docs/real-camera.md)."""
    from sgjax.utils import exported

    exported.prefetch(f"plan {form} {spec!r} {args.model} {args.preset} {args.small_db} {args.db}")


def _frame_json(frame, result, timing: dict, checkpoint: str) -> dict:
    """The depth form's JSON document (README, docs/real-camera.md); checkpoint: `Planner.checkpoint`."""
    import numpy as np

    objects = [{"id": i, "points": int(np.sum(frame.labels == i)),
                "centroid": np.round(frame.object_points(i).mean(0), 6).tolist()} for i in frame.object_ids]
    reasons = {str(key): why for key, why in result.reasons.items()}
    return {"frame": frame.frame, "table": [round(float(v), 6) for v in frame.table.plane], "objects": objects,
            "grasps": [g.to_dict() for g in result.grasps], "reasons": reasons, "checkpoint": checkpoint, "timing": timing}


def _plan_frame(args: argparse.Namespace) -> int:
    import time

    import numpy as np

    start = time.perf_counter()
    try:
        spec = _gripper(args)
    except ValueError as exc:
        return _fail(str(exc))
    scale = 1000.0 if args.depth_scale is None else args.depth_scale
    top = 1 if args.top is None else args.top
    if not (np.isfinite(scale) and scale > 0):
        return _fail(f"--depth-scale must be a number > 0 (depth units per metre; 1000: millimetres), got {scale:g}")
    if top < 1:
        return _fail(f"--top must be >= 1, got {top}")

    from sgjax import perception
    from sgjax.perception.camera import existing_file

    try:
        existing_file(args.depth, "depth image")  # the depth's error first, as its option comes first
        intrinsics = _read_file(args.intrinsics, "intrinsics", perception.read_intrinsics)
        extrinsics = None if args.extrinsics is None else _read_file(args.extrinsics, "extrinsics",
                                                                     perception.read_extrinsics)
        images = {}  # each read once, here, so that its errors name the option's file
        for path, what in ((args.masks, "masks"), (args.workspace_mask, "workspace mask")):
            if path is not None:
                if not os.path.isfile(path):
                    raise FileNotFoundError(f"{path}: no such {what} file")
                images[what] = _read_file(path, what, lambda p, w=what: perception.read_image(p, w))
        masks = images.get("masks")
        # The files read, before the front end (and its SciPy imports): a bad file's error need not wait for it.
        _prefetch_programs(args, spec, f"--depth {args.all_objects}")
        # The depth by its path: the front end reads it (and knows a PNG's scale from a float file's metres).
        frame = perception.Frame.from_depth(args.depth, intrinsics, depth_scale=scale, extrinsics=extrinsics,
                                            masks=masks, workspace=images.get("workspace mask"), seed=args.seed)
    except (ValueError, OSError) as exc:  # PerceptionError is a ValueError, FileNotFoundError an OSError
        return _fail(_one_line(exc))
    if not frame.object_ids and masks is not None and not np.any(np.asarray(masks) > 0):
        return _fail(f"{args.masks}: the masks hold no object (every id is 0, the background)")
    if not frame.object_ids:
        on_table = int(np.sum(frame.labels == perception.TABLE))
        how = ("no masked pixel has a depth point on or above the table" if frame.segmentation == "masks"
               else "no cluster of points stands on the table")
        return _fail(f"no object found above the table: {how} ({len(frame.points)} points, {on_table} on the table; "
                     f"table plane {np.round(frame.table.plane, 4).tolist()})")
    perception_s = time.perf_counter() - start

    from sgjax.grasping import plan_frame

    try:
        db = _database(spec, args.small_db, args.db, check=args.gripper is not None)
        planner = _planner(args, spec, db, per_object=args.all_objects)
        setup_s = time.perf_counter() - start - perception_s
        result = plan_frame(planner, frame, all_objects=args.all_objects, top=top, seed=args.seed)
    except (ValueError, FileNotFoundError) as exc:
        return _fail(_one_line(exc))
    frame = result.frame  # the hypothesis that gave the grasps (`Frame.hypotheses`)
    plans = [p for p in result.plans.values() if p is not None]
    timing = {"perception_s": perception_s, "setup_s": setup_s, "plan_s": result.timing["plan_s"],
              "stage1_s": sum(p.timing.get("stage1_s", 0.0) for p in plans),
              "stage2_s": sum(p.timing.get("stage2_s", 0.0) for p in plans)}
    timing = {k: round(float(v), 4) for k, v in timing.items()}
    timing["compiled"] = any(bool(p.timing.get("compiled")) for p in plans)

    wrote = None
    if args.png:
        from sgjax.draw import draw_on_image

        poses = np.stack([g.pose for g in result.grasps]) if result.grasps else np.zeros((0, 4, 4))
        to_camera = np.eye(4) if frame.extrinsics is None else np.linalg.inv(frame.extrinsics)
        image = perception.read_depth(args.depth, scale)  # the picture's background (only with --png)
        shown = min(len(poses), 20)
        names = [f"{g.object}{'' if g.kind != 'alternative' else '*'}" for g in result.grasps]
        title = (f"{len(result.grasps)} grasp(s) on {len(frame.object_ids)} object(s), {frame.frame} frame"
                 + ("; * alternative" if any(g.kind == "alternative" for g in result.grasps) else ""))
        try:
            draw_on_image(args.png, image, intrinsics.K, to_camera @ poses, np.array([g.width for g in result.grasps]),
                          labels_image=frame.label_image(), scores=np.array([g.score for g in result.grasps]),
                          names=names, max_grasps=shown, title=title, points=frame.points[frame.labels > 0],
                          scene_points=frame.points[frame.labels == perception.TABLE], frame_poses=poses, up=frame.table.normal)
        except OSError as exc:
            return _fail(f"{args.png}: cannot write the picture ({_one_line(exc)})")
        wrote = args.png
    timing["total_s"] = round(time.perf_counter() - start, 4)

    if args.json:
        print(json.dumps(_frame_json(frame, result, timing, planner.checkpoint)))
    else:
        _print_frame_plan(frame, result, timing)
        print(f"  E-RNet checkpoint: {planner.checkpoint}")
        if wrote:
            print(f"wrote {wrote}")
    return 0 if result.grasps else 1


def _print_frame_plan(frame, result, timing: dict) -> None:
    import numpy as np

    r = lambda a, d=4: np.round(np.asarray(a, np.float64), d).tolist()
    where = "camera frame (no extrinsics: x right, y down, z forward)" if frame.frame == "camera" else "world frame"
    sizes = ", ".join(f"{i} ({int(np.sum(frame.labels == i))} points)" for i in frame.object_ids)
    print(f"{where}; table plane {r(frame.table.plane)}")
    print(f"{len(frame.object_ids)} object(s) from {frame.segmentation}: {sizes}")
    for g in result.grasps:
        print(f"  object {g.object}: {g.kind} grasp, score {g.score:.3f}, center {r(g.center)} m, approach {r(g.approach, 3)}, "
              f"width {g.width:.4f} m")
    for key, why in result.reasons.items():
        print(f"  {'no grasp' if key == 'scene' else f'object {key}: no grasp'}: {why}")
    compiled = " (includes compilation)" if timing["compiled"] else ""
    print(f"  timing: perception {timing['perception_s']:.3f} s, planning {timing['plan_s']:.3f} s (stage 1 "
          f"{timing['stage1_s']:.3f} s, stage 2 {timing['stage2_s']:.3f} s){compiled}, total {timing['total_s']:.3f} s")


def _cmd_example_frame(args: argparse.Namespace) -> int:
    import numpy as np
    from PIL import Image

    from envs import camera as camera_lib
    from envs import scene as scene_lib
    from envs import sensors
    from eval.benchmark import resolve_objects
    from eval.declutter import get_setting
    from sgjax.draw import draw_on_image
    from sgjax.utils.files import atomic_write_text

    if args.objects < 1:
        return _fail(f"--objects must be >= 1, got {args.objects}")
    try:
        assets, set_name, _ = resolve_objects(get_setting("seen-10"), objects=None if args.set == "seen" else args.set)
    except (ValueError, FileNotFoundError) as exc:  # an object set not prepared: sgjax objects prepare says how
        return _fail(_one_line(exc))
    # What a real camera sees around a table (floor, robot stand, wall): camera-only, the physics unchanged.
    scene = scene_lib.make_scene(assets, args.objects, args.seed, scene_lib.SceneConfig(surroundings=True))
    camera = camera_lib.CameraConfig()
    sensed = sensors.sense(scene, camera, args.camera, seed=args.seed)
    truth = sensed.truth
    depth_mm = np.clip(np.round(np.nan_to_num(sensed.depth) * 1000.0), 0, 65535).astype(np.uint16)
    ids = np.where(truth.labels >= 0, truth.labels + 1, 0)
    masks = ids.astype(np.uint8 if ids.max() < 256 else np.uint16)
    K = camera.pixel_intrinsic  # OpenCV's pixel convention, as a user's calibration gives it
    h, w = depth_mm.shape

    os.makedirs(args.dir, exist_ok=True)
    path = lambda name: os.path.join(args.dir, name)
    for name, array in (("depth.png", depth_mm), ("masks.png", masks)):
        atomic_write(path(name), lambda tmp, a=array: Image.fromarray(a).save(tmp, format="PNG"))
    atomic_write_text(path("intrinsics.json"), json.dumps({"K": K.tolist(), "width": w, "height": h}) + "\n")
    atomic_write_text(path("extrinsics.json"), json.dumps({"T": truth.extrinsic.tolist()}) + "\n")
    visible = [int(i) for i in np.unique(ids[ids > 0])]
    draw_on_image(path("picture.png"), depth_mm / 1000.0, K, labels_image=ids, cmap="viridis", tint=False,
                  title=f"{args.camera} depth, {len(visible)} object(s) of {set_name} (masks outlined)")
    names = {i: os.path.basename(str(scene.assets[i - 1].name)) for i in visible}
    print(f"wrote {args.dir}: depth.png (16-bit mm, {w}x{h}, {args.camera} camera), intrinsics.json, extrinsics.json "
          f"(camera-to-world), masks.png (ids 0 = background), picture.png")
    print("objects: " + ", ".join(f"{i} {n}" for i, n in names.items()))
    d = args.dir.rstrip("/") or "/"
    print(f"next: sgjax plan --depth {os.path.join(d, 'depth.png')} --intrinsics {os.path.join(d, 'intrinsics.json')}"
          f" --json   (add --extrinsics {os.path.join(d, 'extrinsics.json')} for world coordinates, "
          f"--masks {os.path.join(d, 'masks.png')} for these objects' masks)")
    return 0


def _cmd_declutter(args: argparse.Namespace) -> int:
    from eval.benchmark import result_json, run_benchmark
    from eval.declutter import DeclutterConfig
    from eval.methods import MethodUnavailable, check_method, uses_database
    from eval.protocol import with_preset
    from eval.report import percent

    options = {"model": args.model, "small_db": args.small_db}
    method = with_preset(args.method, args.preset)
    try:
        spec = _gripper(args)
        if spec != DeclutterConfig().gripper and uses_database(method):
            check_method(method, **options)  # an unknown method or option first, then the database build
            _prepare_database(spec, args.small_db)  # no shipped database for this gripper: built once, with a note
        with _warnings_as_notes():  # e.g. the method's checkpoint was trained for another gripper: one line
            result = run_benchmark(
                method,
                setting=args.setting,
                scenes=args.scenes,
                seed=args.seed,
                out=args.out,
                objects=args.objects,
                n_objects=args.n_objects,
                method_options=options,
                config=DeclutterConfig(backend=args.backend, remember_failures=not args.no_memory, sensor=args.camera,
                                       masks=args.masks, gripper=spec),
                pictures=args.pictures,
                progress=not args.quiet,
            )
    except (ValueError, MethodUnavailable, FileNotFoundError) as exc:  # UnknownMethod is a ValueError
        return _fail(str(exc))
    except KeyboardInterrupt:
        print(f"\ninterrupted: rerun the same command to continue with the scenes not logged in {args.out}", file=sys.stderr)
        return 130
    if args.json:
        print(result_json(result))
        return 0
    s = result.summary
    print(f"{result.method} on {result.setting} (seed {result.seed}): {s.scenes} scenes, {s.objects} objects")
    print(f"  GSR {percent(s.gsr)}  TSR {percent(s.tsr)}  GA {s.ga}  ({s.successes} successes, {s.cleared} scenes cleared)")
    t = result.timing["total_s"]
    if t[2]:
        print(f"  planning per grasp: {t[0]:.3f} ± {t[1]:.3f} s (stage 1 {result.timing['stage1_s'][0]:.3f} s, "
              f"stage 2 {result.timing['stage2_s'][0]:.3f} s)")
    print(f"  {result.ran} scene(s) run now, {result.resumed} resumed; tables: {result.tables['results.md']}")
    return 0


def _cmd_report_table(args: argparse.Namespace) -> int:
    """`sgjax table-i` and `sgjax table-ii`: the report path's table `args.table` (`eval.report_path`)."""
    from eval import report_path
    from eval.methods import MethodUnavailable

    methods = None if args.methods is None else [m.strip() for m in args.methods.split(",") if m.strip()]
    try:
        results, skipped = report_path.run_table(args.out, args.table, scenes=args.scenes, methods=methods,
                                                 progress=not args.quiet, camera=args.camera, masks=args.masks)
    except (ValueError, MethodUnavailable, FileNotFoundError) as exc:
        return _fail(str(exc))
    except KeyboardInterrupt:
        print(f"\ninterrupted: rerun the same command to continue in {args.out}", file=sys.stderr)
        return 130
    print(f"{len(results)} runs; tables in {os.path.join(args.out, 'results.md')}" +
          (f"; skipped: {'; '.join(skipped)}" if skipped else ""))
    return 0


def _cmd_baselines_setup(args: argparse.Namespace) -> int:
    from eval import cgn_setup

    prefix = args.prefix if args.prefix else cgn_setup.default_prefix()
    try:
        record = cgn_setup.setup(prefix, python=args.python, torch_index=args.torch_index, max_jobs=args.jobs)
    except (cgn_setup.SetupError, ValueError) as exc:
        return _fail(str(exc), code=1)
    except KeyboardInterrupt:
        print(f"\ninterrupted: rerun `{cgn_setup.COMMAND}` with the same --prefix to resume", file=sys.stderr)
        return 130
    if cgn_setup.installed_python() is not None and os.path.samefile(record["python"], cgn_setup.installed_python()):
        print("sgjax declutter --method contact-graspnet finds this environment by default")
    else:
        print(f"not the default location: export SGJAX_CGN_PYTHON={record['python']} for sgjax declutter to use it")
    return 0


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

    p = sub.add_parser("build-db", help="build the primitive database (templates + EMS fits) into the cache")
    p.add_argument("--small", action="store_true", help="a few dozen primitives (seconds), for tests and quick looks")
    p.add_argument("--out", help="write here instead of the cache directory ($SGJAX_CACHE)")
    p.add_argument("--workers", type=int, default=None, help="threads placing templates (default: cores)")
    p.add_argument("--force", action="store_true", help="rebuild even if the file exists")
    p.add_argument("--ship", action="store_true",
                   help="also write it compressed into the package (sgjax/models/primitive_db), the copy new users load")
    _add_gripper(p, "the gripper whose templates it holds: a preset or a .toml / .json gripper file (default: the "
                    "default gripper, whose database ships); another gripper's is built into the cache (~3 min on 2 cores)")
    p.set_defaults(func=_cmd_build_db)

    p = sub.add_parser("candidates", help="Stage-1 grasp candidates for one object cloud")
    p.add_argument("cloud", help="object cloud: .npy (N x 3, metres), .ply or .pcd")
    p.add_argument("--scene", help="scene cloud to avoid (other objects, the table)")
    p.add_argument("--viewpoint", type=float, nargs=3, metavar=("X", "Y", "Z"), help="camera position (default: origin)")
    p.add_argument("--db", help="a primitive database file (default: the cached default database)")
    p.add_argument("--small-db", action="store_true", help="use the small database (built in seconds)")
    p.add_argument("--top", type=int, default=10, help="grasps to print / draw (default 10)")
    p.add_argument("--json", action="store_true", help="print JSON")
    p.add_argument("--png", metavar="OUT.png", help="draw the cloud with the top grasps")
    p.add_argument("--seed", type=int, default=0)
    _add_gripper(p)
    p.set_defaults(func=_cmd_candidates)

    p = sub.add_parser(
        "plan",
        help="plan a grasp on a scene cloud or a depth image: Stage-1 candidates, E-RNet evaluation and refinement",
        description="Plan a grasp (SuperGrasp Stage 1 + Stage 2) on a scene cloud (sgjax plan CLOUD --mask MASK.npy) "
        "or on a depth image and its calibration (sgjax plan --depth D --intrinsics K: the table and the objects "
        "standing on it are found, grasps come back in the camera's frame, or the world's with --extrinsics; "
        "--json: one document, docs/real-camera.md). Exit status: 0 a grasp, 1 no grasp (the reason is printed), "
        "2 bad input (one line on stderr) or a missing model/database.",
    )
    p.add_argument("cloud", nargs="?", help="scene cloud: .npy (N x 3, metres), .ply or .pcd (the cloud form; "
                   "or give --depth)")
    p.add_argument(
        "--mask", help="the cloud form: .npy, one entry per point: bool (the target) or int object labels (< 0: background)"
    )
    p.add_argument("--viewpoint", type=float, nargs=3, metavar=("X", "Y", "Z"),
                   help="the cloud form: camera position (default: origin)")
    p.add_argument("--depth", metavar="D", help="the depth form: a depth image, 16-bit PNG (see --depth-scale) or float "
                   ".npy/.npz in metres; 0 or NaN: no depth")
    p.add_argument("--intrinsics", metavar="K", help="the depth form: the camera's intrinsics, JSON {\"K\": 3x3} or "
                   "{fx, fy, cx, cy} (+ width, height), ROS CameraInfo YAML or a 3x3 .npy (OpenCV convention)")
    p.add_argument("--depth-scale", type=float, metavar="S", help="a depth PNG's units per metre (default 1000: mm)")
    p.add_argument("--extrinsics", metavar="T", help="camera-to-world 4x4 (.json: a list or {\"T\": ...}; .npy): plan and "
                   "answer in world coordinates (default: the camera's, x right, y down, z forward)")
    p.add_argument("--masks", metavar="M", help="instance ids per pixel (PNG or .npy, 0 = background): the objects "
                   "(default: found by segmenting what stands on the table)")
    p.add_argument("--workspace-mask", metavar="W", help="pixels to use (PNG or .npy, nonzero = in)")
    p.add_argument("--all-objects", action="store_true", help="the depth form: a grasp for every object (default: the best one)")
    p.add_argument("--top", type=int, metavar="K",
                   help="the depth form: up to K grasps per planned object, the chosen one and K-1 alternatives (default 1)")
    p.add_argument("--model", metavar="RUN_DIR", help="an E-RNet `sgjax train` run directory (default: the one shipped "
                   "for the gripper); none: no network, Stage 1's order (better than another gripper's E-RNet, "
                   "docs/grippers.md)")
    p.add_argument("--preset", default="default", choices=preset_names(),
                   help="the planner's named configuration (sgjax.presets; default: today's SuperGrasp)")
    p.add_argument("--db", help="a primitive database file (default: the cached default database)")
    p.add_argument("--small-db", action="store_true", help="use the small database (built in seconds)")
    p.add_argument("--json", action="store_true", help="print the plan as one JSON document")
    p.add_argument("--png", metavar="OUT.png", help="draw the grasps: on the cloud (cloud form), on the image and the "
                   "cloud (depth form)")
    p.add_argument("--seed", type=int, default=0)
    _add_gripper(p, GRIPPER_HELP + "; a gripper other than the default one builds its primitive database into the "
                 "cache on first use (~3 min on 2 cores), and --model should be trained for it (else a warning)")
    p.set_defaults(func=_cmd_plan)

    p = sub.add_parser(
        "example-frame",
        help="write a simulated depth frame to try `sgjax plan --depth` on: depth, intrinsics, extrinsics, masks, picture",
        description="Drop objects of the seen set on a simulated table (with a floor, a robot stand and a wall around "
        "it), render the default camera and write DIR/depth.png (16-bit, millimetres), DIR/intrinsics.json "
        "({\"K\", \"width\", \"height\"}, OpenCV convention), DIR/extrinsics.json (camera-to-world), DIR/masks.png "
        "(instance ids, 0 = background) and DIR/picture.png.",
    )
    p.add_argument("dir", metavar="DIR", help="output folder (created)")
    p.add_argument("--camera", default="exact", choices=SENSORS,
                   help="the depth: exact (default) or a sensor model's (envs.sensors: kinect, realsense, stereo)")
    p.add_argument("--objects", type=int, default=6, metavar="N", help="objects dropped on the table (default 6)")
    p.add_argument("--set", default="seen", metavar="NAME",
                   help="the object set (default seen, the seen-10 benchmark's; tiny: five solids, built in seconds) "
                   "or a folder of meshes")
    p.add_argument("--seed", type=int, default=0, metavar="S", help="the scene's and the sensor noise's seed")
    p.set_defaults(func=_cmd_example_frame)

    objects_parser = sub.add_parser("objects", help="object sets for simulation: prepare (cached) and list")
    objects_sub = objects_parser.add_subparsers(dest="objects_command", required=True)
    for command, func, help_text in (
        ("prepare", _cmd_objects_prepare, "clean, centre, simplify and decompose an object set (cached)"),
        ("list", _cmd_objects_list, "print the prepared objects of a set: name, extents, mass, hulls"),
    ):
        p = objects_sub.add_parser(command, help=help_text)
        which = p.add_mutually_exclusive_group()
        which.add_argument(
            "--set",
            default="all",
            help="tiny | ycb | ycb-seen | ycb-unseen | procedural | seen | unseen | all (default: all)",
        )
        which.add_argument("--objects", metavar="DIR", help="a folder of .obj/.stl/.ply meshes in metres")
        p.set_defaults(func=func)
        if command == "prepare":
            p.add_argument("--workers", type=int, default=1, help="parallel processes (default 1)")
            p.add_argument("--retry-failed", action="store_true", help="retry meshes that failed before")
            p.add_argument("--quiet", action="store_true", help="no progress bar")
        else:
            p.add_argument("--json", action="store_true", help="one JSON object per line")

    p = sub.add_parser(
        "train", help="train E-RNet on labelled grasp shards, or rebuild a shipped checkpoint from its recipe (resumes)"
    )
    recipe_group = p.add_mutually_exclusive_group()
    recipe_group.add_argument(
        "--recipe", default=None, metavar="NAME|FILE",
        help="label and train as a recipe says (train/recipes/NAME.toml or a .toml file): the label sets into "
        "$SGJAX_CACHE/labels/<set>, the run into --out (default runs/<recipe>); no other training option goes with it",
    )
    recipe_group.add_argument("--list-recipes", action="store_true",
                              help="print the shipped recipes: network, label scenes, epochs, estimated CPU hours")
    p.add_argument("--tiny", action="store_true",
                   help="with --recipe: the same recipe at test size (2 scenes per set, the tiny network, 1 epoch; label "
                   "sets <set>-tiny, default --out runs/<recipe>-tiny)")
    p.add_argument("--data", default=None, nargs="+", metavar="DIR",
                   help="directories of .npz sample shards (train/dataset.py format); several must hold disjoint scenes")
    p.add_argument("--out", default=None, help="run directory: checkpoints/, metrics.json/.csv, curves.png")
    p.add_argument("--epochs", type=int, default=None, help="default 100")
    p.add_argument("--batch-size", type=int, default=None, help="default 128")
    p.add_argument("--lr", type=float, default=None, help="default 1e-3")
    p.add_argument("--weight-decay", type=float, default=None, help="default 3e-4")
    p.add_argument("--decoupled-weight-decay", action="store_true", default=None,
                   help="AdamW instead of Adam + L2 (the paper)")
    p.add_argument(
        "--lr-decay-epochs", type=int, default=None, metavar="N",
        help="lower the learning rate along a half cosine to 0 over the last N epochs (default 0: constant, the "
        "paper); a resumed run may add it",
    )
    p.add_argument("--held-out", type=float, default=None, help="fraction of scenes held out (default 0.1)")
    p.add_argument(
        "--devices", type=int, default=None, metavar="N",
        help="data-parallel training on the first N JAX devices: each batch is split over them (--batch-size must be "
        "divisible by N), parameters and optimiser state are replicated; a run resumes on any N. On a CPU, "
        "XLA_FLAGS=--xla_force_host_platform_device_count=N splits the host into N devices (default 1)",
    )
    p.add_argument(
        "--model", choices=("light", "paper", "tiny"), default=None, help="network size (light: CPU default; tiny: smoke tests)"
    )
    p.add_argument(
        "--network", choices=("ernet", "pointnetgpd"), default=None,
        help="ernet (default) or the PointNetGPD baseline (trained on the same shards, `label` only)",
    )
    p.add_argument(
        "--hand-points", type=int, default=None, metavar="N",
        help="E-RNet also sees N points of the hand's swept volume (fingers, palm, the last 5 cm of the approach); "
        "0: the paper's input, the enlarged region only",
    )
    p.add_argument("--seed", type=int, default=None, help="default 0")
    p.add_argument("--synthetic", type=int, default=None, metavar="N", help="first write N synthetic samples to --data")
    p.add_argument(
        "--init", default=None, metavar="RUN_DIR",
        help="start from the latest weights of this `sgjax train` run (same --network, --model and --hand-points; "
        "its optimiser state is not used), e.g. to go on training a checkpoint on more data",
    )
    p.add_argument("--quiet", action="store_true", help="no progress bar or per-epoch lines")
    _add_gripper(p, "the gripper the labels of --data were made for (`sgjax label --gripper`): checked against the "
                 "data's label_config.json; the run takes the data's gripper, recorded in its checkpoints' meta")
    p.set_defaults(func=_cmd_train)

    p = sub.add_parser(
        "score-data",
        help="judge a trained scorer on a labelled directory: AUC overall and per source, calibration, collisions' scores",
    )
    p.add_argument("--data", required=True, nargs="+", metavar="DIR",
                   help="labelled directories (sgjax label --out); several must hold disjoint scenes")
    p.add_argument("--model", default=None, help="a `sgjax train` run directory (default: the shipped checkpoint)")
    p.add_argument("--network", choices=("ernet", "pointnetgpd"), default="ernet")
    p.add_argument("--batch-size", type=int, default=128)
    p.add_argument(
        "--held-out", type=float, default=None, metavar="FRACTION",
        help="only the scenes a `sgjax train --held-out FRACTION --seed SEED` run holds out of these directories "
        "(and the held-out objects): compares runs trained on different data on scenes none trained on",
    )
    p.add_argument("--seed", type=int, default=0, help="the training runs' --seed (with --held-out)")
    p.add_argument("--resamples", type=int, default=1000, metavar="N",
                   help="scene draws behind the 95 %% intervals of AUC and of the top grasp's success (0: none)")
    p.add_argument("--json", action="store_true", help="print every metric as JSON")
    p.set_defaults(func=_cmd_score_data)

    p = sub.add_parser("label", help="label grasps in simulated scenes for E-RNet training (resumable)")
    p.add_argument(
        "--scenes", required=True, metavar="N|A:B",
        help="scenes 0..N-1, or A..B-1 with A:B (rerun with a larger N to extend)",
    )
    p.add_argument(
        "--first-scene", type=int, default=None, metavar="S",
        help="label scenes S..N-1 only: continue a series in a new directory (train reads several); --scenes S:N says the same",
    )
    p.add_argument(
        "--shard", default=None, metavar="K/N",
        help="worker K of N of a job array sharing --out (e.g. $SLURM_ARRAY_TASK_ID/$SLURM_ARRAY_TASK_COUNT): "
        "label only blocks b of scenes_per_shard scenes with b mod N = K; together the N write one serial run's files",
    )
    p.add_argument(
        "--ray", nargs="?", const="", default=None, metavar="ADDRESS",
        help='label on Ray actors: a local cluster on this machine\'s cores, or ray.init(address=ADDRESS) ("auto", '
        '"ray://HEAD:10001"); --out must be reachable by every worker (pip install -e ".[distributed]")',
    )
    p.add_argument("--workers", type=int, default=None, help="Ray workers (default: the cluster's CPUs // --threads)")
    p.add_argument("--out", required=True, help="directory of .npz shards (train/dataset.py format)")
    p.add_argument("--objects", default="seen", help="object set name or a folder of meshes (default: seen)")
    p.add_argument("--backend", default="cpu", help=BACKEND_HELP)
    p.add_argument("--camera", default="exact", choices=SENSORS,
                   help="the depth the samples see: exact (default) or a sensor model's, through the front end of a "
                        "real frame with perfect masks (envs.sensors), for a network that meets a real camera")
    p.add_argument("--n-objects", type=int, default=5, help="objects per scene (paper: 5)")
    p.add_argument("--targets-per-scene", type=int, default=2, help="objects whose grasps are executed per scene")
    p.add_argument(
        "--per-source", default=None, metavar="SOURCE=N,...",
        help="grasps per target from each candidate source (default stage1=8,stage1_paper=8,gpd=8,perturbed=8; "
        "each executed with its 3 refinements)",
    )
    p.add_argument(
        "--held-out-objects", default=None, metavar="NAME,...",
        help="objects never trained on, only in every 20th scene (default: 4 seen objects with --objects seen, "
        "none otherwise; 'none' for none)",
    )
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--small-db", action="store_true", help="the small primitive database (tests, quick runs)")
    p.add_argument("--threads", type=int, default=0, help="simulation threads (default: all cores; with --ray: per worker, default 1)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    _add_gripper(p, GRIPPER_HELP + "; the simulated gripper, Stage 1 and the crops follow it, and label_config.json "
                 "records it whole (a directory resumes only with the same gripper)")
    p.set_defaults(func=_cmd_label)
    p = sub.add_parser(
        "declutter",
        help="decluttering benchmark in simulation (paper Table I): GSR, TSR, GA over N scenes; resumable",
    )
    p.add_argument("--setting", default="seen-10", help="seen-10 | seen-20 | unseen-10 (Table I) | real-similar | real-novel (Table II re-created: the "
                   "ag-105-145 gripper, stereo depth, segmented masks) (default seen-10)")
    p.add_argument("--scenes", type=int, default=30, help="scenes to run (paper: 30)")
    p.add_argument(
        "--method",
        required=True,
        help="supergrasp | supergrasp-norefine | supergrasp-pointnetgpd | supergrasp-stage1 | gpd | pointnetgpd | s1+pointnetgpd | "
        "gpd+s2 | "
        "contact-graspnet | "
        "oracle-topdown (diagnostic, reads ground truth)",
    )
    p.add_argument("--objects", metavar="DIR", help="a folder of meshes (or an object set name) instead of the setting's")
    p.add_argument("--n-objects", type=int, help="objects per scene instead of the setting's (smoke runs)")
    p.add_argument("--seed", type=int, default=0, help="scene seeds derive from it: same seed, same scenes for every method")
    p.add_argument("--out", default="declutter_results", help="logs, pictures, results.md/.csv (default declutter_results)")
    p.add_argument(
        "--model", metavar="RUN_DIR",
        help="the method's network run directory: E-RNet (supergrasp*, gpd+s2) or PointNetGPD (*pointnetgpd)",
    )
    p.add_argument(
        "--preset", default="default", choices=preset_names(),
        help="supergrasp*: the planner's named configuration (sgjax.presets: default = today's SuperGrasp, "
             "paper = the paper's plain one); logs and tables name it as METHOD@PRESET",
    )
    p.add_argument("--small-db", action="store_true", help="the small primitive database (Stage-1 methods; tests)")
    p.add_argument("--backend", default="cpu", help=BACKEND_HELP)
    p.add_argument("--camera", default="exact", choices=SENSORS,
                   help="the depth the method sees: exact (default) or a sensor model's (envs.sensors), through the "
                        "front end of a real frame (sgjax.perception)")
    p.add_argument("--masks", default="truth", choices=MASKS,
                   help="objects from the true instance masks (default) or from clustering the points above the table")
    p.add_argument("--pictures", type=int, default=3, help="draw the first this many scenes (default 3)")
    p.add_argument(
        "--no-memory", action="store_true",
        help="do not hand the method the grasps that already failed in the scene (by default it leaves them out)",
    )
    p.add_argument("--json", action="store_true", help='print {"GSR", "TSR", "GA", "scenes", ...} as JSON')
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    _add_gripper(p, GRIPPER_HELP + "; the simulated gripper and the method's are this one (logs record it)")
    p.set_defaults(func=_cmd_declutter)

    from eval.report_path import TABLE_I, TABLE_II  # light: names and settings

    for command, table, what in (
        ("table-i", TABLE_I, "Every Table I method on seen-10, seen-20 and the sealed unseen objects"),
        ("table-ii", TABLE_II, ("Table II re-created in simulation (the ag-105-145 gripper, stereo depth, segmented "
                                "masks): its methods on real-similar and on real-novel with the sealed objects")),
    ):
        p = sub.add_parser(
            command,
            help=f"the report: {table.name} on a reserved seed, the unseen objects sealed ones (resumable)",
            description=f"{what}, on a seed reserved for reporting (envs/sealed.py): numbers no decision saw. "
            "Run it to report, never to decide.",
        )
        p.add_argument("--out", required=True, help="results directory (logs, results.md; rerun to continue)")
        p.add_argument("--scenes", type=int, default=30, help="scenes per setting (default 30)")
        p.add_argument("--methods", default=None, metavar="M,...",
                       help=f"a subset of the methods ({', '.join(table.methods)}), in this order")
        p.add_argument("--camera", default=None, choices=SENSORS,
                       help="the depth the methods see (envs.sensors; default: the settings' own, exact for Table I)")
        p.add_argument("--masks", default=None, choices=MASKS,
                       help="objects from the true masks or from segmentation (default: the settings' own, truth for Table I)")
        p.add_argument("--quiet", action="store_true", help="no progress bars")
        p.set_defaults(func=_cmd_report_table, table=table)

    baselines_parser = sub.add_parser("baselines", help="set up the environments of out-of-process baselines")
    baselines_sub = baselines_parser.add_subparsers(dest="baselines_command", required=True)
    p = baselines_sub.add_parser(
        "setup", help="create a baseline's own Python environment from PyPI (safe to rerun: resumes, skips what is there)",
        description="Create Contact-GraspNet's environment (python3.11 venv: torch 2.13.0 CPU, numpy<2, "
        "torch-geometric 2.4.0, torch-cluster 1.6.3 built from source, cgn-pytorch 0.4.3), then check that it "
        "loads its checkpoint. Takes ~15 min on 2 cores, most of it building torch-cluster.",
    )
    p.add_argument("baseline", choices=("contact-graspnet",), help="the baseline to set up")
    p.add_argument("--prefix", metavar="DIR",
                   help="where the venv goes (default: $SGJAX_CACHE/envs/contact-graspnet, found without settings; "
                   "elsewhere, set SGJAX_CGN_PYTHON=DIR/bin/python)")
    p.add_argument("--python", default="python3.11", help="the Python 3.11 that creates the venv (default python3.11)")
    p.add_argument("--torch-index", metavar="URL",
                   help="an extra index for torch, e.g. https://download.pytorch.org/whl/cpu where PyPI's torch is a CUDA build")
    p.add_argument("--jobs", type=int, default=2, help="compile jobs building torch-cluster (MAX_JOBS, default 2)")
    p.set_defaults(func=_cmd_baselines_setup)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    from sgjax.utils.cache import enable_compilation_cache

    enable_compilation_cache()  # every command is a new process: reuse what earlier ones compiled
    from sgjax.utils import exported

    try:
        code = args.func(args)
    finally:
        exported.end_group()  # what a caller of main([...]) calls next is not the command's to prefetch
    if argv is None and args.func is _cmd_plan:
        _end_process(code)
    return code


def _end_process(code: int) -> None:
    """End a `sgjax plan` process (the command line's, not a caller's `main([...])`) at once: its output
    flushed and the programs it was still loading in the background done, without Python's teardown of
    XLA's executables and modules (~0.5 s of a ~5 s command on 2 cores, docs/real-camera.md). plan
    writes its files (cache entries, --png) before it returns, each atomically."""
    import logging

    from sgjax.utils import exported

    exported.settle()
    logging.shutdown()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)

