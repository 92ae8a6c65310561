"""The neighbours' fitted superquadrics as obstacles (`sgjax.stage1.filters.fit_collisions`,
`sgjax.stage1.neighbours`): the test against a brute-force reference, its margin on a constructed
contact, and the per-object filtering with its counts and reasons."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from sgjax.geometry.gripper import GripperSpec, hand_samples
from sgjax.geometry.superquadric import Superquadric, implicit_function
from sgjax.stage1.ems import FitResult
from sgjax.stage1.filters import fit_collisions
from sgjax.stage1.neighbours import NeighbourFitConfig, fit_hits, obstacle_fits, padded_fits, without_fit_collisions
from sgjax.stage1.pipeline import Candidates

SPEC = GripperSpec()
SWEEP, STEP = 0.05, 0.006


def random_setup(seed: int, o: int = 12, k: int = 96):
    """Fits scattered over a 30 cm square and hands in random poses among them."""
    rng = np.random.default_rng(seed)
    scale = rng.uniform(0.01, 0.05, (o, 3)).astype(np.float32)
    eps = rng.uniform(0.2, 1.8, (o, 2)).astype(np.float32)
    rot = Rotation.random(o, random_state=seed).as_matrix().astype(np.float32)
    trans = np.c_[rng.uniform(-0.15, 0.15, (o, 2)), rng.uniform(0.0, 0.06, o)].astype(np.float32)
    poses = np.tile(np.eye(4, dtype=np.float32), (k, 1, 1))
    poses[:, :3, :3] = Rotation.random(k, random_state=seed + 1).as_matrix()
    poses[:, :3, 3] = np.c_[rng.uniform(-0.15, 0.15, (k, 2)), rng.uniform(0.0, 0.12, k)]
    widths = rng.uniform(0.0, SPEC.max_opening, k).astype(np.float32)
    owner = rng.integers(-1, o, k).astype(np.int32)
    mask = rng.random(o) > 0.2
    return Superquadric(scale, eps, rot, trans), mask, poses, widths, owner


def brute_force(fits, mask, poses, widths, owner, margin):
    grown = Superquadric(fits.scale + margin, fits.epsilon, fits.rotation, fits.translation)
    out = np.zeros(len(widths), bool)
    for i, (pose, w) in enumerate(zip(poses, widths)):
        world = np.asarray(hand_samples(SPEC, w, SWEEP, STEP)) @ pose[:3, :3].T + pose[:3, 3]
        for j in range(len(mask)):
            if mask[j] and j != owner[i]:
                out[i] |= bool(np.any(np.asarray(implicit_function(jnp.asarray(world), jax.tree.map(lambda x: x[j], grown))) < 1.0))
    return out


@pytest.mark.parametrize("seed", [0, 1])
def test_fit_collisions_match_a_brute_force_reference(seed):
    fits, mask, poses, widths, owner = random_setup(seed)
    reference = brute_force(fits, mask, poses, widths, owner, 0.002)
    assert 0.1 < reference.mean() < 0.9  # a test that can fail both ways
    test = jax.jit(lambda n, c: fit_collisions(poses, widths, owner, fits, mask, SPEC, 0.002, SWEEP, STEP, n, c),
                   static_argnums=(0, 1))
    np.testing.assert_array_equal(np.asarray(test(len(mask), None)), reference)  # every fit: exact
    np.testing.assert_array_equal(np.asarray(test(4, 32)), reference)  # the 4 nearest, in chunks: the same here


def test_margin_and_own_fit_on_a_constructed_contact():
    """A sphere (radius 2 cm) beside the right finger's outer face, d away from its nearest hand sample:
    it meets the hand when d < margin, not otherwise; never when it is the grasped object's own fit."""
    width = 0.04
    samples = np.asarray(hand_samples(SPEC, width, SWEEP, STEP))
    outer = samples[np.isclose(samples[:, 0], width / 2 + SPEC.finger_thickness)]
    # A sample on the face near the fingertip (y = 0), so that the sphere is far from the palm.
    face = outer[np.argmin(np.abs(outer[:, 2] - 0.045) + np.abs(outer[:, 1]))]
    pose = np.eye(4, dtype=np.float32)[None]

    def meets(d, margin, owner=-1):
        centre = face + np.array([0.02 + d, 0.0, 0.0])
        sphere = Superquadric(np.full((1, 3), 0.02, np.float32), np.ones((1, 2), np.float32), np.eye(3, dtype=np.float32)[None],
                              centre[None].astype(np.float32))
        return bool(fit_collisions(pose, np.array([width], np.float32), np.array([owner], np.int32), sphere,
                                   np.array([True]), SPEC, margin, SWEEP, STEP)[0])

    assert meets(-0.001, 0.0) and not meets(0.001, 0.0)
    assert meets(0.001, 0.002) and not meets(0.003, 0.002)
    assert not meets(-0.005, 0.002, owner=0)


