"""Recipes (train/recipe.py, `sgjax train --recipe`): every shipped recipe loads, a bad field is named in
one line, and every shipped recipe runs end to end at tiny size, records itself and the commit in its
checkpoints, and resumes without redoing labels or epochs."""

from __future__ import annotations

import copy
import hashlib
import json
import re
import subprocess
import tomllib
from pathlib import Path

import pytest

from sgjax.stage1.database import DBConfig, default_path, save_database
from sgjax.stage2 import checkpoint, ernet, pointnetgpd
from sgjax_cli import main
from train import label
from train import recipe as recipes

SHIPPED = recipes.recipe_names()
LOADERS = {"ernet": ernet.load_model, "pointnetgpd": pointnetgpd.load_model}
REPO = Path(recipes.__file__).resolve().parent.parent


def _data(name: str = "ernet_default") -> dict:
    with open(recipes.recipe_path(name), "rb") as fh:
        return tomllib.load(fh)


def test_both_shipped_checkpoints_have_a_recipe():
    assert {"ernet_default", "pointnetgpd_default"} <= set(SHIPPED)


@pytest.mark.parametrize("name", SHIPPED)
def test_every_shipped_recipe_loads_and_validates(name):
    recipe = recipes.load_recipe(name)
    path = recipes.recipe_path(name)
    assert recipe.name == name == path.stem  # `--recipe NAME` finds the file of that name
    assert recipe.sha256 == hashlib.sha256(path.read_bytes()).hexdigest()
    assert recipe.cpu_hours > 0 and recipe.labels and recipe.train.epochs >= 1
    assert recipes.load_recipe(path) == recipe  # by path too
    json.dumps(recipe.to_dict())  # what the checkpoints' meta holds
    recipe.train.config(recipe.network)  # a valid TrainConfig
    recipe.tiny().train.config(recipe.network)


def test_shipped_recipes_sharing_a_label_set_agree_on_it():
    """A set is one directory: two recipes naming it must ask for the same labelling."""
    sets: dict[str, recipes.LabelSet] = {}
    for name in SHIPPED:
        for labels in recipes.load_recipe(name).labels:
            assert sets.setdefault(labels.name, labels) == labels, labels.name


def test_the_cli_and_a_recipe_build_one_label_config():
    """`sgjax label`'s options and a recipe's set give the same LabelConfig (so a recipe resumes a set the
    CLI started): the mixed set's own options, and a set of another object set (no held-out objects)."""
    labels = recipes.load_recipe("ernet_default").labels[0]
    cli = label.label_config(objects="seen", seed=0, camera="exact", n_objects=5, targets_per_scene=2,
                               per_source="stage1=8,stage1_paper=8,gpd=8,perturbed=8")
    assert labels.config() == cli and cli.to_json() == labels.config().to_json()
    assert cli.per_source == label.DEFAULT_PER_SOURCE and cli.held_out_objects == label.SEEN_HELD_OUT
    notes = []
    assert label.label_config(objects="tiny", note=notes.append).held_out_objects == () and "tiny" in notes[0]


def _set(data: dict, dotted: str, value) -> dict:
    """A copy of recipe data with `dotted` ("train.epochs", "labels.0.scenes") set (value ... deletes it)."""
    data = copy.deepcopy(data)
    *path, last = dotted.split(".")
    node = data
    for key in path:
        node = node[int(key)] if key.isdigit() else node[key]
    if value is ...:
        del node[last]
    else:
        node[last] = value
    return data


