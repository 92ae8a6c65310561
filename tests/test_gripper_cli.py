"""`--gripper NAME|FILE` end to end on the tiny object set: the benchmark's simulated gripper and its method's,
a labelled directory that records the whole gripper (force and friction too) and resumes only with it, a
checkpoint that records the gripper of its training data, and the planner's warning when it plans for
another gripper. The database key of a gripper is tested in tests/test_gripper_files.py."""

from __future__ import annotations

import dataclasses
import json
import warnings
from pathlib import Path

import numpy as np
import pytest

from sgjax.geometry.gripper import GripperSpec
from sgjax.geometry.gripper_files import gripper_to_dict, load_gripper, save_gripper
from sgjax.stage1.database import DBConfig, default_path, save_database
from sgjax_cli import main

ROBOTIQ = "robotiq-2f85"
# The default gripper's size (so the default database) with another force and pad friction.
MINE = GripperSpec(closing_force=30.0, finger_friction=0.8)


@pytest.fixture(scope="module")
def cache(small_db, tmp_path_factory):
    """A fresh $SGJAX_CACHE holding the session's small database (not built again)."""
    cache = tmp_path_factory.mktemp("cache")
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("SGJAX_CACHE", str(cache))
        save_database(small_db, default_path(DBConfig.small()))
        yield cache


# ---------------------------------------------------------------------------------------------
# Usage errors: one line, exit code 2, before any work.


@pytest.mark.parametrize("command", [
    ["declutter", "--method", "gpd", "--objects", "tiny", "--n-objects", "2", "--scenes", "1", "--out", "{out}"],
    ["label", "--scenes", "1", "--objects", "tiny", "--out", "{out}"],
    ["train", "--data", "nowhere", "--out", "{out}"],
    ["plan", "--depth", "{out}/d.png", "--intrinsics", "{out}/k.json"],
    ["plan", "{out}/cloud.npy", "--mask", "{out}/mask.npy"],
    ["build-db", "--small", "--out", "{out}/db.npz"],
    ["candidates", "{out}/cloud.npy", "--small-db"],
])
def test_a_bad_gripper_is_a_one_line_usage_error(tmp_path, capsys, command):
    bad = tmp_path / "bad.toml"
    save_gripper(GripperSpec(), bad)
    bad.write_text(bad.read_text().replace("max_opening = 0.08", "max_opening = -0.08"))
    out = tmp_path / "out"
    for gripper, message in (("no-such-gripper", "the presets are default, ag-105-145, franka-hand, robotiq-2f85"),
                             (str(bad), "max_opening: must be positive")):
        code = main([*(part.format(out=out) for part in command), "--gripper", gripper])
        err = capsys.readouterr().err
        assert code == 2 and message in err and err.startswith("sgjax: error: --gripper:")
        assert len(err.strip().splitlines()) == 1, err
    assert not out.exists()


def test_only_the_default_gripper_database_ships(tmp_path, capsys):
    assert main(["build-db", "--gripper", "ag-105-145", "--ship", "--out", str(tmp_path / "db.npz")]) == 2
    assert "only the default gripper's database ships" in capsys.readouterr().err
    assert not (tmp_path / "db.npz").exists()


# ---------------------------------------------------------------------------------------------
# The benchmark: the simulated gripper and the method's are --gripper's.


def test_declutter_runs_with_the_gripper_it_is_given(cache, tmp_path, capsys):
    from envs import gripper_model, objects
    from envs.trial import run_trials
    from eval import declutter, report

    out = tmp_path / "out"
    code = main(["declutter", "--method", "gpd", "--objects", "tiny", "--n-objects", "2", "--scenes", "1",
                 "--gripper", ROBOTIQ, "--out", str(out), "--json", "--quiet", "--pictures", "0"])
    assert code == 0, capsys.readouterr().err
    assert json.loads(capsys.readouterr().out)["scenes"] == 1
    spec = load_gripper(ROBOTIQ)
    log = json.loads(report.scene_log_path(out, "gpd", "tiny-2", 0, 0).read_text())
    assert log["gripper"] == gripper_to_dict(spec)  # the whole gripper, force and friction included
    attempts = [a for a in log["attempts"] if a["target"] is not None]
    assert attempts and all(0 < a["width"] <= spec.max_opening for a in log["attempts"])
    # The simulated gripper is the 2F-85: its stroke, its force; a logged grasp opens it to at most its stroke.
    config = declutter.DeclutterConfig(gripper=spec)
    scene = declutter.make_benchmark_scene(objects.tiny_object_set(), 2, 0, 0, config)
    model = scene.model
    for joint, servo in zip(gripper_model.FINGER_JOINTS, gripper_model.FINGER_ACTUATORS):
        np.testing.assert_allclose(model.joint(joint).range, [0.0, spec.max_opening / 2])
        np.testing.assert_allclose(model.actuator(servo).forcerange, [-spec.closing_force, spec.closing_force])
    first = log["attempts"][0]
    result = run_trials(scene, first["target"], np.asarray([first["pose"]]), np.asarray([first["width"]]),
                        config=config.trial)
    assert result.opening.max() <= spec.max_opening + 1e-6
    assert bool(result.label[0]) == first["success"]  # the log's trial, replayed with the same gripper


