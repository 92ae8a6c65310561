"""Grasp trials on real MuJoCo: outcomes, the phases' physics, refinements, backends, bad inputs."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from envs import gripper_model, trial
from envs import rollout as trial_contract
from envs import scene as scene_lib
from envs.objects import tiny_object_set
from envs.trial import Outcome, Phase
from sgjax.geometry.gripper import GripperSpec

IDENTITY = [1.0, 0.0, 0.0, 0.0]
# Approach straight down, closing along world x (y = z cross x = -y_world).
DOWN = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])


def grasp(rotation: np.ndarray, origin) -> np.ndarray:
    pose = np.eye(4)
    pose[:3, :3] = rotation
    pose[:3, 3] = origin
    return pose


def axis_z(quat: np.ndarray) -> np.ndarray:
    return Rotation.from_quat(np.roll(quat, -1)).as_matrix()[:, 2]


@pytest.fixture(scope="module")
def assets():
    return {asset.name.split("/")[1]: asset for asset in tiny_object_set()}


@pytest.fixture(scope="module")
def pair(assets):
    """Two 5 cm cubes on the table, 2 cm apart along x: object 0 at the origin, object 1 at x = 7 cm."""
    cube = assets["box_a"]
    return scene_lib.arrange_scene([cube, cube], [[0, 0, 0.026, *IDENTITY], [0.07, 0, 0.026, *IDENTITY]])


# Grasps of cube 0, fingertips 2 cm above the table (gripper origin 7 cm up).
ACROSS_X = grasp(DOWN, [0, 0, 0.07])
IN_THE_AIR = grasp(DOWN, [0.2, 0.2, 0.07])


def test_box_grasped_across_its_faces_is_lifted_reoriented_and_survives_the_disturbance(pair):
    result = trial.run_trials(pair, 0, ACROSS_X[None], [0.065])
    assert result.outcome.tolist() == [Outcome.SUCCESS]
    assert result.label.tolist() == [True]
    assert result.held[0, Phase.LIFT :].all() and not result.held[0, : Phase.LIFT].any()
    start_z = pair.object_poses()[0, 2]
    assert result.object_pose[0, Phase.LIFT, 2] > start_z + 0.9 * trial.TrialConfig().lift_height
    np.testing.assert_allclose(result.opening[0, Phase.CLOSE], 0.05, atol=0.002)  # the cube's width
    np.testing.assert_allclose(axis_z(result.gripper_pose[0, Phase.DISTURB, 3:]), [0, 0, -1], atol=0.01)
    assert result.slip[0] < 0.003
    assert result.max_speed[0] < 1.0


def test_side_grasp_is_turned_until_the_approach_axis_points_down(assets):
    # A 4 x 6 x 12 cm box standing, grasped from -x across its 4 cm faces.
    quat = np.roll(Rotation.from_euler("z", 90, degrees=True).as_quat(), 1)
    scene = scene_lib.arrange_scene([assets["box_b"]], [[0, 0, 0.061, *quat]])
    side = np.stack([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]], axis=1)  # x_g = y, z_g = x
    result = trial.run_trials(scene, 0, grasp(side, [-0.045, 0, 0.08])[None], [0.065])
    assert result.outcome.tolist() == [Outcome.SUCCESS]
    np.testing.assert_allclose(axis_z(result.gripper_pose[0, Phase.LIFT, 3:]), [1, 0, 0], atol=0.01)
    np.testing.assert_allclose(axis_z(result.gripper_pose[0, Phase.HOLD, 3:]), [0, 0, -1], atol=0.01)
    # The object turned with the gripper: its long (z) axis went from vertical to horizontal.
    np.testing.assert_allclose(axis_z(result.object_pose[0, Phase.LIFT, 3:]), [0, 0, 1], atol=0.02)
    np.testing.assert_allclose(axis_z(result.object_pose[0, Phase.HOLD, 3:]), [1, 0, 0], atol=0.02)


def test_grasp_in_the_air_drops(pair):
    result = trial.run_trials(pair, 0, IN_THE_AIR[None], [0.065])
    assert result.outcome.tolist() == [Outcome.DROPPED_LIFT]
    assert result.opening[0, Phase.CLOSE] < 0.002  # closed on nothing


def test_grasp_through_a_neighbour_is_a_collision(pair):
    # Width 7.5 cm puts the right finger (x = 3.75 ... 4.75 cm) into the neighbour (x >= 4.5 cm).
    result = trial.run_trials(pair, 0, np.stack([ACROSS_X, ACROSS_X]), [0.075, 0.065])
    assert result.outcome.tolist() == [Outcome.COLLISION_APPROACH, Outcome.SUCCESS]


def test_instability_after_a_decided_failure_does_not_change_it(pair):
    """INVALID counts NaNs and flung objects up to the deciding phase only (MJX simulates every phase
    of a failed trial, the C engine with early_stop does not)."""
    from envs.backend_cpu import rollout_cpu

    config = trial.TrialConfig(early_stop=False)
    poses, widths = np.stack([ACROSS_X, ACROSS_X]), np.array([0.075, 0.065])  # through the neighbour; clean
    schedule = trial_contract.make_schedule(poses, widths, pair.gripper, config, pair.model.opt.timestep)
    judge = trial_contract.Judge.make(pair, np.zeros(2, int), trial_contract.layout(pair), config)
    rollout = rollout_cpu(pair, judge, schedule)
    assert trial_contract.classify(judge, rollout).outcome.tolist() == [Outcome.COLLISION_APPROACH, Outcome.SUCCESS]

    def outcome_with(field: str, index: tuple, value: float) -> list:
        changed = getattr(rollout, field).copy()
        changed[index] = value
        return trial_contract.classify(judge, dataclasses.replace(rollout, **{field: changed})).outcome.tolist()

    flung = 2 * config.max_object_speed
    assert outcome_with("max_speed", (0, Phase.DISTURB), flung) == [Outcome.COLLISION_APPROACH, Outcome.SUCCESS]
    assert outcome_with("max_speed", (0, Phase.APPROACH), flung) == [Outcome.INVALID, Outcome.SUCCESS]
    assert outcome_with("max_speed", (1, Phase.DISTURB), flung) == [Outcome.COLLISION_APPROACH, Outcome.INVALID]
    assert outcome_with("end_qpos", (0, Phase.LIFT, 0), np.nan) == [Outcome.COLLISION_APPROACH, Outcome.SUCCESS]
    assert outcome_with("end_qpos", (1, Phase.LIFT, 0), np.nan) == [Outcome.COLLISION_APPROACH, Outcome.INVALID]


def test_what_touched_names_the_table_the_neighbour_and_the_part_of_the_hand(pair, assets):
    # (1) the right finger into the neighbour; (2) fingertips 5 mm below the table top, away from the cubes.
    low = grasp(DOWN, [0.2, 0.2, scene_lib.GripperSpec().finger_length - 0.005])
    result = trial.run_trials(pair, 0, np.stack([ACROSS_X, low, ACROSS_X]), [0.075, 0.065, 0.065])
    assert result.outcome.tolist() == [Outcome.COLLISION_APPROACH, Outcome.COLLISION_APPROACH, Outcome.SUCCESS]
    assert result.decided_at.tolist() == [Phase.APPROACH, Phase.APPROACH, Phase.DISTURB]
    finger = trial.what_touched(pair, result, 0)
    assert finger["phase"] == "approach" and not finger["table"] and finger["objects"][1] == "finger"
    table = trial.what_touched(pair, result, 1)
    assert table == {"phase": "approach", "table": True, "objects": {}}
    held = trial.what_touched(pair, result, 2, Phase.LIFT)
    assert held == {"phase": "lift", "table": False, "objects": {0: "finger"}}
    # (3) A 16 cm tall neighbour 1.5 cm beside the open fingers: the 10 cm palm meets it, the fingers do not.
    tall = scene_lib.arrange_scene([assets["box_a"], assets["box_c"]], [[0, 0, 0.026, *IDENTITY], [0.06, 0, 0.081, *IDENTITY]])
    palm = trial.run_trials(tall, 0, ACROSS_X[None], [0.065])
    assert palm.outcome[0] == Outcome.COLLISION_PREGRASP  # the palm is below the neighbour's top already there
    assert trial.what_touched(tall, palm, 0)["objects"] == {1: "palm"}


def test_the_same_scene_with_a_panda_hand(pair):
    """with_gripper keeps the objects' state and swaps the hand: the Panda's 2 cm fingers (ours: 1 cm)
    at the same fingertip position and opening reach into the neighbour 2 cm away."""
    from eval.replay import fingertips_aligned
    from sgjax.geometry.gripper import PANDA_HAND

    panda = scene_lib.with_gripper(pair, PANDA_HAND)
    assert panda.gripper == PANDA_HAND and panda.model is not pair.model
    np.testing.assert_array_equal(panda.state, pair.state)
    np.testing.assert_allclose(panda.object_poses(), pair.object_poses())
    assert scene_lib.with_gripper(pair, pair.gripper) is pair
    assert scene_lib.with_gripper(pair, PANDA_HAND, like=panda).model is panda.model
    pose = fingertips_aligned(ACROSS_X, pair.gripper, PANDA_HAND)
    np.testing.assert_allclose(pose[2, 3] - PANDA_HAND.finger_length, ACROSS_X[2, 3] - pair.gripper.finger_length)
    ours = trial.run_trials(pair, 0, ACROSS_X[None], [0.065])
    theirs = trial.run_trials(panda, 0, pose[None], [0.065])
    assert ours.outcome.tolist() == [Outcome.SUCCESS]
    assert theirs.outcome.tolist() == [Outcome.COLLISION_APPROACH]
    assert trial.what_touched(panda, theirs, 0)["objects"][1] == "finger"
    # Closing along y instead, away from the neighbour, the Panda hand grasps the cube too.
    along_y = grasp(np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]]), pose[:3, 3])
    assert trial.run_trials(panda, 0, along_y[None], [0.065]).outcome.tolist() == [Outcome.SUCCESS]


def test_gripper_placed_in_an_object_collides_before_the_approach(pair):
    # 3 cm open with the fingertips 4 cm up at the pre-grasp: the fingers are inside the 5 cm cube.
    origin_z = 0.04 + scene_lib.GripperSpec().finger_length - trial.TrialConfig().pregrasp_distance
    inside = grasp(DOWN, [0, 0, origin_z])
    pre = grasp(DOWN, [0.07, 0, 0.12])  # fingertips 7 cm up at the grasp: above cube 1, all free
    result = trial.run_trials(pair, [0, 1], np.stack([inside, pre]), [0.03, 0.065])
    assert result.outcome[0] == Outcome.COLLISION_PREGRASP
    assert result.outcome[1] == Outcome.DROPPED_LIFT  # fingertips 7 cm up: above the cube, closes on air


def test_weak_grip_holds_the_lift_but_slides_under_the_disturbance(assets):
    config = scene_lib.SceneConfig(gripper_physics=gripper_model.GripperPhysics(grip_force=0.6))
    scene = scene_lib.arrange_scene([assets["box_a"]], [[0, 0, 0.026, *IDENTITY]], config)
    result = trial.run_trials(scene, 0, ACROSS_X[None], [0.065])
    assert result.outcome.tolist() == [Outcome.DROPPED_DISTURBANCE]
    assert result.held[0, Phase.HOLD]
    # Approach points down: the object moving down relative to the fingers is +z in the gripper frame.
    shift = result.object_in_gripper[0, Phase.DISTURB] - result.object_in_gripper[0, Phase.HOLD]
    assert shift[2] > trial.TrialConfig().max_slip and abs(shift[0]) < 0.005
    # Without the 1 N force the same grasp survives.
    calm = trial.run_trials(scene, 0, ACROSS_X[None], [0.065], config=trial.TrialConfig(disturbance_force=0.0))
    assert calm.outcome.tolist() == [Outcome.SUCCESS]


@pytest.mark.parametrize(("force", "most"), [(25.0, 0.0004), (140.0, 0.001)])
def test_the_pads_give_little_however_hard_the_grip(assets, force, most):
    """A 5 cm cube squeezed face on sinks into each pad by about what its contact parameters allow
    (`GripperPhysics.pad_solref`, `pad_solimp`: ~0.2 mm at 25 N, ~0.6 mm at a Franka hand's 140 N peak).
    Without the pads' geom priority MuJoCo averaged them with the object's softer defaults: 0.8 and 4.1 mm,
    and objects squeezed by a strong gripper slid out of it under the disturbance."""
    spec = dataclasses.replace(GripperSpec(), closing_force=force)
    scene = scene_lib.arrange_scene([assets["box_a"]], [[0, 0, 0.026, *IDENTITY]], gripper=spec)
    result = trial.run_trials(scene, 0, ACROSS_X[None], [0.065])
    assert result.outcome.tolist() == [Outcome.SUCCESS]
    sunk = 0.5 * (0.05 - result.opening[0, Phase.CLOSE :])  # per pad, each phase from the close on
    assert (sunk > 0.0).all() and (sunk < most).all(), sunk


def test_violent_simulation_is_invalid_never_success(pair):
    result = trial.run_trials(pair, 0, ACROSS_X[None], [0.065], config=trial.TrialConfig(disturbance_force=1e4))
    assert result.outcome.tolist() == [Outcome.INVALID]


def test_early_stop_keeps_outcomes(pair):
    poses = np.stack([ACROSS_X, ACROSS_X, IN_THE_AIR])
    widths = [0.065, 0.075, 0.065]
    fast = trial.run_trials(pair, 0, poses, widths)
    full = trial.run_trials(pair, 0, poses, widths, config=trial.TrialConfig(early_stop=False, batch_size=2))
    np.testing.assert_array_equal(fast.outcome, full.outcome)
    np.testing.assert_allclose(fast.object_pose[0], full.object_pose[0])


def test_refinements_give_four_labels_per_grasp(pair):
    # Fingertips 7 cm up close on air; deepened by 8 mm they still do. At 2 cm they hold the cube.
    poses = np.stack([grasp(DOWN, [0, 0, 0.12]), ACROSS_X])
    labels, result = trial.run_grasp_with_refinements(pair, 0, poses, [0.065, 0.065])
    assert labels.shape == (2, 4) and labels.dtype == bool
    assert not labels[0].any()
    # Cube grasped across x; rotated +-15 deg the 6.5 cm opening still clears the 5 cm cube.
    assert labels[1].all()
    deep = result.gripper_pose.reshape(2, 4, len(Phase), 7)[1, 2, Phase.CLOSE, :3]
    np.testing.assert_allclose(deep, [0, 0, 0.07 - 0.008], atol=0.002)


def test_schedule_reaches_the_grasp_and_turns_down():
    spec = pair_spec = scene_lib.GripperSpec()
    config = trial.TrialConfig()
    schedule = trial_contract.make_schedule(ACROSS_X[None], [0.06], spec, config)
    steps = np.cumsum(schedule.phase_steps)
    assert schedule.nstep == steps[-1] == sum(config.phase_steps(0.002))
    pre = ACROSS_X[:3, 3] - config.pregrasp_distance * ACROSS_X[:3, 2]
    np.testing.assert_allclose(schedule.init_qpos[0, :3], pre)
    np.testing.assert_allclose(schedule.mocap_pos[0, steps[Phase.APPROACH] - 1], ACROSS_X[:3, 3])
    assert schedule.finger_ctrl[0, 0] == pytest.approx(0.03)
    assert schedule.finger_ctrl[0, steps[Phase.CLOSE] - 1] == pytest.approx(config.close_target)
    np.testing.assert_allclose(axis_z(schedule.mocap_quat[0, -1]), [0, 0, -1], atol=1e-9)
    assert schedule.phase_force[Phase.DISTURB] == 1.0 and schedule.phase_force.sum() == 1.0
    again = trial_contract.make_schedule(ACROSS_X[None], [0.06], pair_spec, config)
    np.testing.assert_array_equal(again.mocap_quat, schedule.mocap_quat)


def test_bad_inputs_raise_clear_errors(pair):
    with pytest.raises(ValueError, match=r"shape \[M, 4, 4\]"):
        trial.run_trials(pair, 0, np.eye(4), [0.05])
    with pytest.raises(ValueError, match="widths must have shape"):
        trial.run_trials(pair, 0, ACROSS_X[None], [0.05, 0.05])
    sheared = ACROSS_X.copy()
    sheared[0, 1] = 0.3
    with pytest.raises(ValueError, match="not a rigid transform"):
        trial.run_trials(pair, 0, sheared[None], [0.05])
    mirrored = ACROSS_X.copy()
    mirrored[:3, 0] *= -1
    with pytest.raises(ValueError, match="not a rigid transform"):
        trial.run_trials(pair, 0, mirrored[None], [0.05])
    nan = ACROSS_X.copy()
    nan[0, 3] = np.nan
    with pytest.raises(ValueError, match="non-finite"):
        trial.run_trials(pair, 0, nan[None], [0.05])
    with pytest.raises(ValueError, match="max_opening"):
        trial.run_trials(pair, 0, ACROSS_X[None], [0.09])
    with pytest.raises(ValueError, match="max_opening"):
        trial.run_trials(pair, 0, ACROSS_X[None], [-0.01])
    with pytest.raises(ValueError, match="targets must be in"):
        trial.run_trials(pair, 5, ACROSS_X[None], [0.05])
    with pytest.raises(ValueError, match="one per grasp"):
        trial.run_trials(pair, [0, 1, 0], ACROSS_X[None], [0.05])
    with pytest.raises(ValueError, match="backend"):
        trial.run_trials(pair, 0, ACROSS_X[None], [0.05], backend="bullet")
    with pytest.raises(ValueError, match="GripperSpec"):
        trial.run_trials(pair, 0, ACROSS_X[None], [0.05], spec=scene_lib.GripperSpec(max_opening=0.06, palm_size=(0.1, 0.03, 0.02)))
    removed = scene_lib.remove_object(pair, 1, settle=False)
    with pytest.raises(ValueError, match="removed"):
        trial.run_trials(removed, 1, ACROSS_X[None], [0.05])


def test_sleeping_neighbours_change_nothing(pair):
    """With TrialConfig.sleep the resting neighbour sleeps; grasping and lifting cube 0 beside it gives
    the same outcomes and nearly the same trajectories as without, and the scene's model is untouched."""
    flags = pair.model.opt.enableflags
    poses, widths = np.stack([ACROSS_X, IN_THE_AIR]), [0.065, 0.065]
    awake = trial.run_trials(pair, 0, poses, widths, config=trial.TrialConfig(sleep=False))
    asleep = trial.run_trials(pair, 0, poses, widths, config=trial.TrialConfig(sleep=True))
    assert asleep.outcome.tolist() == awake.outcome.tolist() == [Outcome.SUCCESS, Outcome.DROPPED_LIFT]
    np.testing.assert_allclose(asleep.object_pose[:, :, :3], awake.object_pose[:, :, :3], atol=0.005)
    assert pair.model.opt.enableflags == flags


@pytest.mark.slow
def test_cpu_and_mjx_backends_agree(assets):
    """Same trials on the C engine and MJX give the same outcomes (MJX compiles for ~20-60 s on CPU)."""
    pytest.importorskip("mujoco.mjx")
    scene = scene_lib.arrange_scene([assets["box_a"]], [[0, 0, 0.026, *IDENTITY]])
    poses, widths = np.stack([ACROSS_X, IN_THE_AIR]), [0.065, 0.065]
    cpu = trial.run_trials(scene, 0, poses, widths, backend="cpu")
    mjx = trial.run_trials(scene, 0, poses, widths, backend="mjx-jax")
    assert cpu.outcome.tolist() == [Outcome.SUCCESS, Outcome.DROPPED_LIFT]
    np.testing.assert_array_equal(mjx.outcome, cpu.outcome)
    np.testing.assert_array_equal(mjx.held, cpu.held)
    np.testing.assert_allclose(mjx.object_pose[0, :, :3], cpu.object_pose[0, :, :3], atol=0.01)
    # The pads' contact parameters hold in MJX too (its contacts honour the pads' geom priority).
    np.testing.assert_allclose(mjx.opening[0, Phase.CLOSE :], cpu.opening[0, Phase.CLOSE :], atol=0.0003)


def test_mjx_on_cpu_factors_without_lapack():
    """MJX's rollout on CPU lowers Cholesky to plain JAX ops (`cpu_safe_cholesky`): jaxlib 0.10's batched
    LAPACK kernel deadlocked XLA's CPU pool inside MJX (`sgjax label --backend mjx` hung). Same factors,
    NaN for a matrix that is not positive definite, and only inside the block."""
    import jax

    from envs.backend_mjx import cholesky_columns, cpu_safe_cholesky

    rng = np.random.default_rng(0)
    x = rng.normal(size=(8, 12, 12))
    a = (x @ x.transpose(0, 2, 1) + 12 * np.eye(12)).astype(np.float32)
    with cpu_safe_cholesky():
        inside = jax.jit(lambda m: jax.scipy.linalg.cho_factor(m, lower=True)[0])
        text, got = inside.lower(a).as_text(), np.tril(np.asarray(inside(a)))
    outside = jax.jit(lambda m: jax.scipy.linalg.cho_factor(m, lower=True)[0] * 1.0).lower(a).as_text()
    assert "potrf" not in text and "potrf" in outside
    np.testing.assert_allclose(got, np.linalg.cholesky(a.astype(np.float64)), atol=1e-5)
    bad = a.copy()
    bad[0] = -np.eye(12)
    out = np.asarray(cholesky_columns(bad))
    assert np.isnan(out[0]).all() and np.isfinite(out[1:]).all()


@pytest.mark.slow
def test_cpu_and_mjx_warp_agree(pair):
    """MJX's warp implementation (on CPU here; needs warp-lang) gives the C engine's outcomes too, with
    each trial counting only its own world's contacts in warp's shared contact buffer: the grasp through
    the neighbour collides, and the trial next to it in the batch must not see that contact."""
    from envs.backend_mjx import warp_available

    if not warp_available():
        pytest.skip("warp-lang is not installed")
    poses, widths = np.stack([ACROSS_X, ACROSS_X, IN_THE_AIR]), [0.075, 0.065, 0.065]
    cpu = trial.run_trials(pair, 0, poses, widths, backend="cpu")
    warp = trial.run_trials(pair, 0, poses, widths, backend="mjx-warp")
    assert cpu.outcome.tolist() == [Outcome.COLLISION_APPROACH, Outcome.SUCCESS, Outcome.DROPPED_LIFT]
    np.testing.assert_array_equal(warp.outcome, cpu.outcome)
    # The C engine stops the decided collision early (its later phases are not simulated); MJX runs on.
    np.testing.assert_array_equal(warp.held[1:], cpu.held[1:])
    np.testing.assert_allclose(warp.object_pose[1, :, :3], cpu.object_pose[1, :, :3], atol=0.01)


def test_backend_names_are_checked():
    from envs.backend_mjx import resolve_impl, warp_available

    with pytest.raises(ValueError, match="backend must be one of 'cpu', 'mjx', 'mjx-jax', 'mjx-warp'"):
        trial.check_backend("gpu")
    with pytest.raises(ValueError, match="impl must be"):
        resolve_impl("cuda")
    assert resolve_impl("jax") == "jax"
    import jax

    assert resolve_impl("auto") == ("warp" if warp_available() and jax.default_backend() == "gpu" else "jax")
    if warp_available():
        assert resolve_impl("warp") == "warp"
    else:
        with pytest.raises(ValueError, match="needs the warp-lang package"):
            resolve_impl("warp")
