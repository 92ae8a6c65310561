"""Planner: the paper's decision policy on hand-set scores, Stage 1 + Stage 2 end to end (tiny random
E-RNet, small database, synthetic tabletop), fixed shapes, bad input, and the `sgjax plan` command."""

from __future__ import annotations

import dataclasses
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import nnx

from sgjax import planner as planner_mod, policy
from sgjax.geometry import gripper as gripper_mod, synthetic
from sgjax.stage2 import checkpoint, ernet
from sgjax.stage2.ernet import ERNet, ERNetConfig
from sgjax.geometry.gripper import GripperSpec, near_grasps, refined_pose
from sgjax.planner import Planner, PlannerConfig
from sgjax.policy import decide, select_grasp
from sgjax.geometry.rotations import so3_exp
from sgjax.geometry.superquadric import Superquadric

SPEC = GripperSpec()
CAMERA = np.array([0.4, -0.1, 0.6])
# Random centroid sampling compiles faster than FPS. One Stage-1 shape (batches of 1 object) and the
# default Stage-2 shapes, which `sgjax plan` (default config) then reuses: two compiles in all. No second
# plan with the fallback filter (the paper's planner; that plan has its own test below), so that a plan
# without a grasp says exactly why and compiles nothing more; and the paper's choice, the highest
# evaluation (`PlannerConfig.robust` has its own tests at the end).
TINY = ERNetConfig.tiny(backbone=dataclasses.replace(ERNetConfig.tiny().backbone, sampler="random"))
CONFIG = PlannerConfig(stage1_batch_sizes=(1,), fallback_filter=None, robust=None)
PAPER_RULE = dataclasses.replace(CONFIG, refine_rescore=0)  # a refinement scored by the refine head alone


def box(centre_xy, half, yaw_deg, seed, n=600):
    """A single-view cloud of a box standing on the table (z = 0), seen from CAMERA."""
    c, s = np.cos(np.deg2rad(yaw_deg)), np.sin(np.deg2rad(yaw_deg))
    rot = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
    centre = np.array([*centre_xy, half[2]])
    sq = Superquadric.create(np.asarray(half), (0.1, 0.1), rot, centre)
    cloud = synthetic.single_view_cloud(sq, n, view=CAMERA - centre, seed=seed)
    return cloud[cloud[:, 2] > 0.002]


def tabletop(n_objects=2, seed=0, table=40):
    """-> (scene [N, 3], labels [N]): a noisy table plane (label -1) and boxes labelled 0, 1, ..."""
    rng = np.random.default_rng(seed)
    xs, ys = np.meshgrid(np.linspace(-0.25, 0.25, table), np.linspace(-0.25, 0.25, table))
    clouds = [np.c_[xs.ravel(), ys.ravel(), rng.normal(0, 0.001, xs.size)]]
    labels = [np.full(xs.size, -1)]
    placements = [((0.1, 0.0), (0.03, 0.02, 0.04), 25), ((-0.1, 0.06), (0.025, 0.025, 0.05), 70)]
    for i in range(n_objects):
        clouds.append(box(*placements[i], seed=seed + i))
        labels.append(np.full(len(clouds[-1]), i))
    return np.concatenate(clouds), np.concatenate(labels)


def rigged(eval_bias, refine_bias, seed=0):
    """A tiny ERNet whose heads ignore their input: eval logits `eval_bias` [2], refine logits [3]."""
    model = ERNet(TINY, rngs=nnx.Rngs(seed))
    for head, bias in ((model.eval_head, eval_bias), (model.refine_head, refine_bias)):
        last = head.layers[-1]
        last.kernel[...] = jnp.zeros_like(last.kernel[...])
        last.bias[...] = jnp.asarray(bias, jnp.float32)
    return model


@pytest.fixture(scope="module")
def scene():
    return tabletop()


@pytest.fixture(scope="module")
def planner(small_db):
    return Planner(ERNet(TINY, rngs=nnx.Rngs(0)), small_db, CONFIG)


@pytest.fixture(scope="module")
def first_plan(planner, scene):
    return planner.plan(*scene, viewpoint=CAMERA, seed=0)


# ---------------------------------------------------------------------------------------------
# The decision policy on hand-set scores.

REFINE = np.array([[0.1, 0.2, 0.3], [0.6, 0.95, 0.2], [0.9, 0.1, 0.1], [0.99, 0.99, 0.99]], np.float32)
VALID = np.array([True, True, True, False])


def as_tuple(out):
    index, kind, variant, score = (np.asarray(x).item() for x in out)
    return index, kind, variant, pytest.approx(score, abs=1e-6)


def test_evaluated_grasp_wins_when_its_score_exceeds_the_threshold():
    out = decide(np.array([0.5, 0.9, 0.8, 0.99], np.float32), REFINE, VALID)
    assert as_tuple(out) == (1, 1, -1, 0.9)  # the invalid 0.99 is never chosen


def test_refinement_fallback_picks_the_best_candidate_and_variant():
    eval_prob = np.array([0.6, 0.3, 0.7, 0.99], np.float32)  # 0.7 does not exceed 0.7
    assert as_tuple(decide(eval_prob, REFINE, VALID)) == (1, 2, 1, 0.95)
    # Only above the refine threshold; otherwise no grasp, scored by the best valid eval prob.
    assert as_tuple(decide(eval_prob, REFINE, VALID, refine_threshold=0.95)) == (-1, 0, -1, 0.7)
    assert as_tuple(decide(eval_prob, REFINE * 0.5, VALID)) == (-1, 0, -1, 0.7)
    # The paper's "w/o RNet" ablation never refines.
    assert as_tuple(decide(eval_prob, REFINE, VALID, use_refinement=False)) == (-1, 0, -1, 0.7)
    # Thresholds, like the scores, may be traced: one compile serves all.
    traces = []

    def traced(*args):
        traces.append(1)
        return decide(*args)

    jitted = jax.jit(traced)
    assert as_tuple(jitted(eval_prob, REFINE, VALID, 0.7, 0.7, True)) == (1, 2, 1, 0.95)
    assert as_tuple(jitted(eval_prob, REFINE, VALID, 0.5, 0.7, True)) == (2, 1, -1, 0.7)
    assert as_tuple(jitted(eval_prob, REFINE, VALID, 0.7, 0.7, False)) == (-1, 0, -1, 0.7)
    assert len(traces) == 1