def test_a_method_never_plans_for_another_gripper_than_the_simulated_one(tmp_path):
    from eval.benchmark import run_benchmark
    from eval.declutter import DeclutterConfig
    from eval.gpd import GPDMethod
    from eval.methods import make_method, method_gripper, takes_gripper
    from sgjax.samplers.gpd import GPDConfig

    robotiq = load_gripper(ROBOTIQ)
    assert method_gripper(make_method("gpd", gripper=robotiq)) == robotiq
    assert make_method("gpd", gripper=GripperSpec()).config == GPDConfig()  # the default: as before
    assert takes_gripper("supergrasp@paper") and takes_gripper("gpd+s2") and not takes_gripper("oracle-topdown")
    with pytest.raises(ValueError, match="its config plans for gripper default .* simulates gripper robotiq-2f85"):
        make_method("gpd", config=GPDConfig(), gripper=robotiq)
    with pytest.raises(ValueError, match="its config plans for gripper default"):
        make_method("pointnetgpd", config=_baseline(), gripper=robotiq)
    config = DeclutterConfig(gripper=robotiq)
    with pytest.raises(ValueError, match="plans for gripper default .* benchmark simulates gripper robotiq-2f85"):
        run_benchmark(GPDMethod(), scenes=1, out=tmp_path, config=config, progress=False)
    with pytest.raises(ValueError, match="is not the benchmark's simulated gripper"):
        run_benchmark("gpd", scenes=1, out=tmp_path, config=config, method_options={"gripper": GripperSpec()},
                      progress=False)
    assert not any(tmp_path.iterdir())  # refused before any work


def _baseline():
    from eval.baselines import BaselineConfig

    return BaselineConfig()


# ---------------------------------------------------------------------------------------------
# Labels, a training run, the planner.


@pytest.fixture(scope="module")
def labelled(cache, tmp_path_factory):
    """`sgjax label --gripper FILE` on one tiny scene (the default size, another force and friction) ->
    (gripper file, labelled directory)."""
    root = tmp_path_factory.mktemp("labelled")
    path = save_gripper(MINE, root / "mine.toml")
    labels = root / "labels"
    code = main(["label", "--scenes", "1", "--objects", "tiny", "--n-objects", "2", "--targets-per-scene", "1",
                 "--per-source", "stage1=2,stage1_paper=1,gpd=1,perturbed=1", "--small-db", "--gripper", str(path),
                 "--out", str(labels), "--quiet"])
    assert code == 0
    return path, labels


def test_a_labelled_directory_records_the_whole_gripper_and_resumes_only_with_it(labelled, tmp_path, capsys):
    from train.label import read_config

    path, labels = labelled
    saved = json.loads((labels / "label_config.json").read_text())
    assert saved["gripper"] == gripper_to_dict(MINE)
    config = read_config(labels)
    assert config.spec == MINE and config.gpd.spec == MINE
    assert (config.spec.closing_force, config.spec.finger_friction) == (30.0, 0.8)
    shards = sorted(p.name for p in labels.iterdir() if p.suffix == ".npz")
    other = save_gripper(dataclasses.replace(MINE, closing_force=40.0), tmp_path / "stronger.toml")
    base = ["label", "--scenes", "1", "--objects", "tiny", "--n-objects", "2", "--targets-per-scene", "1",
            "--per-source", "stage1=2,stage1_paper=1,gpd=1,perturbed=1", "--small-db", "--out", str(labels), "--quiet"]
    capsys.readouterr()
    assert main([*base, "--gripper", str(other)]) == 2  # another force: refused
    assert "different labelling config" in capsys.readouterr().err
    assert main(base) == 2  # the default gripper: refused too
    assert main([*base, "--gripper", str(path)]) == 0  # the same gripper: resumes (nothing left to do)
    assert sorted(p.name for p in labels.iterdir() if p.suffix == ".npz") == shards


