"""The judgement metrics against their definitions (brute force) and known cases."""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest

from train.judgement import judge, random_success, reliability, roc_auc, top_outcomes, top_success


def _auc_brute(score, label):
    pos, neg = score[label], score[~label]
    pairs = (pos[:, None] > neg[None, :]) + 0.5 * (pos[:, None] == neg[None, :])
    return pairs.mean()


def test_auc_is_the_probability_a_positive_outranks_a_negative():
    rng = np.random.default_rng(0)
    for _ in range(20):
        n = int(rng.integers(2, 60))
        score = rng.integers(0, 6, n) / 5.0  # many ties
        label = rng.random(n) < 0.5
        if label.all() or not label.any():
            assert roc_auc(score, label) is None
            continue
        assert roc_auc(score, label) == pytest.approx(_auc_brute(score, label))
    assert roc_auc(np.array([0.1, 0.9]), np.array([0, 1])) == 1.0
    assert roc_auc(np.array([0.9, 0.1]), np.array([0, 1])) == 0.0


def test_calibration_error_and_reliability_table():
    score = np.array([0.05, 0.05, 0.95, 0.95])
    label = np.array([0, 0, 1, 1])
    ece, table = reliability(score, label)
    assert ece == pytest.approx(0.05) and [row[2] for row in table] == [2, 2]
    ece, _ = reliability(np.full(10, 0.8), np.r_[np.ones(5), np.zeros(5)])
    assert ece == pytest.approx(0.3)


def test_judge_per_source_collisions_refinement_and_top_grasp():
    score = np.array([0.9, 0.2, 0.8, 0.7, 0.6, 0.1])
    label = np.array([1, 0, 1, 0, 1, 0])
    source = np.array([0, 0, 1, 1, 0, 2])
    outcome = np.array([0, 2, 0, 1, 0, 3])
    scene = np.array([5, 5, 5, 6, 6, 6])
    refine = np.array([[0.9, 0.1, 0.5]] * 6)
    out = judge(score, label, source=source, outcome=outcome, scene=scene, refine_score=refine,
                refine_label=np.array([[1, 0, 1]] * 6), source_names=("a", "b", "c"))
    assert out["auc_per_source"]["a"] == 1.0 and out["auc_per_source"]["b"] == 1.0 and out["auc_per_source"]["c"] is None
    assert out["collision_score"] == pytest.approx((0.2 + 0.7) / 2)
    # Source 0 per scene: scene 5 picks 0.9 (success), scene 6 picks 0.6 (success).
    assert out["top1_success"] == 1.0
    assert top_success(score, label, scene) == pytest.approx(0.5)  # all sources: scene 6 picks the failed 0.7
    # A random source-0 grasp: scene 5 has 1 of 2 succeeding, scene 6 1 of 1.
    assert out["random_success"] == pytest.approx((0.5 + 1.0) / 2)
    assert random_success(label, scene) == pytest.approx((2 / 3 + 1 / 3) / 2)
    # Source 0 competes with 2 grasps in scene 5 and 1 in scene 6.
    assert out["top1_scenes"] == 2 and out["top1_per_scene"] == pytest.approx(1.5)
    # Their trial outcomes: both source-0 picks succeeded; over all sources scene 6's pick (0.7) collided.
    assert out["top1_outcomes"] == {"success": 2}
    assert top_outcomes(score, outcome, scene) == {"success": 1, "collision_pregrasp": 1}
    assert out["per_source"]["b"]["top1_outcomes"] == {"success": 1, "collision_pregrasp": 1}
    # Per source, every metric on that source's samples alone.
    b = out["per_source"]["b"]
    assert b["samples"] == 2 and b["auc"] == 1.0 and b["collision_score"] == pytest.approx(0.7)
    assert b["top1_success"] == pytest.approx(0.5)  # scene 5: its 0.8 succeeds; scene 6: its 0.7 fails
    assert out["per_source"]["c"]["auc"] is None and out["per_source"]["a"]["positive_rate"] == pytest.approx(2 / 3)
    assert out["refine_auc"] == [None, None, None]  # constant labels: undefined