def test_invalid_and_nan_candidates_are_never_chosen():
    none_valid = np.zeros(4, bool)
    assert as_tuple(decide(np.ones(4, np.float32), REFINE, none_valid)) == (-1, 0, -1, 0.0)
    eval_prob = np.array([np.nan, 0.8, 0.2, 0.1], np.float32)
    assert as_tuple(decide(eval_prob, REFINE, np.ones(4, bool))) == (1, 1, -1, 0.8)
    assert as_tuple(decide(np.zeros(0), np.zeros((0, 3)), np.zeros(0, bool))) == (-1, 0, -1, 0.0)
    with pytest.raises(ValueError, match="refine_prob"):
        decide(np.zeros(4), np.zeros(4), VALID)
    with pytest.raises(ValueError, match="valid must have shape"):
        decide(np.zeros(4), REFINE, VALID[:2])


def test_selected_pose_is_the_refined_pose():
    rng = np.random.default_rng(0)
    poses = np.tile(np.eye(4, dtype=np.float32), (4, 1, 1))
    poses[:, :3, 3] = rng.uniform(-0.1, 0.1, (4, 3))
    poses[2, :3, :3] = np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1]])
    widths = np.array([0.03, 0.04, 0.05, 0.06], np.float32)
    refine = REFINE.copy()
    refine[2] = [0.2, 0.1, 0.97]  # candidate 2, variant 2 (+15 deg)
    out = select_grasp(poses, widths, np.full(4, 0.5), refine, VALID, spec=SPEC)
    assert (int(out["index"]), int(out["kind"]), int(out["variant"])) == (2, 2, 2)
    np.testing.assert_allclose(out["pose"], refined_pose(poses[2], 2, SPEC), atol=1e-6)
    np.testing.assert_array_equal(out["initial_pose"], poses[2])
    assert float(out["width"]) == pytest.approx(0.05)
    out = select_grasp(poses, widths, np.array([0.1, 0.2, 0.3, 0.9]), refine, np.ones(4, bool), spec=SPEC)
    assert int(out["kind"]) == 1 and np.array_equal(out["pose"], poses[3])


# ---------------------------------------------------------------------------------------------
# The planner end to end.


def test_plan_scores_every_object_in_one_call(planner, scene, first_plan):
    plan = first_plan
    n_scored = len(plan.scores["eval_prob"])
    assert plan.n_candidates == n_scored == sum(len(c) for c in plan.candidates) > 0  # all fit in one batch
    assert plan.scores["refine_prob"].shape == (n_scored, 3)
    assert {o["label"]: o["candidates"] > 0 for o in plan.objects} == {0: True, 1: True}
    for i, c in enumerate(plan.candidates):
        np.testing.assert_array_equal(plan.scores["object_candidate"][plan.scores["object"] == i], np.arange(len(c)))
    np.testing.assert_array_equal(plan.scores["target"], plan.scores["object"])  # labels 0, 1
    assert plan.scores["valid"].any()
    assert set(plan.timing) == {"stage1_s", "stage2_s", "total_s", "compiled"}
    # A random tiny network: whatever it decided, the plan is consistent with `decide`.
    index, kind, _, score = decide(plan.scores["eval_prob"], plan.scores["refine_prob"], plan.scores["valid"])
    assert plan.kind == planner_mod.KIND_NAMES[int(kind)] and plan.score == pytest.approx(float(score))
    if plan.kind is None:
        assert plan.reason.startswith("best eval") and plan.pose is None
    else:
        assert plan.candidate_index == int(index) and plan.pose.shape == (4, 4)
    record = json.loads(json.dumps(plan.to_dict()))
    assert record["n_scored"] == n_scored and record["kind"] == plan.kind


def test_stage2_cloud_reproduces_the_plans_scores(planner, scene, first_plan):
    """`Planner.stage2_cloud`: stored with a grasp, the plan's Stage-2 cloud gives that plan's own crop, so
    the network scores it as the plan did (what training data taken from plans needs)."""
    from sgjax.stage2.crops import crop_function

    plan = first_plan
    cloud = planner.stage2_cloud(scene[0], seed=0)
    assert cloud.dtype == np.float32 and cloud.shape[1] == 3 and 0 < len(cloud) <= planner.config.scene_cloud.max_points
    assert np.array_equal(cloud, planner.stage2_cloud(scene[0], seed=0))
    assert not np.array_equal(cloud, planner.stage2_cloud(scene[0], seed=1))  # the plan's seed shuffles it
    rows = np.flatnonzero(plan.scores["valid"])[:16]
    poses = np.stack([plan.candidates[int(plan.scores["object"][r])].poses[int(plan.scores["object_candidate"][r])] for r in rows])
    widths = np.array([plan.candidates[int(plan.scores["object"][r])].widths[int(plan.scores["object_candidate"][r])] for r in rows])
    crop = crop_function(planner.model.config.crop)
    region = crop(jnp.asarray(cloud), jnp.asarray(poses, jnp.float32), jnp.asarray(widths, jnp.float32), spec=planner.config.spec,
                  n_points=2048)
    scores = ernet.score_regions(planner.graphdef, planner.state, region.points, region.mask, jnp.asarray(widths, jnp.float32),
                                 spec=planner.config.spec)
    np.testing.assert_allclose(np.asarray(scores.eval_prob), plan.scores["eval_prob"][rows], atol=1e-5)
    other = crop(jnp.asarray(planner.stage2_cloud(scene[0], seed=1)), jnp.asarray(poses, jnp.float32),
                 jnp.asarray(widths, jnp.float32), spec=planner.config.spec, n_points=2048)
    assert not np.array_equal(np.asarray(other.points), np.asarray(region.points))


def test_more_candidates_than_stage2_takes_keeps_each_objects_best():
    obj, row = policy.stage2_subset([5, 1, 3], 6)  # round-robin in match order
    assert list(zip(obj.tolist(), row.tolist())) == [(0, 0), (0, 1), (0, 2), (1, 0), (2, 0), (2, 1)]
    obj, row = policy.stage2_subset([2, 0, 1], 10)
    assert obj.tolist() == [0, 0, 2] and row.tolist() == [0, 1, 0]
    assert len(policy.stage2_subset([], 4)[0]) == 0


