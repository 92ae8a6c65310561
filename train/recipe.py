"""Recipes: a shipped checkpoint rebuilt end to end from one file (`sgjax train --recipe NAME`).

A recipe (train/recipes/NAME.toml, package data) names the label sets a network is trained on and the
training settings:

    name, network ("ernet" | "pointnetgpd"), description, cpu_hours (an estimate of the CPU cost)
    [[labels]]  name, scenes "A:B", seed, objects, camera, n_objects, targets_per_scene, per_source
                (one `sgjax label` run each, into $SGJAX_CACHE/labels/<name>)
    [train]     model (light | paper | tiny), hand_points (E-RNet only, default 0), epochs,
                lr_decay_epochs, batch_size, lr, weight_decay, held_out_fraction, seed

`run_recipe` labels (or resumes labelling) each set through `train.label.label`, with the LabelConfig
that `sgjax label` builds from the same options (`label_config`, shared with the CLI, so that a set
started by hand is resumed, not refused), then trains with `train.trainer.train` or
`train.train_pointnetgpd.train` into a run directory; both steps resume where they stopped. Every
checkpoint's meta records the recipe (with its file's sha256) and the code's git commit.

`tiny=True` runs the same recipe at test size: 2 scenes per set, 1 grasp per source and target, the
tiny object set and the small primitive database, the tiny network, 1 epoch, into label sets named
`<name>-tiny` (never mixed with the real ones).
"""

from __future__ import annotations

import dataclasses
import hashlib
import importlib.resources
import os
import re
import shlex
import sys
import tomllib
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any
from sgjax.utils.provenance import code_commit
from train.label import label_config, parse_per_source

NETWORKS = ("ernet", "pointnetgpd")
MODELS = ("light", "paper", "tiny")
TINY_SUFFIX = "-tiny"  # label sets of tiny runs: never the directories of real ones
TINY_SCENES = 2
TINY_OBJECTS = "tiny"  # envs.objects' generated set: no download, prepared in under a second
TINY_N_OBJECTS = 3
TINY_BATCH = 32
_SAFE_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")  # names become directories


class RecipeError(ValueError):
    """A recipe file that cannot be used; the message is one line naming the file and the field."""

    def __init__(self, source: str, field: str, problem: str):
        super().__init__(f"{source}: {field}: {problem}")


# ---------------------------------------------------------------------------------------------
# The recipe.


@dataclasses.dataclass(frozen=True)
class LabelSet:
    """One `sgjax label` run: `sgjax label --scenes A:B --seed S --objects O --camera C --n-objects N
    --targets-per-scene T --per-source P --out $SGJAX_CACHE/labels/<name>`."""

    name: str
    scenes: str  # "A:B": scenes A..B-1
    seed: int
    objects: str
    camera: str
    n_objects: int
    targets_per_scene: int
    per_source: str  # "SOURCE=N,...", as `sgjax label --per-source`

    @property
    def scene_range(self) -> tuple[int, int]:
        """(first scene, end): scenes first..end-1."""
        first, _, end = self.scenes.partition(":")
        return int(first), int(end)

    def config(self, note: Callable[[str], None] | None = None, gripper=None):
        """The LabelConfig `sgjax label` builds from these options (`label_config`); gripper: a GripperSpec
        (`sgjax label --gripper`; None: the default one)."""
        return label_config(
            objects=self.objects, seed=self.seed, camera=self.camera, n_objects=self.n_objects,
            targets_per_scene=self.targets_per_scene, per_source=self.per_source, note=note, gripper=gripper,
        )

    def tiny(self) -> LabelSet:
        """This set at test size: its first 2 scenes, 1 grasp per drawn source, the tiny objects."""
        first, _ = self.scene_range
        counts = parse_per_source(self.per_source)
        return dataclasses.replace(
            self,
            name=self.name + TINY_SUFFIX,
            scenes=f"{first}:{first + TINY_SCENES}",
            objects=TINY_OBJECTS,
            n_objects=min(self.n_objects, TINY_N_OBJECTS),
            targets_per_scene=1,
            per_source=",".join(f"{name}={min(count, 1)}" for name, count in counts),
        )


