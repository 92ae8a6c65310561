"""Labelling beyond one process: job-array shards and Ray workers write what one serial run writes.

Real scenes, real Stage 1, real trials and real files on the tiny object set (the settings of
tests/test_label.py); the Ray tests start a real local cluster of 2 CPUs and skip without ray.
"""

from __future__ import annotations

import os

import numpy as np
import pytest

from envs.objects import tiny_object_set
from sgjax.stage1.pipeline import Stage1
from train import dataset
from train.label import Labellers, check_shard, label, parse_shard, pending_blocks, scene_blocks

from test_label import CONFIG  # the same tiny labelling set (tests/ is on sys.path: no __init__.py)

FIRST, END = 1, 6  # scenes 1..5: blocks [1, 3), [3, 5), [5, 6), the grid anchored at the first scene
BLOCKS = [(1, 3), (3, 5), (5, 6)]


@pytest.fixture(scope="module")
def setup(small_db):
    return tiny_object_set(), Labellers.make(CONFIG, Stage1(small_db, CONFIG.stage1))


@pytest.fixture(scope="module")
def serial(setup, tmp_path_factory):
    """Scenes 1..5 labelled by one plain serial run -> its directory."""
    objects, labellers = setup
    out = tmp_path_factory.mktemp("serial")
    label(out, END, CONFIG, objects=objects, stage1=labellers.stage1, progress=False, first_scene=FIRST)
    return out


def _files(directory) -> list[str]:
    return sorted(n for n in os.listdir(directory) if n.startswith("scenes-"))


def assert_same_samples(directory, reference) -> None:
    """The same shard files, and every sample field and scene cloud equal, read back with the dataset's
    reader (the .npz zip members carry timestamps, so the files' bytes may differ)."""
    assert _files(directory) == _files(reference)
    for name in _files(reference):
        if not name.endswith(dataset.SHARD_SUFFIX):
            continue
        (got, got_clouds), (want, want_clouds) = (dataset.read_label_shard(os.path.join(d, name)) for d in (directory, reference))
        assert set(got) == set(want)
        for key in want:
            np.testing.assert_array_equal(got[key], want[key], err_msg=f"{name}: {key}")
        assert len(got_clouds) == len(want_clouds)
        for a, b in zip(got_clouds, want_clouds):
            np.testing.assert_array_equal(a, b, err_msg=f"{name}: cloud")


def test_blocks_are_a_fixed_grid_dealt_round_robin(tmp_path):
    assert scene_blocks(FIRST, END, 2) == BLOCKS
    assert scene_blocks(0, 4, 4) == [(0, 4)] and scene_blocks(3, 4, 4) == [(3, 4)]
    assert pending_blocks(tmp_path / "fresh", END, CONFIG, FIRST) == BLOCKS  # a fresh directory: the grid
    assert pending_blocks(tmp_path, END, CONFIG, FIRST, shard=(0, 2)) == [(1, 3), (5, 6)]
    assert pending_blocks(tmp_path, END, CONFIG, FIRST, shard=(1, 2)) == [(3, 5)]
    assert pending_blocks(tmp_path, END, CONFIG, FIRST, shard=(3, 4)) == []  # more workers than blocks
    # A block partly on disk (a shorter earlier run): only its missing scenes are pending.
    (tmp_path / "scenes-000001-000002.npz").write_bytes(b"")
    assert pending_blocks(tmp_path, END, CONFIG, FIRST) == [(2, 3), (3, 5), (5, 6)]
    assert parse_shard("1/2") == (1, 2) and parse_shard(" 0/1 ") == (0, 1) and check_shard((2, 3)) == (2, 3)
    for bad, message in (("3/2", "0 <= K < N"), ("2/2", "0 <= K < N"), ("0/0", "N >= 1"), ("1", "K/N"), ("-1/2", "K/N"), ("a/b", "K/N")):
        with pytest.raises(ValueError, match=message):
            parse_shard(bad)


