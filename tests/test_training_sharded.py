"""Data-parallel training (`TrainConfig.devices`, `sgjax train --devices N`): the same losses and
parameters as on one device, checkpoints that move between device counts, one compilation per device
count, and clear errors for settings that cannot work.

JAX fixes its device count when it starts, so the two-device half runs in a fresh interpreter (this
file run as a script) with XLA_FLAGS=--xla_force_host_platform_device_count=2, two CPU devices; this
process keeps its one device, as a user resuming a two-device run on a smaller machine would.
"""

from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys
from pathlib import Path

import jax
import numpy as np
import pytest
from flax import nnx

from sgjax.stage2 import ernet
from sgjax.stage2.ernet import ERNetConfig
from train import dataset, trainer

# The settings of tests/test_training.py, so that when both run in one session this process reuses
# that module's compiled steps (`make_steps` is cached by graphdef and `step_config`).
TINY = ERNetConfig.tiny(noise_std=0.0, backbone=dataclasses.replace(ERNetConfig.tiny().backbone, sampler="random"))
CONFIG = trainer.TrainConfig(epochs=2, batch_size=16, lr=1e-2, held_out_fraction=0.25, model=TINY, prefetch=2)
N_SAMPLES = 48  # 3 training batches per epoch: enough steps for the sums and the resume to matter

LOSS_KEYS = ("loss", "eval_loss", "refine_loss", "accuracy", "precision", "recall", "samples")


def _samples() -> dict[str, np.ndarray]:
    return dataset.synthetic_samples(N_SAMPLES, seed=0)


def _interrupt_in_second_epoch(epoch: int, step: int) -> None:
    # After epoch 1's checkpoint: the run dies as a killed one would, with one epoch on disk.
    if epoch == 1 and step == 1:
        raise KeyboardInterrupt


def _interrupted_run(samples, run_dir: Path, config: trainer.TrainConfig) -> None:
    try:
        trainer.train(samples, run_dir, config, progress=False, on_step=_interrupt_in_second_epoch)
    except KeyboardInterrupt:
        pass
    assert sorted(os.listdir(run_dir / "checkpoints")) == ["1"]


def _leaves(model: nnx.Module) -> list[np.ndarray]:
    return [np.asarray(x) for x in jax.tree.leaves(nnx.state(model))]