def test_deterministic_and_never_recompiles(planner, scene, first_plan):
    from sgjax.utils.exported import traced_programs

    # Traced, not loaded: a cache that already holds Stage-2 sizes exported by an earlier process lets
    # later plans load them (lazily, when first used), which is not a recompilation.
    traced = traced_programs()
    again = planner.plan(*scene, viewpoint=CAMERA, seed=0)
    for key in ("eval_prob", "refine_prob", "valid", "object_candidate"):
        np.testing.assert_array_equal(again.scores[key], first_plan.scores[key])
    assert (again.kind, again.candidate_index, again.score) == (first_plan.kind, first_plan.candidate_index, first_plan.score)
    assert not again.timing["compiled"]
    # Other scene sizes and candidate counts (one object, a sparser table): the same compiled calls.
    points, labels = scene
    keep = (labels >= 0) | (np.arange(len(labels)) % 3 > 0)
    one = planner.plan(points[keep], np.where(labels[keep] == 1, -1, labels[keep]), viewpoint=CAMERA, seed=3)
    assert one.n_candidates < first_plan.n_candidates and set(one.scores["target"]) == {0}
    target = planner.plan_target(points, points[labels == 1], viewpoint=CAMERA, seed=0)
    assert target.n_candidates > 0 and set(target.scores["target"]) <= {0}
    assert traced_programs() == traced


def test_memory_reuses_unchanged_objects_and_retests_their_neighbours(planner, scene, first_plan):
    """With a Stage1Memory, a second plan of the same observation reuses every object's Stage-1 result
    and gives the same scores; moving one object makes only that one run Stage 1 again; an obstacle put
    over an unchanged object's grasps removes them (filter (iv) runs again on remembered candidates)."""
    from sgjax.stage1.memory import Stage1Memory

    points, labels = scene
    memory = Stage1Memory()
    plans = [planner.plan(points, labels, viewpoint=CAMERA, seed=0, memory=memory) for _ in range(2)]
    assert (plans[0].reused, plans[1].reused) == (0, 2) and (memory.computed, memory.reused) == (2, 2)
    for plan in plans:
        for key in ("eval_prob", "refine_prob", "object_candidate"):
            np.testing.assert_array_equal(plan.scores[key], first_plan.scores[key])
    moved = points.copy()
    moved[labels == 1] += np.array([0.01, 0.0, 0.0])
    third = planner.plan(moved, labels, viewpoint=CAMERA, seed=0, memory=memory)
    assert third.reused == 1 and memory.computed == 3
    # Clutter (unlabelled points above the table) all around object 0, which has not changed: its
    # remembered candidates are tested against it, and those it blocks are gone.
    kept, own = plans[1].candidates[0], points[labels == 0]
    clutter = np.random.default_rng(0).uniform(own.min(0) - 0.04, own.max(0) + [0.04, 0.04, 0.0], (3000, 3))
    clutter = clutter[(clutter[:, 2] > 0.01) & (np.min(np.linalg.norm(clutter[:, None] - own[None], axis=-1), 1) > 0.01)]
    blocked = planner.plan(np.r_[points, clutter], np.r_[labels, np.full(len(clutter), -1)], viewpoint=CAMERA, seed=0,
                           memory=memory)
    assert blocked.reused == 1  # object 0; object 1 is back where it was, not where the memory saw it
    assert len(blocked.candidates[0]) < len(kept) and blocked.candidates[0].counts["collision_scene"] > 0
    memory.forget()
    assert not memory.entries and memory.computed == memory.reused == 0
    with pytest.raises(ValueError, match="reuse_tolerance"):
        PlannerConfig(reuse_tolerance=-1.0)


def test_stage2_batch_sizes_do_not_change_scores(planner, small_db, scene, first_plan):
    assert PlannerConfig().stage2_sizes == (64, 128, 256, 512)
    assert PlannerConfig(max_stage2_candidates=300, stage2_min_slots=100).stage2_sizes == (128, 256, 300)
    assert PlannerConfig().stage2_slots(65) == 128 and PlannerConfig().stage2_slots(512) == 512
    with pytest.raises(ValueError, match="stage2_min_slots"):
        PlannerConfig(stage2_min_slots=0)
    # One 512-slot batch (the old fixed shape) against the smallest that fits: the same scores and choice.
    whole = Planner(planner.model, small_db, dataclasses.replace(CONFIG, stage2_min_slots=512))
    assert whole.config.stage2_sizes == (512,)
    points, labels = scene
    narrow = planner.plan_target(points, points[labels == 1], viewpoint=CAMERA, seed=0)
    wide = whole.plan_target(points, points[labels == 1], viewpoint=CAMERA, seed=0)
    assert 0 < narrow.n_candidates <= 256 and narrow.n_candidates == wide.n_candidates
    for key in ("eval_prob", "refine_prob"):
        np.testing.assert_allclose(wide.scores[key], narrow.scores[key], atol=1e-5)
    assert (wide.kind, wide.candidate_index) == (narrow.kind, narrow.candidate_index)