def test_scene_intervals_resample_whole_scenes():
    """scene_interval: constant scenes give a point; independent scenes give about the binomial width;
    scenes whose samples all agree are one observation each, so the interval is as wide as their count
    allows, not as the sample count suggests."""
    from train.judgement import scene_interval, top_success

    rng = np.random.default_rng(0)
    # Every scene the same: every draw gives the same value.
    scene = np.repeat(np.arange(50), 4)
    score = np.tile([0.9, 0.1, 0.8, 0.2], 50)
    label = np.tile([1, 0, 1, 0], 50)
    assert scene_interval(lambda s, y, g: roc_auc(s, y), score, label, scene, 200) == [1.0, 1.0]
    # 400 scenes, the top grasp succeeding in half: about 0.5 +- 1.96 * sqrt(0.25 / 400) = +- 0.049.
    scene = np.repeat(np.arange(400), 3)
    score = rng.uniform(size=1200)
    label = rng.uniform(size=1200) < 0.5
    point = top_success(score, label, scene)
    lo, hi = scene_interval(top_success, score, label, scene, 500)
    assert lo < point < hi and 0.07 < hi - lo < 0.13
    # Clustered: 40 scenes of 30 samples sharing one label. Resampling samples would give a width of
    # ~0.05; by scene it is ~2 * 1.96 * sqrt(0.25 / 40) = 0.31.
    scene = np.repeat(np.arange(40), 30)
    label = np.repeat(rng.uniform(size=40) < 0.5, 30)
    score = label + rng.normal(0, 2.0, 1200)
    lo, hi = scene_interval(lambda s, y, g: float(np.mean(y)), score, label, scene, 500)
    assert hi - lo > 0.2
    # The judgement carries them, overall and per source; none without resamples.
    source = rng.integers(0, 2, 1200)
    out = judge(score, label, scene=scene, source=source, source_names=("a", "b"), top_source=None, resamples=200)
    assert out["auc_interval"][0] <= out["auc"] <= out["auc_interval"][1]
    assert out["top1_interval"][0] <= out["top1_success"] <= out["top1_interval"][1]
    assert out["per_source"]["a"]["auc_interval"] is not None
    assert "auc_interval" not in judge(score, label, scene=scene)


def test_report_names_how_the_top_picks_failed():
    from train.score_data import report_table

    score = np.array([0.9, 0.2, 0.7, 0.6, 0.8, 0.1])
    label = np.array([1, 0, 0, 1, 0, 1])
    outcome = np.array([0, 2, 5, 0, 2, 0])  # scene 6's and 7's top picks dropped / collided
    scene = np.array([5, 5, 6, 6, 7, 7])
    text = report_table(judge(score, label, outcome=outcome, scene=scene, source=np.zeros(6, int), source_names=("stage1",)))
    assert text.splitlines()[-1] == "Where it failed, its trial ended: collision_approach 1, dropped_disturbance 1 (scenes)."
    text = report_table(judge(score, np.ones(6, int), outcome=np.zeros(6, int), scene=scene, source=np.zeros(6, int)))
    assert "Where it failed" not in text  # no miss, no line


def test_training_and_its_judgement_import_without_mujoco():
    # A GPU box that trains but does not simulate may lack MuJoCo: the trainer and the judgement name
    # trial outcomes from envs.outcome, not from the simulator's modules.
    code = (
        "import sys\n"
        "class Block:\n"
        "    def find_spec(self, name, path=None, target=None):\n"
        "        if name == 'mujoco' or name.startswith('mujoco.'):\n"
        "            raise ImportError('mujoco blocked')\n"
        "sys.meta_path.insert(0, Block())\n"
        "import train.trainer, train.judgement\n"
        "from envs.outcome import Outcome\n"
        "assert train.judgement.COLLISIONS == (Outcome.COLLISION_PREGRASP, Outcome.COLLISION_APPROACH)\n"
        "assert 'mujoco' not in sys.modules\n"
    )
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    done = subprocess.run([sys.executable, "-c", code], cwd=root, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