@dataclasses.dataclass(frozen=True)
class TrainSettings:
    """The `sgjax train` options of a recipe (`train.trainer.TrainConfig`'s fields of the same names)."""

    model: str  # light | paper | tiny
    epochs: int
    lr_decay_epochs: int
    batch_size: int
    lr: float
    weight_decay: float
    held_out_fraction: float
    seed: int
    hand_points: int = 0  # E-RNet only: points of the hand's swept volume (`sgjax train --hand-points`)

    def config(self, network: str, gripper=None):
        """-> the TrainConfig of these settings, with the network's config of size `model`, for `gripper`
        (a GripperSpec; None: the default one), as `sgjax train` builds it from the gripper's labels."""
        from sgjax.geometry.gripper import GripperSpec
        from train.trainer import TrainConfig

        spec = GripperSpec() if gripper is None else gripper
        return TrainConfig(
            epochs=self.epochs, batch_size=self.batch_size, lr=self.lr, weight_decay=self.weight_decay, seed=self.seed,
            held_out_fraction=self.held_out_fraction, lr_decay_epochs=self.lr_decay_epochs,
            model=_network_config(network, self.model, self.hand_points, spec.num_refinements), spec=spec,
        )

    def tiny(self) -> TrainSettings:
        """These settings at test size: the tiny network, 1 epoch, small batches."""
        return dataclasses.replace(
            self, model="tiny", epochs=1, lr_decay_epochs=min(self.lr_decay_epochs, 1),
            batch_size=min(self.batch_size, TINY_BATCH),
        )


def _network_config(network: str, model: str, hand_points: int, refinements: int):
    """The network's config of size `model` (as `sgjax train --model M --hand-points H` builds it, with one
    refine output per refinement of the gripper)."""
    if network == "pointnetgpd":
        from sgjax.stage2.pointnetgpd import PointNetGPDConfig

        return getattr(PointNetGPDConfig, model)()
    from sgjax.stage2.ernet import ERNetConfig

    return getattr(ERNetConfig, model)(hand_points=hand_points, n_refinements=refinements)


@dataclasses.dataclass(frozen=True)
class Recipe:
    """A checkpoint's recipe: label sets + training settings. `path`/`sha256`: the file it was read from."""

    name: str
    network: str  # ernet | pointnetgpd
    description: str
    cpu_hours: float  # estimated CPU cost on 2 cores, labelling included
    labels: tuple[LabelSet, ...]
    train: TrainSettings
    path: str = ""
    sha256: str = ""
    gripper: str | None = None  # a preset name or gripper file (`sgjax --gripper`); None: the default gripper

    def tiny(self) -> Recipe:
        """The same recipe at test size (`LabelSet.tiny`, `TrainSettings.tiny`)."""
        return dataclasses.replace(self, labels=tuple(s.tiny() for s in self.labels), train=self.train.tiny())

    def spec(self):
        """The recipe's GripperSpec (`load_gripper(gripper)`; the default one without a gripper)."""
        from sgjax.geometry.gripper import GripperSpec
        from sgjax.geometry.gripper_files import load_gripper

        return GripperSpec() if self.gripper is None else load_gripper(self.gripper)

    def to_dict(self) -> dict[str, Any]:
        """The recipe as JSON-ready data (what a checkpoint's meta["recipe"] holds, with "tiny"). A recipe
        for the default gripper has no "gripper" entry, as before recipes named one."""
        data = dataclasses.asdict(self)
        if data["gripper"] is None:
            del data["gripper"]
        return data


# ---------------------------------------------------------------------------------------------
# Reading and checking recipe files.

_TOP = {"name": str, "network": str, "description": str, "cpu_hours": float, "labels": list, "train": dict,
        "gripper": str}
_LABEL = {f.name: f.type for f in dataclasses.fields(LabelSet)}
_TRAIN = {f.name: f.type for f in dataclasses.fields(TrainSettings)}
_OPTIONAL = {"hand_points", "gripper"}  # keys that may be left out (PointNetGPD has no hand input; the default gripper)
_TYPES = {"str": str, "int": int, "float": float}


def recipes_dir() -> Path:
    """The shipped recipes (package data of `train`)."""
    return Path(str(importlib.resources.files("train") / "recipes"))


def recipe_names() -> list[str]:
    """The names of the shipped recipes, sorted."""
    return sorted(p.stem for p in recipes_dir().glob("*.toml"))


def recipe_path(name_or_path: str | os.PathLike) -> Path:
    """A shipped recipe's file by name, or the .toml file given; FileNotFoundError naming the choices."""
    text = os.fspath(name_or_path)
    if text.endswith(".toml") or os.sep in text:
        path = Path(text)
        if not path.is_file():
            raise FileNotFoundError(f"no recipe file {text}")
        return path
    path = recipes_dir() / f"{text}.toml"
    if not path.is_file():
        raise FileNotFoundError(f"no recipe named {text!r}; shipped recipes: {', '.join(recipe_names())} (or give a .toml path)")
    return path


