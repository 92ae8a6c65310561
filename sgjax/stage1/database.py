"""The primitive database: ~1.2k standard primitives, their superquadrics and template grasps.

Paper Sec. IV-B: primitives of four families over a grid of shapes and proportional scalings, each
with family-specific template grasps (`sgjax.stage1.primitives`) and superquadric coefficients fitted with our
EMS on full surface samples. Grasps are stored in each primitive's canonical superquadric frame and
closed under that frame's flips (`sgjax.stage1.primitives.symmetrize`), so transferring them to a query is
one matrix product (`sgjax.stage1.matching.transfer_grasps`).

The database is one versioned `.npz` file in the cache directory (`$SGJAX_CACHE/primitive_db/`),
named by the format version and a hash of the build configuration; building is deterministic.
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
import hashlib
import json
import os
from pathlib import Path

import numpy as np

from sgjax.utils.cache import cache_dir
from sgjax.utils.files import atomic_write
from sgjax.geometry.gripper import GripperSpec
from sgjax.stage1.primitives import (
    FAMILIES,
    Primitive,
    TemplateConfig,
    surface_points,
    symmetrize,
    template_grasps,
)
from sgjax.geometry.superquadric import pose_matrix

FORMAT_VERSION = 1  # the file layout
BUILD_VERSION = 1  # bump when template placement or fitting changes: old cached files are then not reused


@dataclasses.dataclass(frozen=True)
class DBConfig:
    """The grid of shapes and scalings. Ratios are relative to the primitive's longest extent.

    scales: longest extent of each proportional scaling (metres).
    cuboid_ratios: candidate ratios for the two shorter edges (every pair r2 >= r3 is used).
    cylinder_aspects: height / diameter.
    elliptical_ratios: r_y / r_x;  elliptical_aspects: height / (2 r_x).
    frustum_ratios: r_top / r_bottom (upside-down frusta are covered by the frame flips);
    frustum_aspects: height / (2 r_bottom).
    min_templates: primitives with fewer surviving templates (e.g. too large to grasp) are left out.
    """

    scales: tuple[float, ...] = tuple(np.round(np.geomspace(0.03, 0.25, 23), 5))
    cuboid_ratios: tuple[float, ...] = (0.15, 0.25, 0.4, 0.6, 0.8, 1.0)
    cylinder_aspects: tuple[float, ...] = (0.15, 0.25, 0.4, 0.6, 0.8, 1.0, 1.3, 1.7, 2.2, 3.0, 4.0)
    elliptical_ratios: tuple[float, ...] = (0.4, 0.6, 0.8)
    elliptical_aspects: tuple[float, ...] = (0.3, 0.6, 1.0, 1.5, 2.5, 4.0)
    frustum_ratios: tuple[float, ...] = (0.3, 0.5, 0.7, 0.85)
    frustum_aspects: tuple[float, ...] = (0.4, 0.8, 1.2, 2.0, 3.0)
    templates: TemplateConfig = TemplateConfig()
    spec: GripperSpec = GripperSpec()
    min_templates: int = 20
    fit_points: int = 1024
    seed: int = 0

    @classmethod
    def small(cls) -> DBConfig:
        """A few dozen primitives of every family, built in seconds (for tests and quick looks)."""
        return cls(
            scales=(0.05, 0.09, 0.15),
            cuboid_ratios=(0.3, 0.6, 1.0),
            cylinder_aspects=(0.5, 1.0, 2.5),
            elliptical_ratios=(0.6,),
            elliptical_aspects=(0.6, 1.5),
            frustum_ratios=(0.5,),
            frustum_aspects=(0.8, 2.0),
        )

    @classmethod
    def for_gripper(cls, spec: GripperSpec, small: bool = False) -> DBConfig:
        """The full grid (or `small`'s) for gripper `spec`: its templates and widths are that gripper's, and
        so is the cache key (the default gripper's database ships; another's is built on first use)."""
        return dataclasses.replace(cls.small() if small else cls(), spec=spec)

    def key(self) -> str:
        """A short hash of everything that changes the database's content."""
        text = json.dumps([FORMAT_VERSION, BUILD_VERSION, dataclasses.asdict(self)], sort_keys=True, default=str)
        return hashlib.sha256(text.encode()).hexdigest()[:12]


def database_shapes(cfg: DBConfig) -> list[Primitive]:
    """Every grid primitive before the template-count cut, in a fixed order."""
    shapes = []
    for s in cfg.scales:
        for i, r2 in enumerate(cfg.cuboid_ratios):
            for r3 in cfg.cuboid_ratios[: i + 1]:
                shapes.append(Primitive("cuboid", (s, s * r2, s * r3)))
        for aspect in cfg.cylinder_aspects:
            d, h = _diameter_height(s, aspect)
            shapes.append(Primitive("cylinder", (d, d, h)))
        for ratio in cfg.elliptical_ratios:
            for aspect in cfg.elliptical_aspects:
                d, h = _diameter_height(s, aspect)
                shapes.append(Primitive("elliptical_cylinder", (d, d * ratio, h)))
        for ratio in cfg.frustum_ratios:
            for aspect in cfg.frustum_aspects:
                d, h = _diameter_height(s, aspect)
                shapes.append(Primitive("frustum", (d, d * ratio, h)))
    return shapes


def _diameter_height(longest: float, aspect: float) -> tuple[float, float]:
    """(diameter, height) with height / diameter = aspect and the larger of the two = longest."""
    return (longest, longest * aspect) if aspect <= 1.0 else (longest / aspect, longest)


@dataclasses.dataclass
class PrimitiveDB:
    """The database in host memory. P primitives, G grasps in all.

    family: [P] int index into FAMILIES;  dims: [P, 3] (see `sgjax.stage1.primitives`);
    sq_scale [P, 3], sq_epsilon [P, 2], sq_rotation [P, 3, 3], sq_translation [P, 3]: the canonical EMS
    fit in the primitive's own frame (T_sq^c);  fit_inlier_ratio [P];
    grasp_offsets [P + 1]: primitive i owns grasps[grasp_offsets[i]:grasp_offsets[i + 1]];
    grasps [G, 4, 4]: template poses in the primitive's superquadric frame;  widths [G];
    template_ids [G]: index of the template within its primitive.
    """

    family: np.ndarray
    dims: np.ndarray
    sq_scale: np.ndarray
    sq_epsilon: np.ndarray
    sq_rotation: np.ndarray
    sq_translation: np.ndarray
    fit_inlier_ratio: np.ndarray
    grasp_offsets: np.ndarray
    grasps: np.ndarray
    widths: np.ndarray
    template_ids: np.ndarray
    config_key: str
    config_json: str

    def __len__(self) -> int:
        return len(self.family)

    @property
    def num_grasps(self) -> np.ndarray:
        """Grasps per primitive [P]."""
        return np.diff(self.grasp_offsets)

    def primitive(self, i: int) -> Primitive:
        return Primitive(FAMILIES[int(self.family[i])], tuple(self.dims[i]))

    def sq_pose(self, i: int) -> np.ndarray:
        """T_sq^c of primitive i: its superquadric frame in the primitive's own frame [4, 4]."""
        return np.asarray(pose_matrix(self.sq_rotation[i], self.sq_translation[i]), np.float64)

    def grasps_of(self, i: int, frame: str = "superquadric") -> tuple[np.ndarray, np.ndarray]:
        """(poses [T, 4, 4], widths [T]) of primitive i in its "superquadric" or "object" frame."""
        lo, hi = self.grasp_offsets[i], self.grasp_offsets[i + 1]
        poses = self.grasps[lo:hi].astype(np.float64)
        if frame == "object":
            poses = self.sq_pose(i) @ poses
        elif frame != "superquadric":
            raise ValueError(f"frame must be 'superquadric' or 'object', got {frame!r}")
        return poses, self.widths[lo:hi].astype(np.float64)

    def padded_grasps(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Grasps padded per primitive for jit: (poses [P, Gmax, 4, 4], widths [P, Gmax], mask [P, Gmax])."""
        counts = self.num_grasps
        g_max = int(counts.max())
        mask = np.arange(g_max)[None, :] < counts[:, None]
        poses = np.tile(np.eye(4, dtype=np.float32), (len(self), g_max, 1, 1))
        widths = np.zeros((len(self), g_max), np.float32)
        poses[mask] = self.grasps
        widths[mask] = self.widths
        return poses, widths, mask

    def summary(self) -> dict:
        """Counts per family and grasp statistics (for the CLI and the README)."""
        counts = self.num_grasps
        return {
            "primitives": len(self),
            "per_family": {f: int(np.sum(self.family == k)) for k, f in enumerate(FAMILIES)},
            "grasps": int(counts.sum()),
            "grasps_per_primitive": {"min": int(counts.min()), "mean": float(counts.mean()), "max": int(counts.max())},
            "config_key": self.config_key,
        }


# ---------------------------------------------------------------------------------------------
# Building.


def _templates_job(args: tuple[Primitive, GripperSpec, TemplateConfig, int]) -> tuple[np.ndarray, np.ndarray]:
    p, spec, tcfg, seed = args
    poses, widths = template_grasps(p, spec, tcfg, seed=seed)
    return poses.astype(np.float32), widths.astype(np.float32)


def _all_templates(shapes: list[Primitive], cfg: DBConfig, workers: int, progress: bool) -> list:
    from tqdm import tqdm

    jobs = [(p, cfg.spec, cfg.templates, cfg.seed + i) for i, p in enumerate(shapes)]
    bar = tqdm(total=len(jobs), desc="templates", unit="prim", disable=not progress)
    if workers <= 1:
        out = []
        for job in jobs:
            out.append(_templates_job(job))
            bar.update()
    else:
        # Threads, not processes: the work is large NumPy array operations that release the GIL, and
        # processes would need fork (unsafe with JAX loaded) or spawn (re-imports the user's script).
        with concurrent.futures.ThreadPoolExecutor(workers) as pool:
            out = []
            for result in pool.map(_templates_job, jobs):
                out.append(result)
                bar.update()
    bar.close()
    return out


def _fit_primitives(shapes: list[Primitive], cfg: DBConfig, progress: bool):
    """Canonical EMS fits of every primitive's full surface: FitResult batched [P]."""
    import jax
    from tqdm import tqdm

    from sgjax.stage1.ems import fit_superquadrics

    clouds = np.stack([surface_points(p, cfg.fit_points, seed=cfg.seed + 100_000 + i) for i, p in enumerate(shapes)])
    # Two compiled batch sizes in all, the last chunk padded with copies: how many primitives keep enough
    # templates depends on the gripper, and a batch of each count would compile EMS anew (~16 s a size).
    chunk = 256 if len(shapes) > 64 else 64
    results = []
    for start in tqdm(range(0, len(shapes), chunk), desc="superquadrics", unit="batch", disable=not progress):
        part = clouds[start : start + chunk]
        n = len(part)
        if n < chunk:
            part = np.concatenate([part, np.repeat(part[-1:], chunk - n, 0)])
        fit = fit_superquadrics(part.astype(np.float32))
        results.append(jax.tree_util.tree_map(lambda x, n=n: np.asarray(x)[:n], fit))
    return jax.tree_util.tree_map(lambda *xs: np.concatenate(xs), *results)


def _cap(poses: np.ndarray, widths: np.ndarray, cap: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Symmetrize, thinning the source templates evenly until the closed set has at most `cap` grasps.

    Returns (poses, widths, template ids) where the id is the grasp's index in the closed set.
    """
    stride = 1
    while True:
        sym_poses, sym_widths = symmetrize(poses[::stride], widths[::stride])
        if len(sym_poses) <= cap:
            return sym_poses, sym_widths, np.arange(len(sym_poses), dtype=np.int32)
        stride += 1


def build_database(cfg: DBConfig = DBConfig(), workers: int | None = None, progress: bool = True) -> PrimitiveDB:
    """Build the database (deterministic in cfg). `workers` threads place the templates (default: cores)."""
    shapes = database_shapes(cfg)
    workers = (os.cpu_count() or 1) if workers is None else workers
    templates = _all_templates(shapes, cfg, workers, progress)
    keep = [i for i, (poses, _) in enumerate(templates) if len(poses) >= cfg.min_templates]
    shapes = [shapes[i] for i in keep]
    templates = [templates[i] for i in keep]
    fit = _fit_primitives(shapes, cfg, progress)

    from tqdm import tqdm

    rows, grasps, widths, ids, counts = [], [], [], [], []
    # Closing each set under the frame flips takes about as long as placing the templates: show it.
    for i, (poses, w) in enumerate(tqdm(templates, desc="frame symmetries", unit="prim", disable=not progress)):
        if not fit.valid[i]:
            continue
        sq_pose = np.asarray(pose_matrix(fit.rotation[i], fit.translation[i]), np.float64)
        in_sq = np.linalg.inv(sq_pose) @ poses.astype(np.float64)
        sym_poses, sym_widths, tid = _cap(in_sq, w.astype(np.float64), cfg.templates.max_templates)
        rows.append(i)
        grasps.append(sym_poses.astype(np.float32))
        widths.append(sym_widths.astype(np.float32))
        ids.append(tid)
        counts.append(len(sym_poses))
    rows = np.asarray(rows)
    return PrimitiveDB(
        family=np.asarray([FAMILIES.index(shapes[i].family) for i in rows], np.int8),
        dims=np.asarray([shapes[i].dims for i in rows], np.float32),
        sq_scale=fit.scale[rows].astype(np.float32),
        sq_epsilon=fit.epsilon[rows].astype(np.float32),
        sq_rotation=fit.rotation[rows].astype(np.float32),
        sq_translation=fit.translation[rows].astype(np.float32),
        fit_inlier_ratio=fit.inlier_ratio[rows].astype(np.float32),
        grasp_offsets=np.concatenate([[0], np.cumsum(counts)]).astype(np.int64),
        grasps=np.concatenate(grasps),
        widths=np.concatenate(widths),
        template_ids=np.concatenate(ids),
        config_key=cfg.key(),
        config_json=json.dumps(dataclasses.asdict(cfg), default=str),
    )


# ---------------------------------------------------------------------------------------------
# Files.

_ARRAYS = [f.name for f in dataclasses.fields(PrimitiveDB) if f.name not in ("config_key", "config_json")]


def default_path(cfg: DBConfig = DBConfig()) -> Path:
    """Where the database for `cfg` lives in the cache directory."""
    return cache_dir("primitive_db") / _file_name(cfg)


def save_database(db: PrimitiveDB, path: str | os.PathLike, compressed: bool = False) -> None:
    """Write the database atomically as one .npz (with its format version and config); `compressed`
    for the copy that ships with the package."""
    arrays = {name: getattr(db, name) for name in _ARRAYS}
    meta = np.asarray(json.dumps({"version": FORMAT_VERSION, "config_key": db.config_key, "config": db.config_json}))
    write = np.savez_compressed if compressed else np.savez
    atomic_write(path, lambda tmp: write(tmp, meta=meta, **arrays))


class _Outdated(ValueError):
    pass


def load_database_file(path: str | os.PathLike) -> PrimitiveDB:
    """Read a database file; raises ValueError naming the problem for a bad or outdated file."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no primitive database at {path} (build one with `sgjax build-db`)")
    try:
        with np.load(path, allow_pickle=False) as data:
            meta = json.loads(str(data["meta"]))
            if meta.get("version") != FORMAT_VERSION:
                raise _Outdated(
                    f"{path} has database format v{meta.get('version')}, this sgjax reads v{FORMAT_VERSION}; "
                    "rebuild it with `sgjax build-db`"
                )
            arrays = {name: data[name] for name in _ARRAYS}
    except _Outdated:
        raise
    except Exception as exc:  # zip, key and JSON errors all mean the same thing to the user
        raise ValueError(f"{path} is not a readable primitive database: {exc}") from exc
    return PrimitiveDB(**arrays, config_key=meta["config_key"], config_json=meta["config"])


# The default database ships with the package (3.7 MB compressed; building it takes ~3 min on 2 cores),
# so a new user's first run does not wait for it. Its name carries the config key, which hashes
# FORMAT_VERSION, BUILD_VERSION and DBConfig: any change to them makes the shipped file not match, and
# the database is built into the cache as before. Refresh it with `sgjax build-db --ship`.
SHIPPED_DIR = Path(__file__).resolve().parent.parent / "models" / "primitive_db"


def shipped_path(cfg: DBConfig = DBConfig()) -> Path:
    """Where a shipped copy of the database for `cfg` would be (only the default config ships)."""
    return SHIPPED_DIR / _file_name(cfg)


def _file_name(cfg: DBConfig) -> str:
    return f"primitive_db-v{FORMAT_VERSION}-{cfg.key()}.npz"


def ship_database(db: PrimitiveDB, cfg: DBConfig = DBConfig()) -> Path:
    """Write `db` (built for `cfg`) compressed into the package's shipped folder, replacing older ones."""
    if db.config_key != cfg.key():
        raise ValueError(f"database was built for config {db.config_key}, not {cfg.key()}")
    SHIPPED_DIR.mkdir(parents=True, exist_ok=True)
    path = shipped_path(cfg)
    for old in SHIPPED_DIR.glob("primitive_db-*.npz"):
        if old != path:
            old.unlink()
    save_database(db, path, compressed=True)
    return path


def load_database(
    cfg: DBConfig = DBConfig(), path: str | os.PathLike | None = None, build: bool = True, progress: bool = True
) -> PrimitiveDB:
    """The database for `cfg`: from `path`, else the cache, else the copy shipped with the package (the
    default config), else built and saved into the cache first (if `build`)."""
    if path is None:
        path = default_path(cfg)
        if not path.is_file() and shipped_path(cfg).is_file():
            return load_database_file(shipped_path(cfg))
    path = Path(path)
    if not path.is_file() and build:
        save_database(build_database(cfg, progress=progress), path)
    return load_database_file(path)
