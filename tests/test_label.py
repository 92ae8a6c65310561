"""The labelling pipeline on the tiny object set: real scenes, real Stage 1, real trials."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest

from envs.objects import tiny_object_set
from sgjax.stage1.pipeline import Stage1
from train import dataset
from train.label import LabelConfig, label, label_scene, scene_seed, summarize

CONFIG = LabelConfig(n_objects=3, grasps_per_scene=4, scenes_per_shard=2, object_set="tiny")


@pytest.fixture(scope="module")
def setup(small_db):
    return tiny_object_set(), Stage1(small_db, CONFIG.stage1)


def test_scene_seeds_are_distinct_and_stable():
    seeds = [scene_seed(0, i) for i in range(100)]
    assert len(set(seeds)) == 100
    assert seeds == [scene_seed(0, i) for i in range(100)]
    assert scene_seed(1, 0) != scene_seed(0, 0)


def test_samples_hold_what_training_needs(setup):
    objects, stage1 = setup
    samples, stats = label_scene(0, objects, stage1, CONFIG)
    n = len(samples["label"])
    assert 1 <= n <= CONFIG.grasps_per_scene
    checked = dataset.validate(samples)  # raises on any wrong field, dtype or shape
    assert stats["trials"] == 4 * n  # each grasp and its 3 refinements
    assert sum(stats["outcomes"].values()) == stats["trials"]
    assert (checked["scene_seed"] == scene_seed(CONFIG.seed, 0)).all()
    assert set(checked["object_name"]) <= {o.name for o in objects}
    # Regions are in the grasp frame: real points lie near the closing region, around the origin.
    real = checked["region"][checked["region_mask"]]
    assert len(real) > 0 and np.abs(real).max() < 0.15
    assert np.all(checked["region"][~checked["region_mask"]] == 0)
    # Poses are rigid transforms and widths within the gripper's stroke.
    rot = checked["pose"][:, :3, :3]
    assert np.allclose(rot @ rot.transpose(0, 2, 1), np.eye(3), atol=1e-4)
    assert ((checked["width"] >= 0) & (checked["width"] <= CONFIG.spec.max_opening)).all()


@pytest.fixture(scope="module")
def whole(setup, tmp_path_factory):
    """Scenes 0 and 1 labelled in one run -> (directory, summary)."""
    objects, stage1 = setup
    out = tmp_path_factory.mktemp("whole")
    return out, label(out, 2, CONFIG, objects=objects, stage1=stage1, progress=False)


def test_resume_gives_the_same_data_as_one_run(setup, whole, tmp_path):
    objects, stage1 = setup
    # An "interrupted" run: scene 0 only, then a leftover temporary file, then the full request.
    label(tmp_path, 1, CONFIG, objects=objects, stage1=stage1, progress=False)
    (tmp_path / "scenes-000001-000002.npz.tmp-dead").write_bytes(b"half a file")
    summary = label(tmp_path, 2, CONFIG, objects=objects, stage1=stage1, progress=False)
    a, b = dataset.read_shards(whole[0]), dataset.read_shards(tmp_path)
    for key in dataset.SAMPLE_FIELDS:
        np.testing.assert_array_equal(a[key], b[key])  # same samples, none lost or duplicated
    assert summary.scenes == 2 and summary.samples == len(a["label"])
    assert sorted(p for p in os.listdir(tmp_path) if p.endswith(".npz")) == [
        "scenes-000000-000001.npz",
        "scenes-000001-000002.npz",
    ]
    # Asking again does nothing new.
    before = os.path.getmtime(tmp_path / "scenes-000001-000002.npz")
    label(tmp_path, 2, CONFIG, objects=objects, stage1=stage1, progress=False)
    assert os.path.getmtime(tmp_path / "scenes-000001-000002.npz") == before


def test_summary_counts_trials_and_positives(whole):
    out, summary = whole
    samples = dataset.read_shards(out)
    assert summary.samples == len(samples["label"])
    valid = samples["valid"]
    assert summary.positives == pytest.approx(samples["label"][valid].mean())
    assert summary.trials == 4 * summary.samples  # each sample is a grasp and its 3 refinements
    assert summary.trials == sum(summary.outcomes.values())
    assert summarize(out) == summary


def test_other_config_in_the_same_directory_is_refused(setup, whole):
    objects, stage1 = setup
    other = LabelConfig(n_objects=3, grasps_per_scene=5, scenes_per_shard=2, object_set="tiny")
    with pytest.raises(ValueError, match="different labelling config"):
        label(whole[0], 3, other, objects=objects, stage1=stage1, progress=False)
    saved = json.loads((whole[0] / "label_config.json").read_text())
    assert saved["grasps_per_scene"] == 4


def test_bad_arguments(setup, tmp_path):
    objects, stage1 = setup
    with pytest.raises(ValueError, match="n_scenes"):
        label(tmp_path, 0, CONFIG, objects=objects, stage1=stage1, progress=False)
    with pytest.raises(ValueError, match="backend"):
        label(tmp_path, 1, CONFIG, objects=objects, stage1=stage1, backend="gpu", progress=False)
    with pytest.raises(ValueError, match="grasps_per_scene"):
        LabelConfig(grasps_per_scene=0)
    with pytest.raises(dataset.DatasetError, match="no labelled shards"):
        summarize(tmp_path)