BAD = [
    # (field to set, value (... deletes it), the field the error must name)
    ("colour", "red", "colour"),
    ("train.momentum", 0.9, "train.momentum"),
    ("labels.0.shard", "0/2", "labels[0].shard"),
    ("network", "resnet", "network"),
    ("name", "a/b", "name"),
    ("cpu_hours", ..., "cpu_hours"),
    ("cpu_hours", 0, "cpu_hours"),
    ("description", 3, "description"),
    ("train.epochs", ..., "train.epochs"),
    ("train.epochs", -1, "train.epochs"),
    ("train.epochs", "30", "train.epochs"),
    ("train.epochs", True, "train.epochs"),
    ("train.lr_decay_epochs", 31, "train.lr_decay_epochs"),
    ("train.model", "huge", "train.model"),
    ("train.lr", 0.0, "train.lr"),
    ("train.weight_decay", -1e-4, "train.weight_decay"),
    ("train.held_out_fraction", 1.0, "train.held_out_fraction"),
    ("train.batch_size", 0, "train.batch_size"),
    ("train.hand_points", -1, "train.hand_points"),
    ("train.seed", -1, "train.seed"),
    ("labels", [], "labels"),
    ("labels.0.scenes", "5:2", "labels[0].scenes"),
    ("labels.0.scenes", "1144", "labels[0].scenes"),
    ("labels.0.scenes", "a:b", "labels[0].scenes"),
    ("labels.0.name", "../elsewhere", "labels[0].name"),
    ("labels.0.name", "mix-tiny", "labels[0].name"),
    ("labels.0.camera", "lidar", "labels[0].camera"),
    ("labels.0.n_objects", 0, "labels[0].n_objects"),
    ("labels.0.targets_per_scene", 0, "labels[0].targets_per_scene"),
    ("labels.0.seed", -3, "labels[0].seed"),
    ("labels.0.seed", ..., "labels[0].seed"),
    ("labels.0.objects", "", "labels[0].objects"),
    ("labels.0.per_source", "stage1:8", "labels[0].per_source"),
    ("labels.0.per_source", "stage1=8,magic=8", "labels[0].per_source"),
    ("labels.0.per_source", "stage1=0", "labels[0]"),  # LabelConfig's own check: some grasps
    ("gripper", "no-such-gripper", "gripper"),
    ("gripper", 3, "gripper"),
]


@pytest.mark.parametrize(("field", "value", "named"), BAD, ids=[f"{f}={v!r}" for f, v, _ in BAD])
def test_a_bad_field_gives_one_line_naming_it(field, value, named):
    with pytest.raises(recipes.RecipeError) as info:
        recipes.parse_recipe(_set(_data(), field, value), "bad.toml")
    message = str(info.value)
    assert "\n" not in message and message.startswith(f"bad.toml: {named}: "), message


def test_pointnetgpd_takes_no_hand_points():
    with pytest.raises(recipes.RecipeError, match=r"^x\.toml: train\.hand_points: an E-RNet input"):
        recipes.parse_recipe(_set(_data("pointnetgpd_default"), "train.hand_points", 32), "x.toml")


def test_duplicate_label_sets_and_bad_files(tmp_path):
    data = _data()
    with pytest.raises(recipes.RecipeError, match=r"^r\.toml: labels: names each set once"):
        recipes.parse_recipe({**data, "labels": data["labels"] * 2}, "r.toml")
    text = recipes.recipe_path("ernet_default").read_text()
    (tmp_path / "neg.toml").write_text(text.replace("epochs = 30", "epochs = -1"))
    with pytest.raises(ValueError, match=r"^neg\.toml: train\.epochs: must be >= 1, got -1$"):
        recipes.load_recipe(tmp_path / "neg.toml")
    (tmp_path / "broken.toml").write_text(text + "\n[train\n")
    with pytest.raises(ValueError, match=r"^broken\.toml: \(file\): not valid TOML"):
        recipes.load_recipe(tmp_path / "broken.toml")
    with pytest.raises(FileNotFoundError, match="shipped recipes: .*ernet_default"):
        recipes.load_recipe("no_such_recipe")


# ---------------------------------------------------------------------------------------------
# End to end at tiny size.


