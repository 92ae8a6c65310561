"""The labelling pipeline on the tiny object set: real scenes, real Stage 1, real trials."""

from __future__ import annotations

import dataclasses
import json
import os

import numpy as np
import pytest

from envs.objects import tiny_object_set
from sgjax.stage1.pipeline import Stage1
from train import dataset
from train import sources
from train.label import Labellers, LabelConfig, label, label_scene, labelled_scene, scene_seed, summarize

CONFIG = LabelConfig(
    n_objects=3,
    targets_per_scene=2,
    per_source=(("stage1", 2), ("stage1_paper", 2), ("gpd", 2), ("perturbed", 2)),
    scenes_per_shard=2,
    object_set="tiny",
    held_out_objects=("tiny/cylinder",),
    held_out_object_every=2,  # scene 1 is built around the cylinder
)


@pytest.fixture(scope="module")
def setup(small_db):
    return tiny_object_set(), Labellers.make(CONFIG, Stage1(small_db, CONFIG.stage1))


def test_scene_seeds_are_distinct_and_stable():
    seeds = [scene_seed(0, i) for i in range(100)]
    assert len(set(seeds)) == 100
    assert seeds == [scene_seed(0, i) for i in range(100)]
    assert scene_seed(1, 0) != scene_seed(0, 0)


def test_samples_hold_what_training_needs(setup):
    objects, labellers = setup
    samples, cloud, stats = label_scene(0, objects, labellers, CONFIG)
    n = len(samples["label"])
    assert 1 <= n <= CONFIG.targets_per_scene * CONFIG.grasps_per_target
    checked = dataset.validate(samples, fields=dataset.LABEL_FIELDS)  # raises on any wrong field, dtype or shape
    assert stats["trials"] == 4 * n  # each grasp and its 3 refinements
    assert sum(stats["outcomes"].values()) == stats["trials"]
    assert (checked["scene_seed"] == scene_seed(CONFIG.seed, 0)).all()
    # Scene 0 is a training scene: no held-out object in it, several sources, each on record.
    assert not checked["held_out_object"].any() and "tiny/cylinder" not in set(checked["object_name"])
    assert set(checked["object_name"]) <= {o.name for o in objects}
    assert len(set(checked["source"])) >= 3 and set(checked["source"]) <= set(range(len(sources.SOURCES)))
    # The labels agree with the recorded outcomes (0 is SUCCESS).
    np.testing.assert_array_equal(checked["label"] == 1, checked["outcome"] == 0)
    np.testing.assert_array_equal(checked["refine_labels"] == 1, checked["refine_outcomes"] == 0)
    # Poses are rigid transforms and widths within the gripper's stroke.
    rot = checked["pose"][:, :3, :3]
    assert np.allclose(rot @ rot.transpose(0, 2, 1), np.eye(3), atol=1e-4)
    assert ((checked["width"] >= 0) & (checked["width"] <= CONFIG.spec.max_opening)).all()
    # The scene's Stage-2 cloud: real world points on the table, within the workspace crop.
    assert len(cloud) > 1000 and np.isfinite(cloud).all() and cloud[:, 2].min() > -0.01
    assert (checked["source"] == sources.source_index("perturbed")).any()


def test_held_out_object_scenes_target_only_held_out_objects(setup):
    objects, labellers = setup
    samples, _, stats = label_scene(1, objects, labellers, CONFIG)
    assert stats["held_out_objects"] and len(samples["label"]) > 0
    assert set(samples["object_name"]) == {"tiny/cylinder"} and samples["held_out_object"].all()


