"""Distillation sets (`train.distill`): real scenes, the real front end and planner, the shipped E-RNet as the
teacher; soft labels through the dataset, the loss and training."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from envs import sensors
from envs.objects import tiny_object_set
from envs.scene import stage2_scene_cloud
from sgjax import presets
from sgjax.planner import Planner
from sgjax.stage2.ernet import evaluation_loss
from train import dataset
from train.distill import DistillConfig, distill
from train.label import labelled_scene, scene_seed

CONFIG = DistillConfig(n_objects=(3,), per_scene=12, perturbed=4, objects="tiny")


@pytest.fixture(scope="module")
def made(tmp_path_factory, small_db):
    """One shard of two tiny scenes, distilled twice into separate directories."""
    objects = tiny_object_set()
    planner = Planner(db=small_db, config=presets.get("default", scene_cloud=stage2_scene_cloud()))
    out = [tmp_path_factory.mktemp(f"distill{k}") for k in range(2)]
    written = [distill(0, 2, d, CONFIG, objects=objects, planner=planner, progress=False) for d in out]
    return out, written, objects, planner


def test_soft_cross_entropy_is_the_hard_one_on_hard_labels_and_is_not_smoothed_again():
    logits = jnp.asarray([[0.3, -1.2], [2.0, 0.5], [-0.4, 0.9]], jnp.float32)
    hard = jnp.asarray([1, 0, 1], jnp.int32)
    assert np.allclose(evaluation_loss(logits, hard, 0.0), evaluation_loss(logits, hard.astype(jnp.float32), 0.0), atol=1e-7)
    y = jnp.asarray([0.25, 0.9, 0.5], jnp.float32)
    log_p = np.log(np.exp(np.asarray(logits)) / np.exp(np.asarray(logits)).sum(1, keepdims=True))
    want = -np.mean((1 - np.asarray(y)) * log_p[:, 0] + np.asarray(y) * log_p[:, 1])
    # The label smoothing of hard labels is not applied to soft ones (a teacher's probabilities carry it).
    assert np.isclose(float(evaluation_loss(logits, y, 0.1)), want, atol=1e-6)
    # Its minimum lies at the teacher's probabilities: the gradient vanishes at logits that give p = y.
    at_y = jnp.stack([jnp.zeros(3), jnp.log(y / (1 - y))], -1)
    grad = jax.grad(lambda z: evaluation_loss(z, y, 0.1))(at_y)
    assert np.abs(np.asarray(grad)).max() < 1e-6


def test_soft_labels_outside_zero_one_are_refused(tmp_path):
    samples = {k: np.zeros((1, *f.shape), f.dtype) for k, f in dataset.LABEL_FIELDS.items()}
    samples["pose"][0] = np.eye(4)
    samples["label"] = np.asarray([0.4], np.float32)
    path = tmp_path / "scenes-000000-000001.npz"
    dataset.write_label_shard(path, samples, [np.zeros((5, 3), np.float32)])
    back, _ = dataset.read_label_shard(path)
    assert back["label"].dtype == np.float32 and back["label"][0] == np.float32(0.4)  # kept soft, not cast to int8
    samples["label"] = np.asarray([1.2], np.float32)
    with pytest.raises(dataset.DatasetError, match="outside"):
        dataset.write_label_shard(tmp_path / "bad.npz", samples, [np.zeros((5, 3), np.float32)])


def test_a_shard_holds_each_candidate_on_the_sensor_and_the_exact_cloud(made):
    (out, _), (written, _), objects, planner = made
    assert len(written) == 1
    samples, clouds = dataset.read_label_shard(written[0])
    rows = samples["cloud_row"]
    assert len(clouds) % 2 == 0 and len(clouds) >= 2
    for scene in range(len(clouds) // 2):  # sensor cloud 2k, exact cloud 2k + 1, the same candidates on both
        sensor, exact = rows == 2 * scene, rows == 2 * scene + 1
        assert sensor.sum() == exact.sum() > 0
        for field in ("pose", "width", "label", "refine_labels"):
            assert np.array_equal(samples[field][sensor], samples[field][exact])
    assert samples["label"].dtype == np.float32 and 0.0 <= samples["label"].min() and samples["label"].max() <= 1.0
    assert samples["label"].std() > 0.05  # the teacher tells the candidates apart
    # The student's view is the sensor's: its cloud is not the exact render's.
    assert not np.array_equal(clouds[0], clouds[1])


def test_the_labels_are_the_teachers_judgement_on_the_exact_render(made):
    (out, _), (written, _), objects, planner = made
    samples, _ = dataset.read_label_shard(written[0])
    index = int(samples["scene_index"][0])
    config = CONFIG.scenes()[index % len(CONFIG.n_objects)]
    seed = scene_seed(config.seed, index)
    scene, _ = labelled_scene(index, objects, config)
    exact = sensors.sense(scene, config.camera, CONFIG.sensor, seed=seed).truth.points
    mine = (samples["scene_index"] == index) & (samples["cloud_row"] % 2 == 1)
    judged = planner.judge(exact, samples["pose"][mine], samples["width"][mine], seed)
    assert judged["valid"].all()
    assert np.allclose(judged["eval_prob"], samples["label"][mine], atol=1e-6)
    # On the sensor's cloud of the same frame the teacher judges otherwise: there is something to learn.
    sensed = sensors.sense(scene, config.camera, CONFIG.sensor, seed=seed)
    points, _ = next(sensors.front_end(sensed, config.camera, CONFIG.masks).hypotheses()).table_and_objects()
    noisy = planner.judge(points, samples["pose"][mine], samples["width"][mine], seed)
    assert np.abs(noisy["eval_prob"] - judged["eval_prob"]).max() > 1e-3


def test_distilling_again_gives_the_same_shard_and_resumes(made):
    (first, second), (written, again), objects, planner = made
    a, ca = dataset.read_label_shard(written[0])
    b, cb = dataset.read_label_shard(again[0])
    assert all(np.array_equal(a[k], b[k]) for k in a) and all(np.array_equal(x, y) for x, y in zip(ca, cb))
    assert distill(0, 2, first, CONFIG, objects=objects, planner=planner, progress=False) == []  # nothing left to do
    with pytest.raises(ValueError, match="another config"):
        distill(0, 2, first, dataclasses.replace(CONFIG, per_scene=5), objects=objects, planner=planner, progress=False)


def test_bad_configs_are_refused():
    with pytest.raises(ValueError, match="exact"):
        DistillConfig(sensor="exact")
    with pytest.raises(ValueError, match="n_objects"):
        DistillConfig(n_objects=())
    with pytest.raises(ValueError):
        DistillConfig(sensor="lidar")


def test_a_network_trains_on_soft_labels(made, tmp_path):
    from train.trainer import TrainConfig, train
    from sgjax.stage2.ernet import ERNetConfig

    (out, _), _, _, _ = made
    config = TrainConfig(epochs=2, batch_size=16, lr=1e-3, held_out_fraction=0.0, model=ERNetConfig.tiny())
    result = train(str(out), str(tmp_path / "run"), config, progress=False)
    losses = [record["train"]["loss"] for record in result.history]
    assert all(np.isfinite(losses)) and losses[-1] < losses[0]


def test_the_judgement_of_soft_labels_without_trials(made):
    """A held-out part of a distillation set is judged as labelled data is (the trainer's held-out
    metrics): its samples ran no trial (outcome -1), so no top pick's outcome is counted."""
    from train.judgement import judge

    (out, _), _, _, _ = made
    data = dataset.read_shards(str(out))
    n = len(data["label"])
    score = np.linspace(0.0, 1.0, n)
    hard = np.round(data["label"])  # as the trainer's metrics take soft labels
    result = judge(score, hard, outcome=data["outcome"], scene=data["scene_seed"], resamples=0)
    assert (data["outcome"] == -1).all() and result["top1_outcomes"] == {}
    assert result["top1_scenes"] == len(np.unique(data["scene_seed"])) and 0.0 <= result["auc"] <= 1.0