def test_directories_without_the_gripper_entry_read_back_as_the_default_gripper(tmp_path):
    from train.label import (
        CONFIG_FILE,
        LabelConfig,
        check_out_dir,
        label_config,
        same_config,
    )

    default = LabelConfig()
    assert "gripper" not in json.loads(default.to_json())  # written as before this entry existed
    (tmp_path / CONFIG_FILE).write_text(default.to_json())
    check_out_dir(str(tmp_path), default)
    for spec in (MINE, load_gripper(ROBOTIQ)):
        with pytest.raises(ValueError, match="different labelling config"):
            check_out_dir(str(tmp_path), default.with_gripper(spec))
    # A non-default gripper's config reads back whole; its gripper entry must agree with stage1.spec.
    robotiq = label_config(objects="tiny", gripper=load_gripper(ROBOTIQ))
    assert LabelConfig.from_json(robotiq.to_json()) == robotiq and not same_config(robotiq.to_json(), default)
    wrong = json.loads(robotiq.to_json())
    wrong["gripper"]["max_opening"] = 0.07
    with pytest.raises(ValueError, match="gripper entry and stage1.spec are different grippers"):
        LabelConfig.from_json(json.dumps(wrong))


# label_config.json of recipe-mix-r1 as written on 2026-12-05 before the gripper entry, GPDConfig's
# objects_per_budget and the recipes existed (copied from that live directory).
SAVED = Path(__file__).parent / "data" / "label_config_recipe-mix-r1.json"


def test_a_directory_labelled_before_these_fields_still_resumes():
    """A labelled directory written before fields were added still matches the config that `sgjax label`
    and the recipe build for it (fields added since read back at their defaults), and no other."""
    from train.label import label_config, same_config

    config = label_config(objects="seen", seed=0, camera="exact", n_objects=5, targets_per_scene=2,
                          per_source="stage1=8,stage1_paper=8,gpd=8,perturbed=8")
    assert same_config(SAVED.read_text(), config)
    assert not same_config(SAVED.read_text(), label_config(objects="seen", seed=1, per_source="stage1=8,stage1_paper=8,gpd=8,perturbed=8"))


@pytest.fixture(scope="module")
def trained(labelled, tmp_path_factory):
    """A tiny E-RNet trained on the labels of `labelled` -> (gripper file, labels, run directory)."""
    path, labels = labelled
    run = tmp_path_factory.mktemp("run") / "run"
    assert main(["train", "--data", str(labels), "--out", str(run), "--model", "tiny", "--epochs", "1",
                 "--held-out", "0", "--batch-size", "4", "--quiet"]) == 0
    return path, labels, run