def load_recipe(name_or_path: str | os.PathLike) -> Recipe:
    """Read and check a recipe: a shipped recipe's name (train/recipes/NAME.toml) or a .toml path.

    Raises FileNotFoundError for a missing recipe, RecipeError (a ValueError, one line naming the file
    and the field) for a malformed one.
    """
    path = recipe_path(name_or_path)
    raw = path.read_bytes()
    try:
        data = tomllib.loads(raw.decode())
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise RecipeError(path.name, "(file)", f"not valid TOML: {exc}") from None
    recipe = parse_recipe(data, path.name)
    return dataclasses.replace(recipe, path=str(path), sha256=hashlib.sha256(raw).hexdigest())


def parse_recipe(data: Mapping[str, Any], source: str = "recipe") -> Recipe:
    """A recipe from parsed TOML; RecipeError naming `source` and the field for anything wrong."""
    top = _fields(data, _TOP, "", source)
    _check_name(top["name"], "name", source)
    _check_choice(top["network"], NETWORKS, "network", source)
    _check(top["cpu_hours"] > 0, source, "cpu_hours", f"must be > 0 (hours), got {top['cpu_hours']}")
    if not top["labels"]:
        raise RecipeError(source, "labels", "needs at least one [[labels]] set")
    gripper = top.get("gripper")
    spec = None
    if gripper is not None:
        from sgjax.geometry.gripper_files import GripperFileError, load_gripper

        try:
            spec = load_gripper(gripper)
        except (GripperFileError, FileNotFoundError, ValueError) as exc:
            raise RecipeError(source, "gripper", str(exc)) from None
    sets = tuple(_label_set(entry, f"labels[{i}]", source, spec) for i, entry in enumerate(top["labels"]))
    names = [s.name for s in sets]
    _check(len(set(names)) == len(names), source, "labels", f"names each set once, got {names}")
    settings = _train_settings(top["train"], top["network"], source)
    return Recipe(top["name"], top["network"], top["description"], top["cpu_hours"], sets, settings, gripper=gripper)


def _fields(table: Any, schema: Mapping[str, Any], where: str, source: str) -> dict[str, Any]:
    """`table`'s entries checked against `schema` (key -> type or type name): no unknown key, none
    missing (but `_OPTIONAL` ones), each of its type (ints are not bools; floats may be written as ints)."""
    if not isinstance(table, dict):
        raise RecipeError(source, where or "(file)", f"must be a table, got {type(table).__name__}")
    prefix = f"{where}." if where else ""
    for key in table:
        if key not in schema:
            raise RecipeError(source, prefix + key, f"unknown key (known: {', '.join(schema)})")
    out = {}
    for key, kind in schema.items():
        kind = _TYPES.get(kind, kind)
        if key not in table:
            if key in _OPTIONAL:
                continue
            raise RecipeError(source, prefix + key, "missing")
        value = table[key]
        if kind is float and isinstance(value, int) and not isinstance(value, bool):
            value = float(value)
        if not isinstance(value, kind) or (kind is int and isinstance(value, bool)):
            raise RecipeError(source, prefix + key, f"must be {kind.__name__}, got {value!r}")
        out[key] = value
    return out


def _check(ok: bool, source: str, field: str, problem: str) -> None:
    if not ok:
        raise RecipeError(source, field, problem)


def _check_name(name: str, field: str, source: str) -> None:
    _check(bool(_SAFE_NAME.match(name)), source, field, f"must be a plain name (letters, digits, _ . -), got {name!r}")


def _check_choice(value: str, choices: tuple[str, ...], field: str, source: str) -> None:
    _check(value in choices, source, field, f"must be one of {', '.join(choices)}, got {value!r}")


