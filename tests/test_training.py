"""Dataset format, split and batching; training: overfitting, outputs, checkpoints, exact resume."""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import nnx

from sgjax.stage2 import crops, ernet
from sgjax.stage2.ernet import ERNetConfig
from train import dataset, trainer

# Random centroid sampling (FPS is covered in test_ernet.py); no noise, which only slows overfitting.
TINY = ERNetConfig.tiny(noise_std=0.0, backbone=dataclasses.replace(ERNetConfig.tiny().backbone, sampler="random"))
CONFIG = trainer.TrainConfig(epochs=2, batch_size=16, lr=1e-2, held_out_fraction=0.25, model=TINY, prefetch=2)


@pytest.fixture(scope="module")
def samples():
    return dataset.synthetic_samples(96, seed=0)


# ---------------------------------------------------------------------------------------------
# Dataset.


def test_shard_round_trip(tmp_path, samples):
    first = dataset.select(samples, np.arange(0, 5))
    second = [{k: v[i] for k, v in samples.items()} for i in range(5, 8)]  # list of per-sample dicts
    dataset.write_shard(tmp_path / "b", first)
    dataset.write_shard(tmp_path / "a.npz", second)
    assert sorted(os.listdir(tmp_path)) == ["a.npz", "b.npz"]  # nothing temporary left behind
    back = dataset.read_shards(tmp_path)
    expected = dataset.select(samples, np.r_[5:8, 0:5])  # shards in file-name order
    for name, field in dataset.SAMPLE_FIELDS.items():
        assert back[name].dtype == field.dtype or field.dtype.kind == "U"
        np.testing.assert_array_equal(back[name], expected[name])


@pytest.mark.parametrize(
    "change,message",
    [
        (lambda s: s.update(region=s["region"][:, :100]), "'region' has shape"),
        (lambda s: s.pop("width"), r"missing fields \['width'\]"),
        (lambda s: s.update(extra=s["width"]), r"unknown fields \['extra'\]"),
        (lambda s: s["region"].__setitem__((0, 0, 0), np.nan) or s["region_mask"].__setitem__((0, 0), True), "NaN"),
        (lambda s: s["label"].__setitem__(1, 2), "'label' must hold 0 or 1"),
        (lambda s: s.update(label=s["label"].astype(np.float32)), "'label' must be int8"),
    ],
)
def test_malformed_samples_are_named(tmp_path, samples, change, message):
    bad = {k: v[:4].copy() for k, v in samples.items()}
    change(bad)
    with pytest.raises(dataset.DatasetError, match=message):
        dataset.write_shard(tmp_path / "bad", bad)
    assert not os.listdir(tmp_path)


def test_unreadable_shards(tmp_path):
    with pytest.raises(dataset.DatasetError, match="no .npz shards"):
        dataset.read_shards(tmp_path)
    (tmp_path / "broken.npz").write_bytes(b"not a zip file")
    with pytest.raises(dataset.DatasetError, match="broken.npz: not a readable"):
        dataset.read_shards(tmp_path)
    with pytest.raises(dataset.DatasetError, match="not a directory"):
        dataset.read_shards(tmp_path / "missing")


def test_split_by_scene_is_deterministic_and_disjoint():
    seeds = np.repeat(np.arange(1000), 3)
    train_idx, held_idx = dataset.split_by_scene(seeds, 0.2, seed=0)
    assert len(train_idx) + len(held_idx) == len(seeds)
    assert not set(seeds[train_idx]) & set(seeds[held_idx])
    assert 0.15 < len(held_idx) / len(seeds) < 0.25
    perm = np.random.default_rng(0).permutation(len(seeds))  # order or sharding does not matter
    _, held_perm = dataset.split_by_scene(seeds[perm], 0.2, seed=0)
    assert set(seeds[perm][held_perm]) == set(seeds[held_idx])
    _, other = dataset.split_by_scene(seeds, 0.2, seed=1)
    assert set(seeds[other]) != set(seeds[held_idx])


def test_batches_have_fixed_shape_and_cover_everything():
    batches = list(dataset.batch_indices(10, 4, np.random.default_rng(0)))
    assert [len(i) for i, _ in batches] == [4, 4, 4]
    weights = np.concatenate([w for _, w in batches])
    index = np.concatenate([i for i, _ in batches])
    assert weights.sum() == 10 and sorted(index[weights > 0].tolist()) == list(range(10))


def test_synthetic_samples_are_labelled_by_geometry(samples):
    assert samples["region_mask"].sum(1).min() > 0
    labels, refine = samples["label"], samples["refine_labels"]
    assert 0 < labels.mean() < 1 and (0 < refine.mean(0)).all() and (refine.mean(0) < 1).all()
    # Stored points lie in the enlarged region of the stored width.
    inside = crops.in_enlarged_region_local(samples["region"][:8], samples["width"][:8], CONFIG.spec)
    assert np.asarray(inside)[samples["region_mask"][:8]].all()
    again = dataset.synthetic_samples(96, seed=0)
    np.testing.assert_array_equal(again["region"], samples["region"])


