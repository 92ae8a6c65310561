"""The E-RNet for a depth camera's clouds (`sgjax/models/ernet_realsense`, train/recipes/ernet_realsense.toml):
which checkpoint a planner, a benchmark method and `sgjax plan --depth` load for sensed and for exact
depth, and that a student of distillation sets records the sensor it was taught."""

from __future__ import annotations

import dataclasses
import json
import shutil

import pytest

from envs.camera import CameraConfig
from envs.objects import tiny_object_set
from eval.benchmark import run_benchmark, run_key
from eval.declutter import DeclutterConfig
from eval.methods import make_method, takes_sensed
from sgjax.geometry.gripper import GripperSpec
from sgjax.geometry.gripper_files import load_gripper
from sgjax.stage2 import checkpoint, ernet

SENSED = "sgjax/models/ernet_realsense"
EXACT = "sgjax/models/ernet_default"


def test_the_shipped_choice_follows_the_depth_and_the_gripper():
    """Sensed depth loads the checkpoint taught a sensor's view for the gripper where one is shipped
    (the default gripper's), else the gripper's own; exact depth never loads a sensor's."""
    default = checkpoint.ERNET_DEFAULT_DIR
    assert checkpoint.checkpoint_sensor(checkpoint.MODELS_DIR / "ernet_realsense") == "realsense"
    assert checkpoint.checkpoint_gripper(checkpoint.MODELS_DIR / "ernet_realsense") == GripperSpec()
    assert checkpoint.checkpoint_sensor(default) == "exact"
    for spec in (None, GripperSpec()):
        assert checkpoint.model_checkpoint(None, default, spec, sensed=True)[0] == SENSED
        assert checkpoint.model_checkpoint(None, default, spec)[0] == EXACT
    ag = load_gripper("ag-105-145")  # its shipped E-RNet saw stereo labels already: one for both depths
    for sensed in (False, True):
        assert checkpoint.shipped_dir(default, ag, sensed) == checkpoint.MODELS_DIR / "ernet_ag-105-145"


def test_a_sensor_taught_checkpoint_only_stands_in_where_nothing_else_fits(tmp_path, monkeypatch):
    """In a models folder holding only a sensor-taught checkpoint for the default gripper besides the
    exact one, exact depth keeps the exact one and sensed depth takes the taught one; where the exact
    one is missing, the taught one is better than another gripper's."""
    models = tmp_path / "models"
    for name in ("ernet_default", "ernet_realsense"):
        shutil.copytree(checkpoint.MODELS_DIR / name / checkpoint.CHECKPOINT_DIR, models / name / checkpoint.CHECKPOINT_DIR)
    default = models / "ernet_default"
    assert checkpoint.shipped_dir(default, GripperSpec()) == default
    assert checkpoint.shipped_dir(default, GripperSpec(), sensed=True) == models / "ernet_realsense"
    shutil.rmtree(default / checkpoint.CHECKPOINT_DIR)
    assert checkpoint.shipped_dir(default, GripperSpec()) == models / "ernet_realsense"


def test_methods_scoring_with_ernet_take_the_sensed_network(small_db):
    assert takes_sensed("supergrasp") and takes_sensed("supergrasp-norefine@paper") and takes_sensed("gpd+s2")
    assert not takes_sensed("s1+pointnetgpd") and not takes_sensed("gpd") and not takes_sensed("contact-graspnet")
    sensed = make_method("supergrasp", db=small_db, sensed=True)
    exact = make_method("supergrasp", db=small_db)
    assert sensed.planner.checkpoint == SENSED and exact.planner.checkpoint == EXACT
    assert sensed.planner.model.config == exact.planner.model.config  # the same network, other weights
    assert make_method("gpd+s2", sensed=True).checkpoint == SENSED and make_method("gpd+s2").checkpoint == EXACT
    with pytest.raises(ValueError, match="does not take option"):
        make_method("s1+pointnetgpd", sensed=True)


def test_the_benchmark_through_a_sensor_scores_with_the_sensed_network_and_keys_it(tmp_path):
    """Observed through the RealSense model, gpd+s2 scores with the sensed E-RNet; the scene log's key
    names it, so a log scored by another network is not resumed; exact depth keeps today's key."""
    objects = tiny_object_set()[:3]
    config = DeclutterConfig(camera=CameraConfig(width=320, height=240), nthread=1, extra_attempts=0,
                             sensor="realsense", masks="truth")
    run_benchmark("gpd+s2", scenes=1, out=tmp_path, object_assets=objects, n_objects=2, config=config, progress=False)
    docs = [json.loads(p.read_text()) for p in sorted(tmp_path.rglob("*.json"))]
    keys = [d["key"] for d in docs if isinstance(d, dict) and isinstance(d.get("key"), dict)]
    assert len(keys) == 1 and keys[0]["network"] == SENSED and keys[0]["view"] == "realsense+truth"
    exact = dataclasses.replace(config, sensor="exact", masks="truth")
    assert "network" not in run_key("gpd+s2", {}, 2, objects, exact)
    assert run_key("gpd+s2", {}, 2, objects, config, network=EXACT) != run_key("gpd+s2", {}, 2, objects, config,
                                                                              network=SENSED)


def test_a_student_of_distillation_sets_records_its_sensor(tmp_path):
    from train.distill import data_sensor

    made = tmp_path / "d"
    made.mkdir()
    (made / "distill.json").write_text('{"distill": {"sensor": "kinect"}, "gripper": {}}')
    other = tmp_path / "e"
    other.mkdir()
    (other / "distill.json").write_text('{"distill": {"sensor": "stereo"}, "gripper": {}}')
    assert data_sensor(str(made)) == "kinect" and data_sensor([str(made), str(tmp_path)]) == "kinect"
    assert data_sensor(str(tmp_path)) is None  # labelled data, not a distillation set
    with pytest.raises(ValueError, match="teach different sensors"):
        data_sensor([str(made), str(other)])
    assert ernet.load_default_model(sensed=True) is not ernet.load_default_model()