def _label_set(entry: Any, where: str, source: str, spec=None) -> LabelSet:
    """One [[labels]] entry, checked: the CLI's own LabelConfig is built from it as the last check."""
    from envs.sensors import SENSORS

    fields = _fields(entry, _LABEL, where, source)
    _check_name(fields["name"], f"{where}.name", source)
    _check(not fields["name"].endswith(TINY_SUFFIX), source, f"{where}.name",
           f"names ending in {TINY_SUFFIX!r} are the sets of --tiny runs, got {fields['name']!r}")
    match = re.fullmatch(r"(\d+):(\d+)", fields["scenes"])
    _check(bool(match) and int(match[1]) < int(match[2]), source, f"{where}.scenes",
           f"must be A:B with A < B (scenes A..B-1), got {fields['scenes']!r}")
    for key in ("seed",):
        _check(fields[key] >= 0, source, f"{where}.{key}", f"must be >= 0, got {fields[key]}")
    for key in ("n_objects", "targets_per_scene"):
        _check(fields[key] >= 1, source, f"{where}.{key}", f"must be >= 1, got {fields[key]}")
    _check(bool(fields["objects"]), source, f"{where}.objects", "must name an object set or a folder of meshes")
    _check_choice(fields["camera"], SENSORS, f"{where}.camera", source)
    _check_per_source(fields["per_source"], f"{where}.per_source", source)
    labels = LabelSet(**fields)
    try:
        labels.config(gripper=spec)  # LabelConfig's own checks too (each source once, sealed seeds and objects, ...)
    except ValueError as exc:
        raise RecipeError(source, where, str(exc)) from None
    return labels


def _check_per_source(text: str, field: str, source: str) -> None:
    """"SOURCE=N,..." with sources that labelling draws (`train.sources.DRAWN`)."""
    from train.sources import DRAWN

    try:
        counts = parse_per_source(text, field)
    except ValueError as exc:
        raise RecipeError(source, field, str(exc).removeprefix(f"{field}: ")) from None
    for name, _ in counts:
        _check(name in DRAWN, source, field, f"unknown source {name!r}; the sources drawn are {', '.join(DRAWN)}")


def _train_settings(table: Any, network: str, source: str) -> TrainSettings:
    """The [train] table, checked as `train.trainer.TrainConfig` would, naming the recipe's field."""
    fields = _fields(table, _TRAIN, "train", source)
    _check_choice(fields["model"], MODELS, "train.model", source)
    hand = fields.get("hand_points", 0)
    _check(hand >= 0, source, "train.hand_points", f"must be >= 0, got {hand}")
    _check(network == "ernet" or hand == 0, source, "train.hand_points",
           "an E-RNet input; the PointNetGPD baseline sees its closing region only")
    for key in ("epochs", "batch_size"):
        _check(fields[key] >= 1, source, f"train.{key}", f"must be >= 1, got {fields[key]}")
    _check(0 <= fields["lr_decay_epochs"] <= fields["epochs"], source, "train.lr_decay_epochs",
           f"must be in [0, epochs={fields['epochs']}], got {fields['lr_decay_epochs']}")
    _check(fields["lr"] > 0, source, "train.lr", f"must be > 0, got {fields['lr']}")
    _check(fields["weight_decay"] >= 0, source, "train.weight_decay", f"must be >= 0, got {fields['weight_decay']}")
    _check(0 <= fields["held_out_fraction"] < 1, source, "train.held_out_fraction",
           f"must be in [0, 1), got {fields['held_out_fraction']}")
    _check(fields["seed"] >= 0, source, "train.seed", f"must be >= 0, got {fields['seed']}")
    return TrainSettings(**fields)


# ---------------------------------------------------------------------------------------------
# Running a recipe.


@dataclasses.dataclass
class RecipeResult:
    """What `run_recipe` made: the label directories, the run directory and its latest checkpoint."""

    label_dirs: list[str]
    run_dir: str
    checkpoint: str  # run_dir/checkpoints/<last epoch>
    train: Any  # train.trainer.TrainResult (model, history, run_dir)


def labels_dir(name: str, cache: str | os.PathLike | None = None) -> Path:
    """Where label set `name` lives: <cache>/labels/<name> (cache None: `$SGJAX_CACHE`)."""
    from sgjax.utils.cache import cache_dir

    return Path(cache, "labels", name) if cache is not None else cache_dir("labels", name)


def run_meta(recipe: Recipe, tiny: bool) -> dict[str, Any]:
    """The meta entries a recipe's checkpoints carry: {"recipe": {...the file's fields, "path", "sha256",
    "tiny"}, "commit": {"sha", "dirty"}}."""
    return {"recipe": recipe.to_dict() | {"tiny": tiny}, "commit": code_commit()}