def test_training_takes_the_data_gripper_and_records_it(trained, tmp_path, capsys):
    from sgjax.stage2 import checkpoint, ernet

    _, labels, run = trained
    _, meta = ernet.load_model(run)
    assert meta["gripper"] == gripper_to_dict(MINE)
    assert checkpoint.checkpoint_gripper(run) == checkpoint.meta_gripper(meta) == MINE
    assert checkpoint.meta_gripper({"epochs_done": 30}) == GripperSpec()  # no record: the default gripper
    assert checkpoint.checkpoint_gripper(checkpoint.ERNET_DEFAULT_DIR) == GripperSpec()  # the shipped one
    capsys.readouterr()
    # --gripper must be the data's.
    assert main(["train", "--data", str(labels), "--out", str(tmp_path / "r"), "--gripper", ROBOTIQ, "--model", "tiny",
                 "--epochs", "1", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "--gripper robotiq-2f85 is not the gripper the labels" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "r").exists()
    # Label directories of different grippers are never trained on together.
    from train.label import LabelConfig, data_gripper
    from train.trainer import TrainConfig, train

    other = tmp_path / "other"
    other.mkdir()
    (other / "label_config.json").write_text(LabelConfig().to_json())
    with pytest.raises(ValueError, match="made for different grippers"):
        data_gripper([labels, other])
    with pytest.raises(ValueError, match="was labelled for gripper a custom gripper"):
        train(str(labels), tmp_path / "r2", TrainConfig(epochs=1), progress=False)
    assert data_gripper(labels) == MINE


def test_the_planner_names_its_checkpoint_and_warns_for_another_gripper(trained, small_db):
    from flax import nnx

    from sgjax import presets
    from sgjax.planner import Planner
    from sgjax.stage2.ernet import ERNet, ERNetConfig

    path, _, run = trained
    with pytest.warns(UserWarning, match=rf"E-RNet checkpoint {run} was trained for gripper a custom gripper .*"
                                         r"closing_force 30 N.* but plans for gripper robotiq-2f85 .*sgjax label --gripper"):
        planner = Planner(str(run), small_db, presets.get("default", gripper=load_gripper(ROBOTIQ)))
    assert planner.checkpoint == str(run) and planner.checkpoint_gripper == MINE
    with warnings.catch_warnings(record=True) as caught:  # the gripper it was trained for: no warning
        warnings.simplefilter("always")
        planner = Planner(str(run), small_db, presets.get("default", gripper=load_gripper(path)))
        assert planner.config.spec == MINE
        planner = Planner(None, small_db)  # the shipped checkpoint, the default gripper
        assert planner.checkpoint == "sgjax/models/ernet_default" and planner.checkpoint_gripper == GripperSpec()
        model = ERNet(ERNetConfig.tiny(), rngs=nnx.Rngs(0))
        planner = Planner(model, small_db, presets.get("default", gripper=load_gripper(ROBOTIQ)))
        assert planner.checkpoint == "an in-memory model" and planner.checkpoint_gripper is None
        from sgjax.stage2.scorers import Stage1Order
        planner = Planner(Stage1Order(), small_db, dataclasses.replace(presets.get("default", gripper=load_gripper(ROBOTIQ)),
                                                                       use_refinement=False))
        assert planner.checkpoint == "none (Stage 1's order)" and planner.checkpoint_gripper is None
    assert not [w for w in caught if "trained for gripper" in str(w.message)]
    with pytest.warns(UserWarning, match="was trained for gripper default"):
        Planner(None, small_db, presets.get("default", gripper=MINE))
    assert presets.get("paper", gripper=MINE).stage1.filter == presets.get("paper").stage1.filter
    assert presets.get("default", gripper=GripperSpec()) == presets.get("default")


def test_the_planner_takes_the_checkpoint_shipped_for_its_gripper(trained, small_db, tmp_path, monkeypatch):
    """Beside `ernet_default`, a checkpoint shipped for another gripper (`sgjax/models/ernet_<gripper>`,
    its meta's record) is what a planner for that gripper loads by default, without a warning; a gripper
    nothing was shipped for still gets the default one and the warning."""
    import shutil

    from sgjax import presets
    from sgjax.planner import Planner
    from sgjax.stage2 import checkpoint

    for preset, shipped in (("ag-105-145", "ernet_ag-105-145"), (ROBOTIQ, "ernet_robotiq-2f85"), ("franka-hand", "ernet_default"),
                           ("default", "ernet_default")):
        assert checkpoint.shipped_dir(checkpoint.ERNET_DEFAULT_DIR, load_gripper(preset)) == checkpoint.MODELS_DIR / shipped
    _, _, run = trained
    models = tmp_path / "models"
    shutil.copytree(checkpoint.ERNET_DEFAULT_DIR / checkpoint.CHECKPOINT_DIR, models / "ernet_default" / checkpoint.CHECKPOINT_DIR)
    shutil.copytree(run / checkpoint.CHECKPOINT_DIR, models / "ernet_mine" / checkpoint.CHECKPOINT_DIR)
    monkeypatch.setattr(checkpoint, "MODELS_DIR", models)
    monkeypatch.setattr(checkpoint, "ERNET_DEFAULT_DIR", models / "ernet_default")
    assert checkpoint.shipped_dir(checkpoint.ERNET_DEFAULT_DIR, MINE) == models / "ernet_mine"
    assert checkpoint.shipped_dir(checkpoint.ERNET_DEFAULT_DIR, GripperSpec()) == models / "ernet_default"
    assert checkpoint.shipped_dir(checkpoint.ERNET_DEFAULT_DIR, None) == models / "ernet_default"
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        mine = Planner(None, small_db, presets.get("default", gripper=MINE))
        default = Planner(None, small_db)
    assert not [w for w in caught if "trained for gripper" in str(w.message)]
    assert mine.checkpoint == "sgjax/models/ernet_mine" and mine.checkpoint_gripper == MINE
    assert mine.model.config == trained_config(run)
    assert default.checkpoint == "sgjax/models/ernet_default" and default.checkpoint_gripper == GripperSpec()
    with pytest.warns(UserWarning, match="E-RNet checkpoint sgjax/models/ernet_default was trained for gripper default"):
        Planner(None, small_db, presets.get("default", gripper=load_gripper(ROBOTIQ)))


def trained_config(run):
    """The model config a run directory's checkpoint records."""
    from sgjax.stage2 import ernet

    return ernet.load_model(run)[0].config