def test_perturbation_moves_and_turns_within_its_ranges():
    rng = np.random.default_rng(0)
    spec = CONFIG.spec
    poses = np.tile(np.eye(4), (500, 1, 1))
    poses[:, :3, 3] = rng.normal(size=(500, 3))
    moved = sources.perturb(poses, rng, spec, sources.Perturbation((0.005, 0.02), (5.0, 20.0)))
    rel = np.einsum("nji,njk->nik", poses[:, :3, :3], moved[:, :3, :3])
    angle = np.rad2deg(np.arccos(np.clip((np.trace(rel, axis1=1, axis2=2) - 1) / 2, -1, 1)))
    assert angle.min() >= 5.0 - 1e-6 and angle.max() <= 20.0 + 1e-6
    centre = lambda p: p[:, :3, 3] + p[:, :3, 2] * 0.5 * spec.finger_length  # noqa: E731
    shift = np.linalg.norm(centre(moved) - centre(poses), axis=1)
    assert shift.min() >= 0.005 - 1e-9 and shift.max() <= 0.02 + 1e-9
    assert np.allclose(moved[:, :3, :3] @ moved[:, :3, :3].transpose(0, 2, 1), np.eye(3), atol=1e-9)


def test_paper_filters_drop_only_the_extra_judgement():
    paper = sources.paper_filters(CONFIG.stage1)
    assert paper.filter.hidden_contacts == "accept" and paper.filter.shadow_depth == 0.0
    assert paper.filter.min_points == CONFIG.stage1.filter.min_points  # (ii) and (iii) as the paper's
    assert paper.filter.max_normal_angle_deg == CONFIG.stage1.filter.max_normal_angle_deg


@pytest.fixture(scope="module")
def whole(setup, tmp_path_factory):
    """Scenes 0 and 1 labelled in one run -> (directory, summary)."""
    objects, labellers = setup
    out = tmp_path_factory.mktemp("whole")
    return out, label(out, 2, CONFIG, objects=objects, stage1=labellers.stage1, progress=False)


def test_resume_gives_the_same_data_as_one_run(setup, whole, tmp_path):
    objects, labellers = setup
    stage1 = labellers.stage1
    # An "interrupted" run: scene 0 only, then a leftover temporary file, then the full request.
    label(tmp_path, 1, CONFIG, objects=objects, stage1=stage1, progress=False)
    (tmp_path / "scenes-000001-000002.npz.tmp-dead").write_bytes(b"half a file")
    summary = label(tmp_path, 2, CONFIG, objects=objects, stage1=stage1, progress=False)
    a, b = dataset.read_shards(whole[0]), dataset.read_shards(tmp_path)
    for key in dataset.SAMPLE_FIELDS:
        np.testing.assert_array_equal(a[key], b[key])  # same samples and crops, none lost or duplicated
    assert summary.scenes == 2 and summary.samples == len(a["label"])
    assert sorted(p for p in os.listdir(tmp_path) if p.endswith(".npz")) == [
        "scenes-000000-000001.npz",
        "scenes-000001-000002.npz",
    ]
    # Asking again does nothing new.
    before = os.path.getmtime(tmp_path / "scenes-000001-000002.npz")
    label(tmp_path, 2, CONFIG, objects=objects, stage1=stage1, progress=False)
    assert os.path.getmtime(tmp_path / "scenes-000001-000002.npz") == before


def test_a_series_continued_in_a_second_directory_reads_as_one(setup, whole, tmp_path):
    objects, labellers = setup
    first, second = tmp_path / "first", tmp_path / "second"
    label(first, 1, CONFIG, objects=objects, stage1=labellers.stage1, progress=False)
    label(second, 2, CONFIG, objects=objects, stage1=labellers.stage1, progress=False, first_scene=1)
    assert [p for p in os.listdir(second) if p.endswith(".npz")] == ["scenes-000001-000002.npz"]
    a, b = dataset.read_shards(whole[0]), dataset.read_shards([first, second])
    for key in dataset.SAMPLE_FIELDS:
        np.testing.assert_array_equal(a[key], b[key])
    with pytest.raises(dataset.DatasetError, match="same scenes"):
        dataset.read_shards([whole[0], second])  # scene 1 twice
    with pytest.raises(ValueError, match="first_scene"):
        label(second, 1, CONFIG, objects=objects, stage1=labellers.stage1, progress=False, first_scene=1)