def _child(work: Path) -> None:
    """The two-device half, in a process started with two CPU devices: writes work/child.json and the
    parameters of its runs (work/<name>.npz)."""
    assert len(jax.devices()) == 2, jax.devices()
    samples, two = _samples(), dataclasses.replace(CONFIG, devices=2)
    out: dict = {}
    result = trainer.train(samples, work / "two", two, progress=False)
    out["two_history"] = result.history
    out["two_model_devices"] = sorted({d.id for x in jax.tree.leaves(nnx.state(result.model)) for d in x.devices()})
    np.savez(work / "two.npz", *_leaves(result.model))
    _interrupted_run(samples, work / "two_interrupted", two)  # resumed by the parent, on one device
    # The parent's one-device checkpoint, resumed on two devices.
    resumed = trainer.train(samples, work / "one_interrupted", two, progress=False)
    out["one_then_two_history"] = resumed.history
    np.savez(work / "one_then_two.npz", *_leaves(resumed.model))
    graphdef, _ = nnx.split(result.model)
    _, train_step, eval_step = trainer.make_steps(graphdef, two)
    out["compiled"] = [train_step._cache_size(), eval_step._cache_size()]
    try:
        trainer.train(samples, work / "four", dataclasses.replace(CONFIG, devices=4), progress=False)
    except ValueError as exc:
        out["too_many"] = str(exc)
    (work / "child.json").write_text(json.dumps(out))


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> dict:
    work = tmp_path_factory.mktemp("sharded")
    samples = _samples()
    one = trainer.train(samples, work / "one", CONFIG, progress=False)
    _interrupted_run(samples, work / "one_interrupted", CONFIG)  # resumed by the child, on two devices
    # The child sees two CPU devices; the suite's own XLA_FLAGS (tests/conftest.py: cheaper codegen) stay.
    env = {**os.environ, "XLA_FLAGS": (os.environ.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=2").strip()}
    done = subprocess.run(
        [sys.executable, __file__, str(work)], env=env, capture_output=True, text=True, timeout=900
    )
    assert done.returncode == 0, done.stderr[-3000:]
    child = json.loads((work / "child.json").read_text())
    two_then_one = trainer.train(samples, work / "two_interrupted", CONFIG, progress=False)
    return {
        "work": work,
        "one": one,
        "child": child,
        "two": list(np.load(work / "two.npz").values()),
        "one_then_two": list(np.load(work / "one_then_two.npz").values()),
        "two_then_one": two_then_one,
    }


def _assert_histories_close(a: list[dict], b: list[dict]) -> None:
    assert [r["epoch"] for r in a] == [r["epoch"] for r in b]
    for ra, rb in zip(a, b, strict=True):
        for split in ("train", "held_out"):
            for key in LOSS_KEYS:
                x, y = ra[split][key], rb[split][key]
                if x is None or y is None:  # undefined (e.g. precision with no positive call): on both
                    assert x is y, (ra["epoch"], split, key, x, y)
                else:
                    np.testing.assert_allclose(x, y, rtol=1e-4, err_msg=f"epoch {ra['epoch']} {split} {key}")
            np.testing.assert_allclose(ra[split]["refine_accuracy"], rb[split]["refine_accuracy"], rtol=1e-4)
        np.testing.assert_allclose(ra["held_out"]["judgement"]["auc"], rb["held_out"]["judgement"]["auc"], rtol=1e-4)


def _assert_params_close(a: list[np.ndarray], b: list[np.ndarray]) -> None:
    assert len(a) == len(b)
    for x, y in zip(a, b, strict=True):
        np.testing.assert_allclose(x, y, rtol=1e-4, atol=1e-5)


def test_two_devices_train_as_one(runs):
    """Batches split over two devices: the same per-epoch losses and metrics (train and the sharded
    held-out evaluation) and the same parameters, up to the order of float sums."""
    _assert_histories_close(runs["child"]["two_history"], runs["one"].history)
    assert runs["one"].history[-1]["train"]["loss"] < runs["one"].history[0]["train"]["loss"]  # it did train
    _assert_params_close(runs["two"], _leaves(runs["one"].model))
    # One compilation of each step on the mesh, shared by a run resumed there from a one-device
    # checkpoint (restored onto the same replicated sharding).
    assert runs["child"]["compiled"] == [1, 1]
    # The returned model lives on one device, as a one-device run's does.
    assert runs["child"]["two_model_devices"] == [0]


def test_checkpoints_move_between_device_counts(runs):
    """Interrupted after epoch 1 on two devices and resumed on one (in this one-device process), and
    the other way round: both end where the uninterrupted one-device run ends."""
    one = runs["one"]
    _assert_histories_close(runs["two_then_one"].history, one.history)
    _assert_params_close(_leaves(runs["two_then_one"].model), _leaves(one.model))
    _assert_histories_close(runs["child"]["one_then_two_history"], one.history)
    _assert_params_close(runs["one_then_two"], _leaves(one.model))
    # The model loader reads a two-device run here too, exactly as it was saved.
    model, meta = ernet.load_model(runs["work"] / "two")
    assert meta["epochs_done"] == 2
    for a, b in zip(_leaves(model), runs["two"], strict=True):
        np.testing.assert_array_equal(a, b)
    stored = json.loads((runs["work"] / "two" / "metrics.json").read_text())["train_config"]
    assert stored["devices"] == 2


def test_device_count_is_not_part_of_the_run_or_the_compilation():
    two = dataclasses.replace(CONFIG, devices=2)
    assert two.resume_key() == CONFIG.resume_key() and "devices" not in CONFIG.resume_key()
    assert trainer.step_config(two) == trainer.step_config(CONFIG)


def test_bad_device_settings_are_named(runs, tmp_path, capsys):
    with pytest.raises(ValueError, match="batch_size 15 is not divisible by devices=2"):
        dataclasses.replace(CONFIG, batch_size=15, devices=2)
    with pytest.raises(ValueError, match="devices must be >= 1"):
        dataclasses.replace(CONFIG, devices=0)
    # More devices than JAX sees: the count, and the CPU hint, before any data is read.
    with pytest.raises(ValueError, match=r"1 cpu device\(s\).*XLA_FLAGS=--xla_force_host_platform_device_count=2"):
        trainer.train(tmp_path / "no-data", tmp_path / "run", dataclasses.replace(CONFIG, devices=2), progress=False)
    assert "2 cpu device(s)" in runs["child"]["too_many"] and "device_count=4" in runs["child"]["too_many"]
    import sgjax_cli as cli

    args = ["train", "--data", str(tmp_path), "--out", str(tmp_path / "run"), "--model", "tiny", "--quiet"]
    assert cli.main([*args, "--batch-size", "15", "--devices", "2"]) == 2
    assert "not divisible by devices=2" in capsys.readouterr().err
    assert cli.main([*args, "--batch-size", "16", "--devices", "2"]) == 2
    assert "xla_force_host_platform_device_count=2" in capsys.readouterr().err


if __name__ == "__main__":
    _child(Path(sys.argv[1]))