def run_label_set(labels: LabelSet, cache: str | os.PathLike | None = None, *, small_db: bool = False,
                  progress: bool = True, gripper=None) -> Path:
    """Label (or resume labelling) one set into `labels_dir(labels.name, cache)` as `sgjax label` does
    -> the directory. small_db: Stage 1 on the small primitive database (`sgjax label --small-db`);
    gripper: a GripperSpec (`sgjax label --gripper`; None: the default one)."""
    from sgjax.stage1.database import DBConfig, load_database
    from sgjax.stage1.pipeline import Stage1
    from train import label

    config = labels.config(note=(lambda text: print(text, file=sys.stderr)) if progress else None, gripper=gripper)
    out = labels_dir(labels.name, cache)
    first, end = labels.scene_range
    stage1 = Stage1(load_database(DBConfig.for_gripper(config.spec, small=True), progress=progress), config.stage1) \
        if small_db else None
    summary = label.label(out, end, config, stage1=stage1, progress=progress, first_scene=first)
    if progress:
        print(f"labels {labels.name} ({out}):", *(f"  {line}" for line in summary.lines()), sep="\n")
    return out


def _trainer(network: str) -> Callable:
    if network == "pointnetgpd":
        from train import train_pointnetgpd

        return train_pointnetgpd.train
    from train import trainer

    return trainer.train


def latest_checkpoint(run_dir: str | os.PathLike) -> Path:
    """run_dir/checkpoints/<highest epoch> (FileNotFoundError when there is none)."""
    from sgjax.stage2.checkpoint import CHECKPOINT_DIR

    root = Path(run_dir, CHECKPOINT_DIR)
    steps = sorted(int(p.name) for p in root.iterdir() if p.name.isdigit()) if root.is_dir() else []
    if not steps:
        raise FileNotFoundError(f"no checkpoints in {run_dir}")
    return root / str(steps[-1])


def run_recipe(recipe: Recipe, out: str | os.PathLike, *, cache: str | os.PathLike | None = None, tiny: bool = False,
               progress: bool = True) -> RecipeResult:
    """Rebuild a recipe's checkpoint: label each set (resuming), then train into `out` (resuming after
    the last finished epoch). cache: where labels/<name> live (None: `$SGJAX_CACHE`). tiny: the recipe
    at test size (`Recipe.tiny`) on the small primitive database. Raises what labelling and training
    raise (ValueError for a directory made with other settings, `train.dataset.DatasetError`).
    """
    run = recipe.tiny() if tiny else recipe
    spec = run.spec()
    dirs = [run_label_set(s, cache, small_db=tiny, progress=progress, gripper=spec) for s in run.labels]
    config = run.train.config(run.network, spec)
    result = _trainer(run.network)(
        [str(d) for d in dirs], out, config, progress=progress, extra_meta=run_meta(recipe, tiny)
    )
    return RecipeResult([str(d) for d in dirs], os.fspath(out), str(latest_checkpoint(out)), result)


def ship_lines(run_dir: str | os.PathLike, name: str) -> list[str]:
    """Shell lines that ship a run's latest checkpoint as sgjax/models/<name>, as the shipped ones are:
    the last epoch's params and meta (no optimiser state) plus metrics.csv, curves.png, reliability.png."""
    from sgjax.stage2.checkpoint import CHECKPOINT_DIR, MODELS_DIR, OPT_STATE_ITEM

    checkpoint = latest_checkpoint(run_dir)
    dest = MODELS_DIR / name
    q = shlex.quote
    extras = [q(str(Path(run_dir, f))) for f in ("metrics.csv", "curves.png", "reliability.png") if Path(run_dir, f).exists()]
    return [
        f"rm -rf {q(str(dest))} && mkdir -p {q(str(dest / CHECKPOINT_DIR))}",
        f"cp -r {q(str(checkpoint))} {q(str(dest / CHECKPOINT_DIR))}/",
        f"rm -rf {q(str(dest / CHECKPOINT_DIR / checkpoint.name / OPT_STATE_ITEM))}",
        *([f"cp {' '.join(extras)} {q(str(dest))}/"] if extras else []),
    ]


def describe(recipe: Recipe) -> str:
    """One recipe in a few lines (`sgjax train --list-recipes`)."""
    sets = "; ".join(f"{s.name} scenes {s.scenes} seed {s.seed} ({s.objects}, {s.camera})" for s in recipe.labels)
    gripper = "" if recipe.gripper is None else f", gripper {recipe.gripper}"
    return (f"{recipe.name}  [{recipe.network}, {recipe.train.model}, {recipe.train.epochs} epochs, "
            f"~{recipe.cpu_hours:g} CPU h{gripper}]\n  {recipe.description}\n  labels: {sets}")