def test_summary_counts_trials_and_positives(whole):
    out, summary = whole
    samples = dataset.read_shards(out)
    assert summary.samples == len(samples["label"])
    valid = samples["valid"]
    assert summary.positives == pytest.approx(samples["label"][valid].mean())
    assert summary.trials == 4 * summary.samples  # each sample is a grasp and its 3 refinements
    assert summary.trials == sum(summary.outcomes.values())
    assert summarize(out) == summary
    # Per-source counts add up to the valid samples, and the held-out scene's samples are counted.
    assert sum(n for n, _ in summary.per_source.values()) == summary.valid_samples
    assert summary.held_out_object_samples == int((valid & samples["held_out_object"]).sum()) > 0


def test_crops_are_the_planners_crops_of_the_stored_cloud(whole):
    """A cropped sample equals `crop_regions` on the stored scene cloud, and the crop cache returns the same."""
    from sgjax.stage2.crops import crop_regions

    out, _ = whole
    path = dataset.shard_paths(out)[0]
    labels, clouds = dataset.read_label_shard(path)
    cropped = dataset.read_shards(out)  # fills the cache
    again = dataset.read_shards(out)  # read from the cache
    np.testing.assert_array_equal(cropped["region"], again["region"])
    i = 0
    cloud = clouds[labels["cloud_row"][i]]
    direct = crop_regions(cloud, labels["pose"][i : i + 1], labels["width"][i : i + 1], CONFIG.spec, dataset.REGION_POINTS)
    np.testing.assert_allclose(cropped["region"][i], np.asarray(direct.points)[0], atol=1e-6)
    np.testing.assert_array_equal(cropped["region_mask"][i], np.asarray(direct.mask)[0])
    assert cropped["region_mask"][i].sum() > 0


def test_other_config_in_the_same_directory_is_refused(setup, whole):
    objects, stage1 = setup
    other = dataclasses.replace(CONFIG, targets_per_scene=1)
    with pytest.raises(ValueError, match="different labelling config"):
        label(whole[0], 3, other, objects=objects, stage1=stage1.stage1, progress=False)
    saved = json.loads((whole[0] / "label_config.json").read_text())
    assert saved["targets_per_scene"] == 2


def test_bad_arguments(setup, tmp_path):
    objects, stage1 = setup
    with pytest.raises(ValueError, match="n_scenes"):
        label(tmp_path, 0, CONFIG, objects=objects, stage1=stage1.stage1, progress=False)
    with pytest.raises(ValueError, match="backend"):
        label(tmp_path, 1, CONFIG, objects=objects, stage1=stage1.stage1, backend="gpu", progress=False)
    with pytest.raises(ValueError, match="targets_per_scene"):
        LabelConfig(targets_per_scene=0)
    with pytest.raises(ValueError, match="unknown candidate source 'grasps'"):
        LabelConfig(per_source=(("grasps", 4),))
    for retired in ("stage1_relabel", "finalist"):  # codes of older directories, no longer drawn
        with pytest.raises(ValueError, match=f"{retired} only names samples of directories labelled by earlier"):
            LabelConfig(per_source=(("stage1", 4), (retired, 4)))
    with pytest.raises(ValueError, match="not in object set 'tiny'"):
        label(tmp_path, 1, dataclasses.replace(CONFIG, held_out_objects=("ycb/058_golf_ball",)), objects=objects, stage1=stage1.stage1, progress=False)
    with pytest.raises(dataset.DatasetError, match="no labelled shards"):
        summarize(tmp_path)


def test_swept_crops_hold_the_region_and_the_hands_path(whole):
    """The "swept" crop of a sample holds at least the points of its "enlarged" crop (a superset region)."""
    out, _ = whole
    enlarged, swept = dataset.read_shards(out, "enlarged"), dataset.read_shards(out, "swept")
    assert (swept["region_mask"].sum(1) >= enlarged["region_mask"].sum(1)).all()
    assert (swept["region_mask"].sum(1) > enlarged["region_mask"].sum(1)).any()
    with pytest.raises(dataset.DatasetError, match="unknown crop 'palm'"):
        dataset.read_shards(out, "palm")