def fit_result(sq: Superquadric, valid=True) -> FitResult:
    one = lambda v: np.float32(v)
    return FitResult(np.asarray(sq.scale), np.asarray(sq.epsilon), np.asarray(sq.rotation), np.asarray(sq.translation),
                     one(1.0), one(0.001), np.int32(0), np.bool_(valid))


def candidates(poses, widths, fit) -> Candidates:
    n = len(widths)
    z = np.zeros(n, np.int64)
    return Candidates(poses.astype(np.float64), widths.astype(np.float64), z, z, z, np.zeros(n), z, fit,
                      {"transferred": n, "kept": n})


def test_without_fit_collisions_removes_counts_and_explains():
    """Object 0's grasps whose hand meets object 1's fit go, with the count; an object whose every grasp
    goes gets the reason; an invalid fit is no obstacle; the Candidates given are not changed."""
    fits, mask, poses, widths, owner = random_setup(3, o=3, k=64)
    sqs = [jax.tree.map(lambda x: x[i], fits) for i in range(3)]
    given = [candidates(poses[:40], widths[:40], fit_result(sqs[0])), candidates(poses[40:], widths[40:], fit_result(sqs[1])),
             candidates(poses[:0], widths[:0], fit_result(sqs[2], valid=False))]
    config = NeighbourFitConfig(margin=0.002, step=STEP, nearest=4, object_slots=8)
    far = [np.full((10, 3), 5.0)] * 3  # observed points far from every fit: no fit is discounted
    out = without_fit_collisions(given, obstacle_fits(given, far, config), SPEC, config, SWEEP, (64, 128))
    stacked, fit_mask = padded_fits(given, 8)
    assert fit_mask.tolist() == [True, True] + [False] * 6
    expected = brute_force(stacked, fit_mask, poses, widths, np.r_[np.zeros(40, np.int32), np.ones(24, np.int32)], 0.002)
    for c, got, hits in zip(given, out[:2], (expected[:40], expected[40:])):
        assert 0 < hits.sum() < len(hits)
        np.testing.assert_array_equal(got.poses, c.poses[~hits])
        assert got.counts["collision_fit"] == hits.sum() and got.counts["kept"] == (~hits).sum()
        assert len(c) == c.counts["kept"] == len(hits)  # unchanged
    assert out[2].counts["collision_fit"] == 0 and len(out[2]) == 0
    # Every grasp of object 0 inside object 1's fit: none left, and why.
    inside = np.tile(np.eye(4, dtype=np.float32), (5, 1, 1))
    inside[:, :3, 3] = np.asarray(sqs[1].translation)
    pair = [candidates(inside, np.full(5, 0.03, np.float32), fit_result(sqs[0])), given[1]]
    blocked = without_fit_collisions(pair, obstacle_fits(pair, far[:2], config), SPEC, config, SWEEP, (64,))
    assert len(blocked[0]) == 0 and "all 5 candidates" in blocked[0].reason and "fitted superquadric" in blocked[0].reason
    # ... unless object 1's fit holds object 0's own observed points (more than max_overlap of them): then
    # that fit is wrong where object 0's grasps go, and it is no obstacle for them (it still is for others).
    centre = np.asarray(sqs[1].translation)
    own = np.r_[np.tile(centre, (3, 1)), np.full((97, 3), 5.0)]  # 3 % of object 0's points inside fit 1
    kept = without_fit_collisions(pair, obstacle_fits(pair, [own, far[1]], config), SPEC, config, SWEEP, (64,))
    assert len(kept[0]) == 5 and kept[0].counts["collision_fit"] == 0
    _, _, pairs = obstacle_fits(given[:2], [own, far[1]], config)
    assert pairs[:2, :2].tolist() == [[False, False], [True, False]]
    _, _, pairs = obstacle_fits(given[:2], [own[1:], far[1]], dataclasses.replace(config, max_overlap=0.025))
    assert pairs[0, 1]  # 2 of 99 points: within 2.5 %
    # Many candidates: several calls of the largest size give what one call gives.
    many = fit_hits(np.tile(poses, (3, 1, 1)), np.tile(widths, 3), np.tile(owner, 3), fits, mask, SPEC, config, SWEEP, (64,))
    np.testing.assert_array_equal(many, np.tile(brute_force(fits, mask, poses, widths, owner, 0.002), 3))


@pytest.mark.parametrize("change, message", [({"margin": -0.001}, "margin"), ({"margin": float("nan")}, "margin"),
                                             ({"step": 0.0}, "step"), ({"nearest": 0}, "nearest"),
                                             ({"max_overlap": 1.5}, "max_overlap")])
def test_bad_config_raises(change, message):
    with pytest.raises(ValueError, match=message):
        dataclasses.replace(NeighbourFitConfig(), **change)