def _files(directory: str | Path) -> dict[str, tuple[int, int]]:
    """name -> (size, mtime_ns) of every file under `directory`: what a rerun must leave alone."""
    root = Path(directory)
    return {str(p.relative_to(root)): (p.stat().st_size, p.stat().st_mtime_ns) for p in sorted(root.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def tiny_runs(small_db, tmp_path_factory):
    """Every shipped recipe run at tiny size in a fresh cache, then run again -> (cache, {name: (recipe,
    first result, files after the first run, second result)})."""
    cache = tmp_path_factory.mktemp("cache")
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("SGJAX_CACHE", str(cache))
        save_database(small_db, default_path(DBConfig.small()))  # built once per session, not per cache
        runs = {}
        for name in SHIPPED:
            recipe = recipes.load_recipe(name)
            out = cache / "runs" / name
            first = recipes.run_recipe(recipe, out, tiny=True, progress=False)
            runs[name] = [recipe, first, {d: _files(d) for d in [*first.label_dirs, out]}]
        for name, run in runs.items():  # after all first runs: a shared set is complete before any rerun
            run[2] = {d: _files(d) for d in run[2]}
            run.append(recipes.run_recipe(run[0], cache / "runs" / name, tiny=True, progress=False))
        yield cache, runs


@pytest.mark.parametrize("name", SHIPPED)
def test_tiny_run_makes_a_loadable_checkpoint_recording_recipe_and_commit(tiny_runs, name):
    cache, runs = tiny_runs
    recipe, first, _, _ = runs[name]
    assert first.label_dirs == [str(cache / "labels" / (s.name + "-tiny")) for s in recipe.labels]
    assert Path(first.checkpoint) == cache / "runs" / name / "checkpoints" / "1"
    assert first.train.history[0]["train"]["samples"] > 0  # it labelled and trained on something
    model, meta = LOADERS[recipe.network](first.run_dir)
    assert model.config == recipe.tiny().train.config(recipe.network).model
    assert meta["recipe"] == json.loads(json.dumps({**recipe.to_dict(), "tiny": True}))
    assert meta["recipe"]["sha256"] == recipe.sha256 and meta["recipe"]["train"]["epochs"] == recipe.train.epochs
    head = subprocess.run(["git", "-C", str(REPO), "rev-parse", "HEAD"], capture_output=True, text=True, check=False)
    if head.returncode == 0:
        assert meta["commit"]["sha"] == head.stdout.strip() and isinstance(meta["commit"]["dirty"], bool)
    else:
        assert meta["commit"] == {"sha": "unknown", "dirty": None}
    if recipe.network == "pointnetgpd":
        assert meta["network"] == "pointnetgpd"  # extra_meta does not replace it
    # The recipe's gripper (the default one where it names none) labelled the set and trained the model.
    assert checkpoint.meta_gripper(meta) == recipe.spec() == label.data_gripper(first.label_dirs)
    assert ("gripper" in meta["recipe"]) == (recipe.gripper is not None)


@pytest.mark.parametrize("name", SHIPPED)
def test_rerun_resumes_without_redoing_labels_or_epochs(tiny_runs, name):
    _, runs = tiny_runs
    _, first, files, second = runs[name]
    for directory, before in files.items():
        assert _files(directory) == before, directory  # not a file of the labels or the run rewritten
    assert second.checkpoint == first.checkpoint and len(second.train.history) == 1
    assert second.train.history == first.train.history


def test_the_cli_runs_a_recipe_at_tiny_size(tiny_runs, tmp_path, capsys):
    cache, _ = tiny_runs
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("SGJAX_CACHE", str(cache))  # the labels made above: reused, not redone
        labels = cache / "labels" / "recipe-mix-r1-tiny"
        before = _files(labels)
        assert main(["train", "--recipe", "ernet_default", "--tiny", "--out", str(tmp_path / "run"), "--quiet"]) == 0
        out = capsys.readouterr().out
        assert f"checkpoint {tmp_path / 'run' / 'checkpoints' / '1'}" in out and "not a checkpoint to ship" in out
        assert ernet.load_model(tmp_path / "run")[1]["recipe"]["name"] == "ernet_default"
        # `sgjax label` with the set's own options finds the recipe's directory complete: one LabelConfig.
        tiny = recipes.load_recipe("ernet_default").labels[0].tiny()
        assert main(["label", "--scenes", tiny.scenes, "--objects", tiny.objects, "--n-objects", str(tiny.n_objects),
                     "--targets-per-scene", "1", "--per-source", tiny.per_source, "--small-db", "--out", str(labels),
                     "--quiet"]) == 0
        assert _files(labels) == before


def test_recipe_usage_errors(tmp_path, capsys):
    assert main(["train", "--recipe", "ernet_default", "--epochs", "3", "--seed", "0"]) == 2
    assert re.search(r"--recipe sets .*--epochs, --seed", capsys.readouterr().err)
    assert main(["train", "--recipe", "ernet_default", "--data", str(tmp_path)]) == 2
    assert "--data" in capsys.readouterr().err
    assert main(["train", "--recipe", "no_such_recipe"]) == 2
    assert "no recipe named 'no_such_recipe'" in capsys.readouterr().err
    assert main(["train", "--tiny", "--data", str(tmp_path), "--out", str(tmp_path / "run")]) == 2
    assert "--tiny" in capsys.readouterr().err
    assert main(["train", "--out", str(tmp_path / "run")]) == 2
    assert "train needs --data" in capsys.readouterr().err
    with pytest.raises(SystemExit):  # argparse: not both
        main(["train", "--recipe", "ernet_default", "--list-recipes"])
    capsys.readouterr()
    assert main(["train", "--list-recipes"]) == 0
    listing = capsys.readouterr().out
    for name in SHIPPED:
        recipe = recipes.load_recipe(name)
        assert name in listing and recipe.network in listing and f"scenes {recipe.labels[0].scenes}" in listing
        assert f"{recipe.train.epochs} epochs" in listing


def test_ship_lines_copy_the_last_epoch_without_optimiser_state(tiny_runs):
    _, runs = tiny_runs
    first = runs["ernet_default"][1]
    lines = recipes.ship_lines(first.run_dir, "ernet_default")
    assert any(f"cp -r {first.checkpoint} " in line for line in lines)
    assert any(line.startswith("rm -rf ") and line.endswith("/checkpoints/1/opt_state") for line in lines)


# The shipped checkpoints, each rebuilt from its recipe.
REBUILT = ["ernet_default", "pointnetgpd_default", "ernet_ag-105-145", "ernet_robotiq-2f85"]


@pytest.mark.parametrize("name", REBUILT)
def test_a_shipped_checkpoint_is_its_recipes_product(name):
    """A shipped checkpoint records the recipe file as it is in the repository today (same bytes), the
    full training it asks for, and a clean commit of this repository: so `sgjax train --recipe NAME`
    rebuilds it from the code it names."""
    recipe = recipes.load_recipe(name)
    model, meta = LOADERS[recipe.network](checkpoint.MODELS_DIR / name)
    recorded = dict(meta["recipe"])
    assert Path(recorded.pop("path")).parts[-3:] == ("train", "recipes", f"{name}.toml")  # the checkout it ran in
    expected = json.loads(json.dumps({**recipe.to_dict(), "tiny": False}))
    expected.pop("path", None)
    assert recorded == expected
    assert meta["recipe"]["sha256"] == hashlib.sha256(recipes.recipe_path(name).read_bytes()).hexdigest()
    assert meta["epochs_done"] == recipe.train.epochs and model.config == recipe.train.config(recipe.network).model
    assert re.fullmatch(r"[0-9a-f]{40}", meta["commit"]["sha"]) and meta["commit"]["dirty"] is False
    known = subprocess.run(["git", "-C", str(REPO), "cat-file", "-e", meta["commit"]["sha"] + "^{commit}"],
                           capture_output=True, check=False)
    inside = subprocess.run(["git", "-C", str(REPO), "rev-parse", "--is-shallow-repository"],
                            capture_output=True, text=True, check=False)
    if inside.returncode == 0 and inside.stdout.strip() == "false":  # a full clone holds the commit
        assert known.returncode == 0, f"{name} was trained at {meta['commit']['sha']}, not a commit of this repository"