def test_forced_scores_give_each_decision(small_db, scene):
    """Heads that ignore their input: every valid candidate has the same scores, so the first valid wins."""
    refine_model = rigged([0.0, -5.0], [-5.0, -5.0, 5.0])  # eval 0.007, refine variant 2: 0.993
    plan = Planner(refine_model, small_db, PAPER_RULE).plan(*scene, viewpoint=CAMERA)
    first_valid = int(np.argmax(plan.scores["valid"]))
    assert (plan.kind, plan.refine_variant, plan.candidate_index) == ("refined", 2, first_valid)
    assert plan.score == pytest.approx(1 / (1 + np.exp(-5.0)), rel=1e-5)
    obj, row = plan.scores["object"][first_valid], plan.scores["object_candidate"][first_valid]
    initial = plan.candidates[obj].poses[row]
    np.testing.assert_array_equal(plan.initial_pose, initial)
    np.testing.assert_allclose(plan.pose, refined_pose(initial.astype(np.float32), 2, SPEC), atol=1e-5)
    assert plan.width == plan.candidates[obj].widths[row] and plan.target == obj

    ablation = Planner(refine_model, small_db, dataclasses.replace(CONFIG, use_refinement=False))
    none = ablation.plan(*scene, viewpoint=CAMERA)
    assert none.kind is None and none.pose is None and none.reason == "best eval 0.01 <= 0.7 (refinement disabled)"

    weak = Planner(rigged([0.0, -5.0], [-5.0, -1.0, -5.0]), small_db, PAPER_RULE).plan(*scene, viewpoint=CAMERA)
    assert weak.kind is None and weak.reason == "best eval 0.01 <= 0.7 and best refine 0.27 <= 0.7"

    # Re-scored (the default): the same refinement is judged again by the evaluation head at its pose.
    # An evaluation of 0.007 there sinks it (sqrt(0.993 * 0.007) = 0.08); one of 0.69, still below the
    # bar as an evaluated grasp, lets it through at sqrt(0.993 * 0.69) = 0.83.
    sunk = Planner(refine_model, small_db, CONFIG).plan(*scene, viewpoint=CAMERA)
    assert sunk.kind is None and sunk.reason == "best eval 0.01 <= 0.7 and best re-scored refinement 0.08 <= 0.7"
    both = Planner(rigged([0.0, 0.8], [-5.0, -5.0, 5.0]), small_db, CONFIG).plan(*scene, viewpoint=CAMERA)
    sig = lambda z: 1 / (1 + np.exp(-z))
    assert (both.kind, both.refine_variant, both.candidate_index) == ("refined", 2, first_valid)
    assert both.score == pytest.approx(np.sqrt(sig(5.0) * sig(0.8)), rel=1e-5)
    np.testing.assert_allclose(both.pose, plan.pose, atol=1e-6)

    strong = Planner(rigged([0.0, 5.0], [5.0, 5.0, 5.0]), small_db, CONFIG).plan(*scene, viewpoint=CAMERA)
    assert strong.kind == "evaluated" and strong.refine_variant is None and strong.candidate_index == first_valid
    np.testing.assert_array_equal(strong.pose, initial)


def test_refined_poses_that_collide_are_left_out(small_db, scene):
    """Before a refined pose is executed it passes Stage 1's obstacle and table tests; the policy passes over
    the refinements that fail them, in its own order (here: refine variant 0 of the first valid candidate)."""
    config = dataclasses.replace(PAPER_RULE, support_plane=(0.0, 0.0, 1.0, 0.0), avoid_distance=1e-4, avoid_angle_deg=0.01)
    planner = Planner(rigged([0.0, -5.0], [5.0, 4.0, 3.0]), small_db, config)  # variant 0 > 1 > 2, all > 0.7
    points, labels = scene
    first = planner.plan(points, labels, viewpoint=CAMERA)
    cands = first.candidates[0]  # object 0's candidates, scored first
    obstacles = points[planner.stage1.off_table(points, config.support_plane) & (labels != 0)]
    deepened = np.asarray(refined_pose(cands.poses.astype(np.float32), 0, SPEC))
    found = planner.stage1.collisions(points[labels == 0], obstacles, deepened, cands.widths, CAMERA, 0,
                                      config.support_plane, lift=True)
    hits = found["collision_scene"] | found["below_support"]  # the target is E-RNet's to judge
    assert hits.any() and not hits.all()  # some refinements of these box grasps reach the table
    # Leave out the candidates before the first whose refinement collides: the policy now meets it first.
    k = int(np.argmax(hits))
    plan = planner.plan(points, labels, viewpoint=CAMERA, avoid=cands.poses[:k])
    s = plan.scores
    rows = s["object_candidate"][(s["object"] == 0) & s["valid"]]
    assert rows[0] == k
    expected = next(i for i, r in enumerate(rows) if not hits[r])
    assert (plan.kind, plan.refine_variant, plan.refinements_rejected) == ("refined", 0, expected)
    np.testing.assert_array_equal(plan.initial_pose, cands.poses[rows[expected]])
    np.testing.assert_allclose(plan.pose, found["poses"][rows[expected]], atol=1e-5)
    executed = planner.stage1.collisions(points[labels == 0], obstacles, plan.pose[None], [plan.width], CAMERA, 0,
                                         config.support_plane)
    assert not (executed["collision_scene"][0] or executed["below_support"][0])
    assert plan.to_dict()["refinements_rejected"] == expected