def test_train_and_judge_on_labelled_scenes(whole, tmp_path, capsys):
    """E-RNet with the swept input trains on label shards; its held-out objects are judged every epoch,
    and `sgjax score-data` judges the run on the same directory."""
    from sgjax.stage2.ernet import ERNetConfig
    from sgjax_cli import main
    from train import score_data, trainer

    out, summary = whole
    model = ERNetConfig.tiny(hand_points=16)
    config = trainer.TrainConfig(epochs=1, batch_size=16, held_out_fraction=0.0, model=model, prefetch=1)
    result = trainer.train(out, tmp_path / "run", config, progress=False)
    objects = result.history[-1]["held_out_objects"]["judgement"]
    assert 0 < objects["samples"] <= summary.held_out_object_samples
    scored = score_data.score_directory(out, tmp_path / "run")
    assert scored["held_out_objects"]["samples"] == objects["samples"]
    assert scored["samples"] == objects["samples"] + scored["seen_objects"]["samples"]
    assert scored["classifier"]["samples"] == scored["samples"] and 0.0 <= scored["random_success"] <= 1.0
    assert set(scored["per_source"]) <= set(summary.per_source) and all("auc" in m for m in scored["per_source"].values())
    assert main(["score-data", "--data", str(out), "--model", str(tmp_path / "run")]) == 0
    printed = capsys.readouterr().out
    assert "| held out objects |" in printed and "| source stage1 |" in printed
    assert f"top Stage-1 grasp of each of {scored['top1_scenes']} scenes is picked among {scored['top1_per_scene']:.1f}" in printed
    assert main(["score-data", "--data", str(out), "--model", str(tmp_path / "run"), "--json"]) == 0
    keys = json.loads(capsys.readouterr().out)
    assert {"auc", "per_source", "ece", "top1_success", "random_success", "auc_interval", "top1_interval"} <= set(keys)
    assert keys["auc_interval"] is None or keys["auc_interval"][0] <= keys["auc"] <= keys["auc_interval"][1]
    assert main(["score-data", "--data", str(out), "--model", str(tmp_path / "run"), "--resamples", "-1"]) != 0
    assert main(["score-data", "--data", str(tmp_path / "nowhere"), "--model", str(tmp_path / "run")]) != 0
    # --held-out: only the scenes a run with that split holds out, and the held-out objects. Scene 0 holds
    # only held-out objects here, so a split that holds out scene 1 keeps every seen sample, one that
    # trains on it none.
    samples = dataset.read_shards(out)
    scene, seen = samples["scene_seed"], samples["valid"] & ~samples["held_out_object"]
    held_in = lambda s: np.isin(scene, scene[dataset.split_by_scene(scene, 0.5, s)[1]])
    for wanted in (True, False):
        seed = next(s for s in range(64) if len(np.unique(scene[held_in(s)])) == 1 and (held_in(s) & seen).any() == wanted)
        part = score_data.score_directory(out, tmp_path / "run", held_out=0.5, seed=seed)
        assert part["held_out_objects"]["samples"] == objects["samples"]
        assert (part["seen_objects"] or {}).get("samples", 0) == int((held_in(seed) & seen).sum()) == (seen.sum() if wanted else 0)
    assert main(["score-data", "--data", str(out), "--model", str(tmp_path / "run"), "--held-out", "0.5", "--seed", str(seed)]) == 0