# ---------------------------------------------------------------------------------------------
# Training.


def test_model_overfits_a_tiny_batch(samples):
    model = ernet.ERNet(TINY, rngs=nnx.Rngs(0))
    graphdef, params = nnx.split(model)
    tx, train_step, _ = trainer.make_steps(graphdef, CONFIG)
    params, opt_state = jax.device_put((params, tx.init(params)), jax.devices()[0])  # as `train` does
    weight = (np.arange(16) < 8).astype(np.float32)  # 8 real rows, 8 padding rows (weight 0)
    batch = jax.device_put(dataset.make_batch(samples, np.arange(16), weight))  # as the loader does
    losses, eval_losses = [], []
    for step in range(100):
        params, opt_state, stats = train_step(params, opt_state, batch, jax.random.key(step), jnp.float32(1.0))
        losses.append(float(stats["loss"] / stats["n"]))
        eval_losses.append(float(stats["eval_loss"] / stats["n"]))
    assert float(stats["n"]) == 8.0  # padding rows do not count
    assert np.mean(losses[-10:]) < 0.5 * losses[0], losses[::10]
    assert np.mean(eval_losses[-10:]) < 0.7 * eval_losses[0], eval_losses[::10]  # both heads learn
    assert train_step._cache_size() == 1


@pytest.fixture(scope="module")
def trained(samples, tmp_path_factory):
    run = tmp_path_factory.mktemp("run_a")
    return trainer.train(samples, run, CONFIG, progress=False)