def test_two_shard_workers_write_what_one_serial_run_writes(setup, serial, tmp_path):
    """Workers 1/2 and 0/2 (in that order: scenes labelled out of order) into one directory."""
    objects, labellers = setup
    common = dict(objects=objects, stage1=labellers.stage1, progress=False, first_scene=FIRST)
    label(tmp_path, END, CONFIG, shard=(1, 2), **common)
    assert [n for n in _files(tmp_path) if n.endswith(".npz")] == ["scenes-000003-000005.npz"]  # only its block
    summary = label(tmp_path, END, CONFIG, shard=(0, 2), **common)
    assert summary.scenes == END - FIRST  # the summary covers both workers' shards
    assert_same_samples(tmp_path, serial)
    assert not [n for n in os.listdir(tmp_path) if ".tmp-" in n]
    with pytest.raises(ValueError, match="0 <= K < N"):
        label(tmp_path, END, CONFIG, shard=(2, 2), **common)
    # A worker without a block of its own (4 workers, 3 blocks) finishes quietly, before anyone else.
    idle = label(tmp_path / "idle", END, CONFIG, shard=(3, 4), **common)
    assert idle.scenes == 0 and os.listdir(tmp_path / "idle") == ["label_config.json"]


@pytest.mark.parametrize(
    "options, message",
    [
        (["--scenes", "4", "--shard", "3/2"], "0 <= K < N"),
        (["--scenes", "4", "--shard", "two"], "--shard must be K/N"),
        (["--scenes", "4", "--shard", "0/2", "--ray"], "give one of them"),
        (["--scenes", "4", "--workers", "2"], "needs --ray"),
        (["--scenes", "5:3"], "no scenes to label"),
        (["--scenes", "2:x"], "--scenes must be N"),
        (["--scenes", "2:5", "--first-scene", "1"], "give the first scene once"),
    ],
)
def test_label_scale_out_options_are_checked_before_any_work(tmp_path, capsys, options, message):
    from sgjax_cli import main

    assert main(["label", "--out", str(tmp_path / "labels"), *options]) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "labels").exists()


# --------------------------------------------------------------------------------------------------
# Ray: a real local cluster of 2 CPUs (skipped without ray).


@pytest.fixture(scope="module")
def ray_cluster():
    ray = pytest.importorskip("ray")
    # Workers inherit this process's environment ($SGJAX_CACHE, XLA_FLAGS): the same cache, the same code.
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    yield ray
    ray.shutdown()


def test_ray_workers_write_what_one_serial_run_writes(ray_cluster, small_db, serial, tmp_path):
    from train.label_ray import label_ray

    run = label_ray(tmp_path, END, CONFIG, db=small_db, workers=2, first_scene=FIRST, progress=False)
    assert run.workers == 2 and run.requeued == 0 and run.skipped == 0
    assert sorted((r["start"], r["end"]) for r in run.shards) == BLOCKS
    workers = {r["worker"] for r in run.shards}
    assert len(workers) == 2 and not any(w.endswith(f":{os.getpid()}") for w in workers)  # two actor processes
    assert run.trials > 0 and run.summary.scenes == END - FIRST
    assert_same_samples(tmp_path, serial)
    # Resumable: asking again finds every block on disk and starts nothing.
    again = label_ray(tmp_path, END, CONFIG, db=small_db, workers=2, first_scene=FIRST, progress=False)
    assert again.shards == [] and again.workers == 0 and again.summary == run.summary


def test_a_worker_dying_mid_block_loses_and_duplicates_nothing(ray_cluster, small_db, serial, tmp_path):
    """One actor exits (os._exit) after its first scene, before writing: its block is queued again for a
    fresh actor, and the directory ends up with every block exactly once and the serial run's samples."""
    from train.label_ray import label_ray

    out, marker = tmp_path / "out", tmp_path / "crashed"
    run = label_ray(out, END, CONFIG, db=small_db, workers=2, first_scene=FIRST, progress=False, crash_marker=marker)
    assert marker.exists() and run.requeued == 1 and run.restarts == 1
    assert sorted((r["start"], r["end"]) for r in run.shards) == BLOCKS  # each block written exactly once
    assert_same_samples(out, serial)
    assert not [n for n in os.listdir(out) if ".tmp-" in n]
    dead = marker.read_text().split()[0]
    assert not any(r["worker"].endswith(f":{dead}") for r in run.shards)


def test_ray_errors_are_clear(ray_cluster, small_db, tmp_path):
    from train.label_ray import label_ray

    with pytest.raises(ValueError, match="workers must be >= 1"):
        label_ray(tmp_path, END, CONFIG, db=small_db, workers=0, progress=False)
    with pytest.raises(ValueError, match="first_scene"):
        label_ray(tmp_path, 1, CONFIG, db=small_db, first_scene=1, progress=False)