def test_a_labelled_directory_replays_to_its_recorded_outcomes(setup, whole):
    """A labelled directory's config reads back, its scenes rebuild from their index alone
    (`labelled_scene`), and the simulator replays every recorded grasp to its recorded outcome."""
    from envs.trial import run_trials
    from train.label import labelled_scene, read_config

    objects, _ = setup
    assert read_config(whole[0]) == CONFIG  # the config back from label_config.json, nested ones included
    scene, _ = labelled_scene(0, objects, CONFIG)
    stored = dataset.read_label_shard(whole[0] / "scenes-000000-000002.npz")[0]
    stored = {k: v[stored["scene_index"] == 0] for k, v in stored.items()}
    names = [a.name for a in scene.assets]
    assert sorted(stored["object_name"]) and set(stored["object_name"]) <= set(names)
    rows = np.flatnonzero(stored["valid"] & (stored["source"] < 2))  # stage1 and stage1_paper
    assert len(rows) > 0
    targets = np.array([names.index(str(n)) for n in stored["object_name"][rows]])
    replayed = run_trials(scene, targets, stored["pose"][rows].astype(np.float64), stored["width"][rows], config=CONFIG.trial)
    np.testing.assert_array_equal(replayed.outcome, stored["outcome"][rows])


def test_a_labelled_directory_resumes_after_a_config_field_was_added(tmp_path):
    """A directory labelled before `SceneConfig.surroundings` existed holds a config without it: the same
    settings, so it resumes; other settings are still refused."""
    from train.label import CONFIG_FILE, check_out_dir

    saved = json.loads(LabelConfig().to_json())
    del saved["scene"]["surroundings"]
    (tmp_path / CONFIG_FILE).write_text(json.dumps(saved, sort_keys=True))
    check_out_dir(str(tmp_path), LabelConfig())
    with pytest.raises(ValueError, match="different labelling config"):
        check_out_dir(str(tmp_path), dataclasses.replace(LabelConfig(), n_objects=3))


def test_samples_through_a_sensor_see_its_noisy_frame(setup):
    """`LabelConfig.sensor`: the same scene and trials, the crops and candidates from the sensor's frame
    as the front end makes it (perfect masks)."""
    from envs import sensors

    objects, labellers = setup
    noisy = dataclasses.replace(CONFIG, sensor="realsense")
    assert json.loads(noisy.to_json())["sensor"] == "realsense" and LabelConfig.from_json(noisy.to_json()) == noisy
    samples, cloud, stats = label_scene(0, objects, labellers, noisy)
    _, exact_cloud, _ = label_scene(0, objects, labellers, CONFIG)
    assert len(samples["label"]) >= 1 and stats["trials"] == 4 * len(samples["label"])
    dataset.validate(samples, fields=dataset.LABEL_FIELDS)
    assert len(cloud) > 1000 and not np.array_equal(np.sort(cloud, axis=0), np.sort(exact_cloud, axis=0))
    # The observation: the table and the objects the front end found, labelled by object index.
    scene, _ = labelled_scene(0, objects, noisy)
    obs = sensors.sensed_observation(scene, noisy.camera, "realsense", seed=scene_seed(noisy.seed, 0))
    assert set(np.unique(obs.point_labels)) <= {-1, *range(scene.n_objects)}
    truth = sensors.sensed_observation(scene, noisy.camera, "exact", seed=scene_seed(noisy.seed, 0))
    for k in np.unique(obs.point_labels[obs.point_labels >= 0]):  # each object's points where the exact render has it
        assert np.linalg.norm(obs.object_cloud(k).mean(0) - truth.object_cloud(k).mean(0)) < 0.01
    with pytest.raises(ValueError, match="exact, kinect, realsense, stereo"):
        dataclasses.replace(CONFIG, sensor="sonar")


def test_a_sensor_frame_without_a_table_skips_the_scene(setup):
    """A frame the front end cannot use (here: a camera looking up, no depth at all) is recorded as a
    skipped scene; the run goes on."""
    from envs.camera import CameraConfig

    objects, labellers = setup
    skyward = CameraConfig(width=64, height=48, position=(0.0, 0.0, 0.5), lookat=(0.0, 0.0, 2.0), up=(0.0, 1.0, 0.0))
    samples, _, stats = label_scene(0, objects, labellers, dataclasses.replace(CONFIG, sensor="realsense", camera=skyward))
    assert stats["skipped"].startswith("front end: ") and "no valid pixel" in stats["skipped"]
    assert len(samples["label"]) == 0