def test_training_writes_metrics_curves_and_checkpoints(trained):
    run = trained.run_dir
    assert [r["epoch"] for r in trained.history] == [1, 2]
    for split in ("train", "held_out"):
        m = trained.history[-1][split]
        assert m["samples"] > 0 and np.isfinite(m["loss"]) and 0 <= m["accuracy"] <= 1
        assert len(m["refine_accuracy"]) == 3
    run = Path(run)
    record = json.loads((run / "metrics.json").read_text())
    assert record["history"] == trained.history
    rows = (run / "metrics.csv").read_text().strip().splitlines()
    assert len(rows) == 3 and rows[0].startswith("epoch,train_loss")
    assert (run / "curves.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert (run / "reliability.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert sorted(os.listdir(run / "checkpoints")) == ["1", "2"]
    # The held-out judgement: computed from the same scores as the summed metrics.
    judged = trained.history[-1]["held_out"]["judgement"]
    held = trained.history[-1]["held_out"]
    assert judged["samples"] == held["samples"] and 0.0 <= judged["auc"] <= 1.0 and 0.0 <= judged["ece"] <= 1.0
    assert sum(n for _, _, n in judged["reliability"]) == judged["samples"]
    assert len(judged["refine_auc"]) == 3 and "synthetic" not in judged["auc_per_source"]
    graphdef, _ = nnx.split(trained.model)
    _, train_step, eval_step = trainer.make_steps(graphdef, CONFIG)
    assert train_step._cache_size() == 1 and eval_step._cache_size() == 1  # compiled once


def test_checkpoint_round_trip(trained, samples):
    model, meta = ernet.load_model(trained.run_dir)
    assert meta["epochs_done"] == 2 and model.config == TINY and meta["history"] == trained.history
    graphdef, state = nnx.split(model)
    for a, b in zip(jax.tree.leaves(state), jax.tree.leaves(nnx.state(trained.model))):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    # Identical outputs (the trainer's compiled evaluation step on the same batch).
    _, _, eval_step = trainer.make_steps(graphdef, CONFIG)
    batch = jax.device_put(dataset.make_batch(samples, np.arange(16), np.ones(16, np.float32)))
    a = eval_step(state, batch, jax.random.key(0))
    b = eval_step(nnx.state(trained.model), batch, jax.random.key(0))
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    first, _ = ernet.load_model(trained.run_dir, epoch=1)
    assert not np.array_equal(np.asarray(first.eval_head.layers[0].kernel[...]), np.asarray(model.eval_head.layers[0].kernel[...]))
    with pytest.raises(FileNotFoundError):
        ernet.load_model(os.path.join(trained.run_dir, "nowhere"))


def test_interrupted_run_resumes_to_identical_result(trained, samples, tmp_path):
    def interrupt(epoch, step):
        if epoch == 1 and step == 1:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        trainer.train(samples, tmp_path, CONFIG, progress=False, on_step=interrupt)
    assert sorted(os.listdir(tmp_path / "checkpoints")) == ["1"]  # the finished epoch only
    resumed = trainer.train(samples, tmp_path, CONFIG, progress=False)
    assert resumed.history == trained.history
    for a, b in zip(jax.tree.leaves(nnx.state(resumed.model)), jax.tree.leaves(nnx.state(trained.model))):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    with pytest.raises(ValueError, match="other settings"):
        trainer.train(samples, tmp_path, trainer.TrainConfig(**{**CONFIG.__dict__, "lr": 5e-3}), progress=False)


def test_lr_decay_schedule_steps_and_resume(trained, samples, tmp_path):
    config = trainer.TrainConfig(**{**CONFIG.__dict__, "epochs": 4, "lr_decay_epochs": 2})
    scales = [config.lr_scale(epoch, step, 4) for epoch in range(4) for step in range(4)]
    assert scales[:9] == [1.0] * 9  # constant through epoch 2 and the first step of the decay
    assert scales[8 + 4] == pytest.approx(0.5) and scales[-1] == pytest.approx(0.5 * (1 + np.cos(np.pi * 7 / 8)))
    assert all(a > b for a, b in zip(scales[8:], scales[9:]))  # strictly falling in the decay
    with pytest.raises(ValueError, match="lr_decay_epochs"):
        trainer.TrainConfig(epochs=3, lr_decay_epochs=4)
    # The factor scales the real step: 0 leaves the parameters as they were, and never recompiles.
    graphdef, params = nnx.split(trained.model)
    tx, train_step, _ = trainer.make_steps(graphdef, config)
    params, opt_state = jax.device_put((params, tx.init(params)), jax.devices()[0])
    before = [np.asarray(x).copy() for x in jax.tree.leaves(params)]
    batch = jax.device_put(dataset.make_batch(samples, np.arange(16), np.ones(16, np.float32)))
    params, opt_state, _ = train_step(params, opt_state, batch, jax.random.key(0), jnp.float32(0.0))
    for a, b in zip(before, jax.tree.leaves(params)):
        np.testing.assert_array_equal(a, np.asarray(b))
    params, opt_state, _ = train_step(params, opt_state, batch, jax.random.key(0), jnp.float32(0.5))
    assert any(not np.array_equal(a, np.asarray(b)) for a, b in zip(before, jax.tree.leaves(params)))
    # A finished constant-rate run takes a decay when extended (epochs and the schedule's tail may change).
    shutil.copytree(trained.run_dir, tmp_path / "run")
    resumed = trainer.train(samples, tmp_path / "run", config, progress=False)
    assert [r["epoch"] for r in resumed.history] == [1, 2, 3, 4] and resumed.history[:2] == trained.history
    stored = json.loads((tmp_path / "run" / "metrics.json").read_text())["train_config"]
    assert stored["lr_decay_epochs"] == 2


def test_init_starts_from_another_runs_weights(trained, samples, tmp_path):
    """`init`: the run starts from that run's latest weights (a rate so small that one epoch keeps them
    to 1e-6, where a fresh start differs by the initialisation), is fingerprinted with it, and refuses
    a network of another config or a directory with no checkpoint."""
    config = trainer.TrainConfig(**{**CONFIG.__dict__, "epochs": 1, "lr": 1e-12, "weight_decay": 0.0})
    started = trainer.train(samples, tmp_path / "a", config, progress=False, init=trained.run_dir)
    fresh = trainer.train(samples, tmp_path / "b", config, progress=False)
    # The init run's weights as saved (the fixture's live arrays may have been donated by another test).
    saved = jax.tree.leaves(nnx.state(ernet.load_model(trained.run_dir)[0]))
    for a, b in zip(jax.tree.leaves(nnx.state(started.model)), saved, strict=True):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), atol=1e-6)
    assert any(np.abs(np.asarray(a) - np.asarray(b)).max() > 1e-3 for a, b in zip(jax.tree.leaves(nnx.state(fresh.model)), saved))
    with pytest.raises(ValueError, match="other settings"):  # resuming it without its init is another run
        trainer.train(samples, tmp_path / "a", trainer.TrainConfig(**{**config.__dict__, "epochs": 2}), progress=False)
    other = trainer.TrainConfig(**{**config.__dict__, "model": dataclasses.replace(TINY, hand_points=8)})
    with pytest.raises(ValueError, match="another config"):
        trainer.train(samples, tmp_path / "c", other, progress=False, init=trained.run_dir)
    with pytest.raises(ValueError, match="init"):
        trainer.train(samples, tmp_path / "d", config, progress=False, init=tmp_path / "nowhere")


def test_cli_train_synthetic_then_resume_and_bad_data(tmp_path, capsys):
    import sgjax_cli as cli

    data, out = tmp_path / "data", tmp_path / "run"
    args = ["train", "--data", str(data), "--out", str(out), "--model", "tiny", "--batch-size", "16", "--quiet"]
    assert cli.main([*args, "--synthetic", "48", "--epochs", "1", "--held-out", "0"]) == 0  # no held-out set
    assert (out / "metrics.json").exists() and len(dataset.read_shards(data)["label"]) == 48
    assert cli.main([*args, "--epochs", "2", "--held-out", "0"]) == 0  # continues after epoch 1
    assert [r["epoch"] for r in json.loads((out / "metrics.json").read_text())["history"]] == [1, 2]
    assert cli.main([*args, "--epochs", "2", "--held-out", "0.5"]) == 2  # other settings: refused
    assert "other settings" in capsys.readouterr().err
    (tmp_path / "empty").mkdir()
    assert cli.main(["train", "--data", str(tmp_path / "empty"), "--out", str(out), "--quiet"]) == 2
    assert "no .npz shards" in capsys.readouterr().err