def test_a_set_records_its_gripper_and_its_scenes_are_labellings(tmp_path):
    """A distillation set's directory names its gripper as a labelled one does (`sgjax train` trains for
    it), and its scenes are the ones `sgjax label` makes of the same options: the seen set's held-out
    objects left out, none for another set."""
    from sgjax.geometry.gripper import GripperSpec
    from sgjax.geometry.gripper_files import load_gripper
    from train import distill as distill_mod
    from train.label import data_gripper, label_config

    robotiq = load_gripper("robotiq-2f85")
    for name, spec in (("r", robotiq), ("d", GripperSpec())):
        (tmp_path / name).mkdir()
        distill_mod._check_out_dir(str(tmp_path / name), CONFIG, spec)
    assert data_gripper(str(tmp_path / "r")) == robotiq and data_gripper(str(tmp_path / "d")) == GripperSpec()
    seen = DistillConfig(n_objects=(10, 20))
    assert seen.scenes() == [label_config(objects="seen", seed=7, n_objects=n) for n in (10, 20)]
    assert seen.scenes()[0].held_out_objects and CONFIG.scenes()[0].held_out_objects == ()


def test_judge_gives_a_plans_own_scores(made):
    """`Planner.judge` on a plan's scene and seed repeats the scores the plan's Stage 2 gave its candidates."""
    _, _, objects, planner = made
    config = CONFIG.scenes()[0]
    scene, _ = labelled_scene(0, objects, config)
    obs = sensors.sense(scene, config.camera, "exact", seed=3).truth
    plan = planner.plan(obs.points, obs.point_labels, config.camera.position, seed=3)
    scores = plan.scores
    assert scores is not None and len(scores["eval_prob"])
    poses = np.stack([plan.candidates[o].poses[r] for o, r in zip(scores["object"], scores["object_candidate"])])
    widths = np.asarray([plan.candidates[o].widths[r] for o, r in zip(scores["object"], scores["object_candidate"])])
    judged = planner.judge(obs.points, poses, widths, seed=3)
    assert np.array_equal(judged["valid"], scores["valid"])
    assert np.allclose(judged["eval_prob"], scores["eval_prob"], atol=1e-6)