def test_rescored_refinements_are_judged_at_their_refined_pose(small_db, scene):
    """`refine_rescore`: when no evaluation passes, the refine head's best R proposals are scored again by
    E-RNet at their refined pose (checked against `ernet.score` called on those poses), each scoring the
    geometric mean of the two; the policy decides on those scores, others count 0."""
    model = ERNet(TINY, rngs=nnx.Rngs(3))
    config = dataclasses.replace(CONFIG, eval_threshold=0.99, refine_threshold=0.3, refine_rescore=8)
    planner = Planner(model, small_db, config)
    plan = planner.plan(*scene, viewpoint=CAMERA, seed=0)
    s = plan.scores
    head = np.where(s["valid"][:, None], s["refine_prob"], -1.0)
    k = head.shape[1]
    top = np.argsort(-head.reshape(-1), kind="stable")[:8]
    index, variant = top // k, top % k
    rescored = np.zeros_like(head, bool)
    rescored[index, variant] = True
    assert not s["refine_score"][~rescored].any()
    # The same E-RNet call the planner makes, on the refined poses of those proposals.
    poses = np.stack([plan.candidates[o].poses[r] for o, r in zip(s["object"], s["object_candidate"])]).astype(np.float32)
    widths = np.array([plan.candidates[o].widths[r] for o, r in zip(s["object"], s["object_candidate"])], np.float32)
    scene_pad, scene_mask = planner._scene(scene[0], 0)
    refined = np.asarray(refined_pose(poses[index], variant, SPEC))
    graphdef, state = nnx.split(model)
    judged = ernet.score(graphdef, state, scene_pad, refined, widths[index], scene_mask, spec=SPEC, key=jax.random.key(0))
    expected = np.sqrt(s["refine_prob"][index, variant] * np.where(judged.valid, judged.eval_prob, 0.0))
    np.testing.assert_allclose(s["refine_score"][index, variant], expected, atol=2e-5)
    best = int(np.argmax(s["refine_score"].reshape(-1)))
    assert expected.max() > 0.3  # the random network's scores lie around 0.5: some refinement passes
    assert (plan.kind, plan.candidate_index, plan.refine_variant) == ("refined", best // k, best % k)
    assert plan.score == pytest.approx(float(s["refine_score"].max()), abs=1e-6)


def test_avoided_poses_are_never_planned_again(small_db, scene):
    """`avoid` (the benchmark's memory of failed grasps): the same grasps are left out before Stage 2."""
    strong = Planner(rigged([0.0, 5.0], [5.0, 5.0, 5.0]), small_db, CONFIG)  # first valid candidate wins
    first = strong.plan(*scene, viewpoint=CAMERA)
    assert first.kind == "evaluated"
    second = strong.plan(*scene, viewpoint=CAMERA, avoid=first.pose[None])
    assert second.kind == "evaluated" and second.n_candidates == first.n_candidates
    all_poses = np.concatenate([c.poses for c in first.candidates])
    near_first = near_grasps(all_poses.astype(np.float64), first.pose[None], SPEC, xp=np)
    assert len(second.scores["eval_prob"]) == len(all_poses) - near_first.sum()  # only those were left out
    assert not near_grasps(second.pose[None], first.pose[None], SPEC, xp=np)[0]
    # Rows still index each object's Stage-1 candidates.
    obj, row = second.scores["object"], second.scores["object_candidate"]
    chosen = second.candidate_index
    np.testing.assert_array_equal(second.pose, second.candidates[obj[chosen]].poses[row[chosen]])
    # Every candidate avoided: no grasp, and the reason says why.
    none = strong.plan(*scene, viewpoint=CAMERA, avoid=all_poses)
    assert none.kind is None and none.reason.startswith(f"all {first.n_candidates} candidates are within 0.01 m and 15 deg")
    # An empty list changes nothing; a bad one is named.
    same = strong.plan(*scene, viewpoint=CAMERA, avoid=np.zeros((0, 4, 4)))
    np.testing.assert_array_equal(same.pose, first.pose)
    with pytest.raises(ValueError, match=r"avoid must be gripper poses \[F, 4, 4\]"):
        strong.plan(*scene, avoid=np.zeros((2, 3, 4)))
    with pytest.raises(ValueError, match="avoid holds NaN"):
        strong.plan(*scene, avoid=np.full((1, 4, 4), np.nan))


def test_small_objects_are_skipped_with_a_reason(planner, scene):
    points, labels = scene
    speck = np.random.default_rng(1).normal([0.0, -0.15, 0.01], 0.004, (20, 3))
    plan = planner.plan(np.r_[points, speck], np.r_[labels, np.full(20, 7)], viewpoint=CAMERA)
    skipped = [o for o in plan.objects if o["label"] == 7]
    assert skipped == [{"label": 7, "points": 20, "candidates": 0, "reason": "20 visible points < min_object_points 50"}]
    assert set(plan.scores["target"]) == {0, 1}

    only = planner.plan(np.r_[points, speck], np.r_[np.full(len(points), -1), np.full(20, 7)])
    assert only.kind is None and only.reason == "no object with at least 50 visible points (object 7: 20)"
    assert planner.plan(points, np.full(len(points), -1)).reason.startswith("no object points")
    target = planner.plan_target(points, speck)
    assert target.kind is None and "20 visible points" in target.reason


def test_no_candidates_gives_the_stage1_reason(planner, scene):
    points, labels = scene
    flat = np.c_[np.random.default_rng(2).uniform(-0.2, -0.1, (80, 2)), np.zeros(80)]  # a coplanar patch
    plan = planner.plan(np.r_[points[labels < 0], flat], np.r_[labels[labels < 0], np.full(80, 3)])
    assert plan.kind is None and plan.reason.startswith("no candidates: object 3:") and "coplanar" in plan.reason
    assert plan.n_candidates == 0 and plan.timing["stage2_s"] == 0.0
    # The support plane reaches Stage 1's filter (v): a "table" at z = 0.5 leaves nothing above it.
    high = Planner(planner.model, planner.stage1.db, dataclasses.replace(CONFIG, support_plane=(0, 0, 1, -0.5)))
    plan = high.plan(points, labels, viewpoint=CAMERA)
    assert plan.kind is None and "below the support plane" in plan.reason and not plan.timing["compiled"]


def test_fallback_filter_plans_again_only_when_nothing_was_found(small_db, scene):
    """`PlannerConfig.fallback_filter`: a plan that finds no grasp is made again with that filter, and
    only then; the grasp it executes is the one a planner with that filter would choose."""
    from sgjax.stage1.filters import FilterConfig

    strong = rigged([0.0, 5.0], [5.0, 5.0, 5.0])
    starved = dataclasses.replace(CONFIG.stage1, filter=FilterConfig(min_points=5000))  # (ii) removes all
    plain = Planner(strong, small_db, CONFIG).plan(*scene, viewpoint=CAMERA)
    assert plain.ok and not plain.fallback
    rescued = Planner(strong, small_db, dataclasses.replace(CONFIG, stage1=starved, fallback_filter=FilterConfig()))
    plan = rescued.plan(*scene, viewpoint=CAMERA)
    assert plan.ok and plan.fallback and plan.to_dict()["fallback"]
    assert rescued._fallback_stage().match_db is rescued.stage1.match_db  # one device copy of the database
    np.testing.assert_array_equal(plan.pose, plain.pose)
    assert plan.n_candidates == plain.n_candidates > 0
    # No fallback needed: the first plan stands (the starving filter as fallback is never run).
    unused = Planner(strong, small_db, dataclasses.replace(CONFIG, fallback_filter=FilterConfig(min_points=5000)))
    first = unused.plan(*scene, viewpoint=CAMERA)
    assert first.ok and not first.fallback and not unused._fallback_stages
    # Both plans find nothing: the reason gives both.
    hopeless = Planner(strong, small_db, dataclasses.replace(CONFIG, stage1=starved, fallback_filter=starved.filter))
    none = hopeless.plan(*scene, viewpoint=CAMERA)
    assert none.kind is None and not none.fallback
    assert none.reason.startswith("no candidates: ") and "; with the fallback filter: no candidates: " in none.reason
    assert "fewer than 5000 points between the fingers" in none.reason


@pytest.mark.parametrize(
    "change, message",
    [
        (lambda p, lab: (p[:, :2], lab), r"scene_points must have shape \[N, 3\]"),
        (lambda p, lab: (np.zeros((0, 3)), lab[:0]), "scene_points is empty"),
        (lambda p, lab: (np.where(np.arange(len(p))[:, None] == 5, np.nan, p), lab), "NaN or inf"),
        (lambda p, lab: (p, lab[:-1]), r"labels must have shape \[N\]"),
        (lambda p, lab: (p, lab + 0.5), "integer object ids"),
        (lambda p, lab: (p, lab >= 0), "bool target mask"),
    ],
)
def test_bad_inputs_raise_clear_errors(planner, scene, change, message):
    with pytest.raises(ValueError, match=message):
        planner.plan(*change(*scene))


def test_bad_target_viewpoint_and_masks(planner, scene, small_db):
    points, labels = scene
    with pytest.raises(ValueError, match="target_points must have shape"):
        planner.plan_target(points, points[:, :2])
    with pytest.raises(ValueError, match="viewpoint must be 3 finite numbers"):
        planner.plan(points, labels, viewpoint=(0, 1))
    model = ERNet(TINY, rngs=nnx.Rngs(0))
    with pytest.raises(ValueError, match="object masks overlap"):
        planner_mod.plan(points, np.stack([labels >= 0, labels == 1]), model=model, db=small_db, config=CONFIG)
    with pytest.raises(ValueError, match="target mask must be bool with shape"):
        planner_mod.plan(points, (labels >= 0)[:-1], model=model, db=small_db, config=CONFIG)
    with pytest.raises(ValueError, match="n_refinements|refinements"):
        Planner(model, small_db, PlannerConfig(stage1=dataclasses.replace(CONFIG.stage1, spec=GripperSpec(refine_angles_deg=(0.0,)))))


def test_missing_default_model_says_how_to_make_one(tmp_path, monkeypatch):
    monkeypatch.setattr(checkpoint, "ERNET_DEFAULT_DIR", tmp_path / "ernet_default")
    with pytest.raises(FileNotFoundError, match="ernet_default.*sgjax train --data DIR --out RUN_DIR.*--model RUN_DIR"):
        ernet.load_default_model()


# ---------------------------------------------------------------------------------------------
# Command line.


def save_run_dir(model: ERNet, run_dir) -> None:
    """A `sgjax train` run directory holding `model` (the trainer's checkpoint layout, no training)."""
    import orbax.checkpoint as ocp

    from sgjax.stage2 import checkpoint
    from train import trainer

    manager = trainer._checkpoint_manager(str(run_dir))
    meta = {"epochs_done": 1, "history": [], "model_config": model.config.to_dict()}
    args = {checkpoint.PARAMS_ITEM: ocp.args.StandardSave(nnx.state(model)), checkpoint.META_ITEM: ocp.args.JsonSave(meta)}
    manager.save(1, args=ocp.args.Composite(**args))
    manager.wait_until_finished()
    manager.close()


def test_cli_plan(tmp_path, capsys, monkeypatch, small_db):
    from sgjax_cli import main
    from sgjax.stage1.database import save_database

    run, db = tmp_path / "run", tmp_path / "db.npz"
    save_run_dir(rigged([0.0, 5.0], [0.0, 0.0, 0.0]), run)
    save_database(small_db, db)
    points, labels = tabletop(n_objects=1, seed=4)  # one object: the Stage-1 shape the tests compiled
    np.save(tmp_path / "scene.npy", points.astype(np.float32))
    np.save(tmp_path / "labels.npy", labels.astype(np.int32))
    np.save(tmp_path / "mask.npy", labels == 0)
    base = [str(tmp_path / "scene.npy"), "--model", str(run), "--db", str(db), "--viewpoint", *map(str, CAMERA)]

    png = tmp_path / "plan.png"
    assert main(["plan", *base, "--mask", str(tmp_path / "labels.npy"), "--json", "--png", str(png)]) == 0
    record = json.loads(capsys.readouterr().out)
    assert record["kind"] == "evaluated" and record["target"] == 0 and np.array(record["pose"]).shape == (4, 4)
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    compiled = planner_mod._compile_count()
    assert main(["plan", *base, "--mask", str(tmp_path / "labels.npy"), "--json"]) == 0
    capsys.readouterr()
    assert planner_mod._compile_count() == compiled  # a second plan of the same shapes compiles nothing

    assert main(["plan", *base, "--mask", str(tmp_path / "mask.npy")]) == 0
    out = capsys.readouterr().out
    assert "evaluated grasp" in out and "stage 1" in out and f"E-RNet checkpoint: {run}" in out
    # --model none: no network, Stage 1's order (its best candidate passes with score 1, nothing refined).
    no_network = [a if a != str(run) else "none" for a in base]
    assert main(["plan", *no_network, "--mask", str(tmp_path / "labels.npy"), "--json"]) == 0
    record = json.loads(capsys.readouterr().out)
    assert record["checkpoint"] == "none (Stage 1's order)" and record["kind"] == "evaluated" and record["score"] == 1.0
    with pytest.raises(SystemExit):  # argparse names the known presets
        main(["plan", *base, "--mask", str(tmp_path / "mask.npy"), "--preset", "nope"])
    assert "invalid choice: 'nope'" in capsys.readouterr().err

    np.save(tmp_path / "short.npy", labels[:-3])
    assert main(["plan", *base, "--mask", str(tmp_path / "short.npy")]) == 2
    assert "mask" in capsys.readouterr().err
    assert main(["plan", *base, "--mask", str(tmp_path / "missing.npy")]) == 2
    assert "no such file" in capsys.readouterr().err
    monkeypatch.setattr(checkpoint, "ERNET_DEFAULT_DIR", tmp_path / "ernet_default")
    assert main(["plan", str(tmp_path / "scene.npy"), "--mask", str(tmp_path / "mask.npy"), "--db", str(db)]) == 2
    assert "sgjax train" in capsys.readouterr().err


def tall_and_low():
    """A tall box with a low one close behind it, the low one's side facing it hidden from the camera:
    -> (scene [N, 3], labels [N] (-1 table, 0 tall, 1 low), the tall box's cloud, the low one's)."""
    rng = np.random.default_rng(0)
    xs, ys = np.meshgrid(np.linspace(-0.25, 0.25, 40), np.linspace(-0.25, 0.25, 40))
    table = np.c_[xs.ravel(), ys.ravel(), rng.normal(0, 0.001, xs.size)]
    tall, low = box((0.0, 0.0), (0.02, 0.025, 0.05), 0, seed=0), box((-0.06, 0.0), (0.02, 0.03, 0.02), 0, seed=1)
    points = np.concatenate([table, tall, low])
    labels = np.concatenate([np.full(len(table), -1), np.zeros(len(tall), int), np.ones(len(low), int)])
    return points, labels, tall, low


def test_candidates_meeting_a_neighbours_fit_are_removed(planner):
    """A tall box with a low one close behind it, the low one's side facing it hidden from the camera:
    the planner removes the candidates whose hand meets the other object's fitted superquadric (not
    their observed points: filter (iv) has those), exactly those, counted per object; off, they stay."""
    from sgjax.stage1 import neighbours

    points, labels, tall, low = tall_and_low()
    config = planner.config
    try:
        with_fits = planner.plan(points, labels, viewpoint=CAMERA)
        planner.config = dataclasses.replace(config, neighbour_fits=None)
        without = planner.plan(points, labels, viewpoint=CAMERA)
    finally:
        planner.config = config
    fit_cfg = config.neighbour_fits
    fits, mask, pairs = neighbours.obstacle_fits(without.candidates, [tall, low], fit_cfg)
    assert mask[:2].all() and pairs[0, 1] and pairs[1, 0]
    removed = 0
    for o, (kept, everything) in enumerate(zip(with_fits.candidates, without.candidates)):
        hits = neighbours.fit_hits(everything.poses.astype(np.float32), everything.widths.astype(np.float32),
                                   np.full(len(everything), o, np.int32), fits, mask, SPEC, fit_cfg, 0.05, (64, 512), pairs)
        np.testing.assert_array_equal(kept.poses, everything.poses[~hits])
        assert kept.counts["collision_fit"] == hits.sum() and "collision_fit" not in everything.counts
        removed += hits.sum()
    assert removed > 0 and with_fits.n_candidates == without.n_candidates - removed


def test_second_plan_prefers_candidates_clear_of_the_neighbours_fits(small_db):
    """The second plan (the first finds nothing here) plans with the candidates whose hand meets no other
    object's fit, exactly those, when they give a grasp; when the test removes them all (a fit grown by
    30 cm), it plans with every candidate, where the first plan, which removes them, finds nothing."""
    from sgjax.stage1 import neighbours
    from sgjax.stage1.filters import FilterConfig
    from sgjax.stage1.neighbours import NeighbourFitConfig

    points, labels, tall, low = tall_and_low()
    strong = rigged([0.0, 5.0], [5.0, 5.0, 5.0])
    starved = dataclasses.replace(CONFIG.stage1, filter=FilterConfig(min_points=5000))  # the first plan finds nothing
    second = dataclasses.replace(CONFIG, stage1=starved, fallback_filter=FilterConfig())

    def plan(fit_config):
        return Planner(strong, small_db, dataclasses.replace(second, neighbour_fits=fit_config)).plan(points, labels, viewpoint=CAMERA)

    prefer, everything = plan(NeighbourFitConfig()), plan(None)
    assert prefer.ok and prefer.fallback and everything.ok
    fit_cfg = NeighbourFitConfig()
    fits, mask, pairs = neighbours.obstacle_fits(everything.candidates, [tall, low], fit_cfg)
    removed = 0
    for o, (kept, whole) in enumerate(zip(prefer.candidates, everything.candidates)):
        hits = neighbours.fit_hits(whole.poses.astype(np.float32), whole.widths.astype(np.float32),
                                   np.full(len(whole), o, np.int32), fits, mask, SPEC, fit_cfg, 0.05, (64, 512), pairs)
        np.testing.assert_array_equal(kept.poses, whole.poses[~hits])
        removed += hits.sum()
    assert removed > 0 and prefer.n_candidates == everything.n_candidates - removed

    blocking = NeighbourFitConfig(margin=0.3, max_overlap=1.0)  # every hand meets the other object's fit
    strict = Planner(strong, small_db, dataclasses.replace(CONFIG, neighbour_fits=blocking)).plan(points, labels, viewpoint=CAMERA)
    assert not strict.ok and "meet a neighbour's fitted superquadric" in strict.reason
    rescued = plan(blocking)
    assert rescued.ok and rescued.fallback and rescued.n_candidates == everything.n_candidates
    np.testing.assert_array_equal(rescued.pose, everything.pose)


# ---------------------------------------------------------------------------------------------
# `PlannerConfig.robust`: the choice among the best candidates by scores at perturbed poses.

def test_perturbed_poses_move_and_turn_the_hand_in_its_own_frame():
    rotation = np.asarray(so3_exp(jnp.array([0.3, -0.7, 1.1])), np.float64)
    pose = np.eye(4)
    pose[:3, :3], pose[:3, 3] = rotation, [0.1, -0.2, 0.3]
    out = np.asarray(gripper_mod.perturbed_poses(pose, 0.005, 10.0), np.float64)
    assert out.shape == (5, 4, 4)
    y, z = rotation[:, 1], rotation[:, 2]
    for k, offset in enumerate((-0.005 * y, 0.005 * y, -0.005 * z)):
        np.testing.assert_allclose(out[k, :3, 3], pose[:3, 3] + offset, atol=1e-6)
        np.testing.assert_allclose(out[k, :3, :3], rotation, atol=1e-6)
    for k, sign in ((3, -1.0), (4, 1.0)):
        np.testing.assert_allclose(out[k, :3, 3], pose[:3, 3], atol=1e-6)
        np.testing.assert_allclose(out[k, :3, 2], z, atol=1e-6)  # the same approach axis
        assert np.degrees(np.arctan2(out[k, :3, 0] @ y, out[k, :3, 0] @ rotation[:, 0])) == pytest.approx(sign * 10.0, abs=1e-3)


def test_robust_scores_judge_only_the_best_passing_candidates():
    eval_prob = np.array([0.95, 0.6, 0.9, 0.99, 0.8, np.nan], np.float32)
    valid = np.array([True, True, True, False, True, True])
    asked = []

    def judge(index):
        asked.append(np.asarray(index))
        return np.where(np.asarray(index)[:, None] == 0, 0.2, 0.9) * np.ones((len(index), 5))

    robust = policy.robust_scores(eval_prob, valid, 0.7, 2, judge)
    np.testing.assert_array_equal(asked[0], [0, 2])  # 0.99 is invalid, 0.8 is third, 0.6 and NaN fail
    np.testing.assert_allclose(robust[[0, 2]], [(0.95 + 5 * 0.2) / 6, (0.9 + 5 * 0.9) / 6], atol=1e-6)
    assert np.isnan(robust[[1, 3, 4, 5]]).all()
    choice = {"index": np.int32(0), "kind": np.int32(1), "variant": np.int32(-1), "score": np.float32(0.95), "pose": None}
    out = policy.robust_choice(choice, {"eval_prob": eval_prob, "robust_score": robust})
    assert int(out["index"]) == 2 and out["score"] == pytest.approx(0.9)
    # One passing candidate: nothing to compare, nothing judged, the choice stands.
    alone = policy.robust_scores(eval_prob, valid & (np.arange(6) == 0), 0.7, 4, judge)
    assert np.isnan(alone).all() and len(asked) == 1
    assert policy.robust_choice(choice, {"eval_prob": eval_prob, "robust_score": alone}) is choice


def test_robust_choice_in_the_planner_is_judged_by_ernet_at_the_perturbed_poses(small_db, scene):
    """`PlannerConfig.robust`: the planner's robust scores equal E-RNet's scores at `perturbed_poses` of the
    best passing candidates (called directly), and the plan executes the highest of them."""
    model = ERNet(TINY, rngs=nnx.Rngs(3))
    config = dataclasses.replace(CONFIG, eval_threshold=0.0, robust=planner_mod.RobustChoice(top=4))
    planner = Planner(model, small_db, config)
    plan = planner.plan(*scene, viewpoint=CAMERA, seed=0)
    s = plan.scores
    judged = np.flatnonzero(np.isfinite(s["robust_score"]))
    e = np.where(s["valid"], s["eval_prob"], -np.inf)
    np.testing.assert_array_equal(np.sort(judged), np.sort(np.argsort(-e, kind="stable")[:4]))
    poses = np.stack([plan.candidates[o].poses[r] for o, r in zip(s["object"], s["object_candidate"])]).astype(np.float32)
    widths = np.array([plan.candidates[o].widths[r] for o, r in zip(s["object"], s["object_candidate"])], np.float32)
    perturbed = np.asarray(gripper_mod.perturbed_poses(poses[judged], 0.005, 10.0)).reshape(-1, 4, 4)
    scene_pad, scene_mask = planner._scene(scene[0], 0)
    graphdef, state = nnx.split(model)
    out = ernet.score(graphdef, state, scene_pad, perturbed, np.repeat(widths[judged], 5), scene_mask, spec=SPEC,
                      key=jax.random.key(0))
    around = np.where(out.valid, out.eval_prob, 0.0).reshape(-1, 5)
    np.testing.assert_allclose(s["robust_score"][judged], (s["eval_prob"][judged] + around.sum(1)) / 6, atol=2e-5)
    assert plan.kind == "evaluated" and plan.candidate_index == judged[np.argmax(s["robust_score"][judged])]
    assert plan.score == pytest.approx(float(s["eval_prob"][plan.candidate_index]))


def test_robust_choice_config_errors():
    """Bad `RobustChoice` settings, and more perturbed poses than a Stage-2 call takes, are refused by name."""
    for bad, message in (({"top": 1}, "top must be >= 2"), ({"shift": -0.001}, "shift must be in"),
                         ({"angle_deg": 90.0}, "angle_deg must be in")):
        with pytest.raises(ValueError, match=message):
            planner_mod.RobustChoice(**bad)
    with pytest.raises(ValueError, match="exceed max_stage2_candidates"):
        dataclasses.replace(CONFIG, robust=planner_mod.RobustChoice(top=200))


# ---------------------------------------------------------------------------------------------


def test_judge_gives_a_plans_own_scores(small_db):
    """`Planner.judge` on a plan's scene and seed repeats the scores the plan's Stage 2 gave its candidates:
    another sampler's grasps are judged as the planner's own are."""
    from envs import sensors
    from envs.objects import tiny_object_set
    from envs.scene import stage2_scene_cloud
    from sgjax import presets
    from train.label import LabelConfig, labelled_scene

    planner = Planner(db=small_db, config=presets.get("default", scene_cloud=stage2_scene_cloud()))
    config = LabelConfig(n_objects=3, seed=7, object_set="tiny", held_out_objects=())
    scene, _ = labelled_scene(0, tiny_object_set(), config)
    obs = sensors.sense(scene, config.camera, "exact", seed=3).truth
    plan = planner.plan(obs.points, obs.point_labels, config.camera.position, seed=3)
    scores = plan.scores
    assert scores is not None and len(scores["eval_prob"])
    poses = np.stack([plan.candidates[o].poses[r] for o, r in zip(scores["object"], scores["object_candidate"])])
    widths = np.asarray([plan.candidates[o].widths[r] for o, r in zip(scores["object"], scores["object_candidate"])])
    judged = planner.judge(obs.points, poses, widths, seed=3)
    assert np.array_equal(judged["valid"], scores["valid"])
    assert np.allclose(judged["eval_prob"], scores["eval_prob"], atol=1e-6)
    assert planner.judge(obs.points, poses[:0], widths[:0])["eval_prob"].shape == (0,)
    with pytest.raises(ValueError, match="2 poses but 1 widths"):
        planner.judge(obs.points, poses[:2], widths[:1])
