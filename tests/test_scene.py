"""Tabletop scenes, the depth camera and the simulated gripper's frame (real MuJoCo, tiny object set)."""

from __future__ import annotations

import mujoco
import numpy as np
import trimesh
import pytest
from scipy.spatial.transform import Rotation

from envs import camera, gripper_model
from envs import rollout as trial_contract
from envs import scene as scene_lib
from envs.objects import tiny_object_set
from sgjax.geometry.gripper import GripperSpec, gripper_boxes

IDENTITY = [1.0, 0.0, 0.0, 0.0]


@pytest.fixture(scope="module")
def objects():
    return tiny_object_set()


@pytest.fixture(scope="module")
def scene(objects):
    return scene_lib.make_scene(objects, 5, seed=3)


def test_same_seed_same_scene_other_seed_differs(objects, scene):
    again = scene_lib.make_scene(objects, 5, seed=3)
    np.testing.assert_array_equal(again.state, scene.state)
    np.testing.assert_array_equal(again.present, scene.present)
    other = scene_lib.make_scene(objects, 5, seed=4)
    assert np.abs(other.object_poses()[:, :3] - scene.object_poses()[:, :3]).max() > 0.01


def test_objects_rest_inside_the_workspace(scene):
    assert scene.at_rest and scene.present.sum() >= 3
    half = 0.5 * scene.config.workspace_size
    poses = scene.object_poses()[scene.present]
    assert (np.abs(poses[:, :2]) <= half).all() and (poses[:, 2] > 0).all()
    # At rest: another 0.2 s of simulation moves nothing by more than a millimetre.
    data = scene.data()
    mujoco.mj_step(scene.model, data, nstep=100)
    adr = scene.model.jnt_qposadr[scene.model.body_jntadr[scene.body_ids[scene.present]]]
    moved = np.stack([data.qpos[a : a + 3] for a in adr]) - poses[:, :3]
    assert np.abs(moved).max() < 1e-3


def test_objects_leaving_the_workspace_are_removed(objects):
    # One box placed past the workspace edge (still on the table), one inside.
    box = objects[0]
    scene = scene_lib.arrange_scene([box, box], [[0.3, 0.0, 0.026, *IDENTITY], [0.0, 0.0, 0.026, *IDENTITY]])
    assert scene.present.tolist() == [False, True]
    np.testing.assert_allclose(scene.object_poses()[0, :3], scene_lib.park_position(0), atol=1e-3)


def test_after_trial_keeps_what_a_failed_grasp_did(objects):
    box = objects[0]
    scene = scene_lib.arrange_scene([box, box], [[-0.1, 0.0, 0.026, *IDENTITY], [0.1, 0.0, 0.026, *IDENTITY]])
    qpos = scene.qpos.copy()
    adr = scene.model.jnt_qposadr[scene.model.body_jntadr[scene.body_ids]]
    # As if a failed grasp had dropped box 0 from 5 cm, 4 cm further along x, turned about z.
    qpos[adr[0] : adr[0] + 7] = [-0.06, 0.0, 0.08, np.cos(0.3), 0.0, 0.0, np.sin(0.3)]
    after = scene_lib.after_trial(scene, qpos)
    poses = after.object_poses()
    assert after.present.all() and after.at_rest
    np.testing.assert_allclose(poses[0, :2], [-0.06, 0.0], atol=5e-3)  # it fell straight down and stays
    assert abs(poses[0, 2] - scene.object_poses()[0, 2]) < 2e-3  # resting on the table again
    np.testing.assert_allclose(poses[1, :3], scene.object_poses()[1, :3], atol=1e-3)  # untouched
    np.testing.assert_array_equal(scene_lib.after_trial(scene, qpos).state, after.state)  # deterministic
    # A box pushed out of the workspace is removed; an invalid trial changes nothing.
    qpos[adr[1] : adr[1] + 3] = [0.3, 0.0, 0.026]
    assert scene_lib.after_trial(scene, qpos).present.tolist() == [True, False]
    assert scene_lib.after_trial(scene, np.full_like(qpos, np.nan)) is scene
    with pytest.raises(ValueError, match="qpos must have shape"):
        scene_lib.after_trial(scene, qpos[:-1])


def test_remove_object_is_deterministic_and_hides_it(scene):
    index = int(np.flatnonzero(scene.present)[0])
    removed = scene_lib.remove_object(scene, index)
    again = scene_lib.remove_object(scene, index)
    np.testing.assert_array_equal(removed.state, again.state)
    assert not removed.present[index] and removed.present.sum() >= scene.present.sum() - 2
    assert removed.model is scene.model  # same compiled model: MJX needs no recompile
    obs = camera.observe(removed, camera.CameraConfig(width=160, height=120))
    assert index not in obs.object_clouds()
    with pytest.raises(ValueError, match="already removed"):
        scene_lib.remove_object(removed, index)
    with pytest.raises(ValueError, match="out of range"):
        scene_lib.remove_object(scene, scene.n_objects)


def test_bad_scene_inputs(objects):
    with pytest.raises(ValueError, match="n_objects"):
        scene_lib.make_scene(objects, 0, seed=0)
    with pytest.raises(ValueError, match="empty"):
        scene_lib.make_scene([], 3, seed=0)
    with pytest.raises(ValueError, match=r"shape \[N, 7\]"):
        scene_lib.arrange_scene(objects[:2], [[0, 0, 0.1, *IDENTITY]])
    with pytest.raises(ValueError, match="unit length"):
        scene_lib.arrange_scene(objects[:1], [[0, 0, 0.1, 1, 1, 0, 0]])
    with pytest.raises(ValueError, match="workspace_size"):
        scene_lib.SceneConfig(workspace_size=1.0, table_size=0.8)


def _surface_distance(asset, pose: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Distances of world points to the asset's visual mesh placed at pose[7]."""
    mesh = scene_lib._load_mesh(asset.visual_path)
    rotation = Rotation.from_quat(np.roll(pose[3:], -1)).as_matrix()
    local = (points - pose[:3]) @ rotation
    # Brute force over every triangle (exact, no spatial index or extra library needed).
    _, distance, _ = trimesh.proximity.closest_point_naive(mesh, local)
    return distance


def test_camera_cloud_lies_on_the_object_surfaces(scene):
    obs = camera.observe(scene)
    clouds = obs.object_clouds()
    assert set(clouds) <= set(np.flatnonzero(scene.present))
    assert len(clouds) >= 3
    for index, cloud in clouds.items():
        distance = _surface_distance(scene.assets[index], scene.object_poses()[index], cloud)
        assert distance.max() < 1e-4, (index, distance.max())
    assert max(len(c) for c in clouds.values()) > 500  # several hundred points per visible object
    table = obs.points[obs.point_labels == scene_lib.TABLE]
    np.testing.assert_allclose(table[:, 2], 0.0, atol=1e-5)
    # Depth is the camera-frame z of each point.
    cam = np.linalg.inv(obs.extrinsic)
    local = obs.points @ cam[:3, :3].T + cam[:3, 3]
    np.testing.assert_allclose(local[:, 2], obs.depth[obs.depth > 0], rtol=1e-5)


def test_rays_cast_in_parts_on_threads_hit_what_one_call_hits(scene, monkeypatch):
    from envs import raycast

    monkeypatch.setattr(raycast, "_MIN_RAYS_PER_THREAD", 1000)
    observations = {}
    for threads in (1, 3):
        monkeypatch.setattr(raycast, "RAY_THREADS", threads)
        observations[threads] = camera.observe(scene)  # 640 x 480 rays
    assert (observations[1].labels >= 0).sum() > 1000  # objects are in view
    np.testing.assert_array_equal(observations[3].depth, observations[1].depth)
    np.testing.assert_array_equal(observations[3].labels, observations[1].labels)
    np.testing.assert_array_equal(observations[3].points, observations[1].points)


def test_depth_noise_is_seeded_and_moves_points_along_rays(scene):
    config = camera.CameraConfig(width=160, height=120)
    exact = camera.observe(scene, config)
    noise = camera.DepthNoise(dropout=0.1)
    noisy = camera.observe(scene, camera.CameraConfig(width=160, height=120, noise=noise), seed=7)
    again = camera.observe(scene, camera.CameraConfig(width=160, height=120, noise=noise), seed=7)
    np.testing.assert_array_equal(noisy.depth, again.depth)
    kept = noisy.depth > 0
    assert 0.05 < 1 - kept.sum() / (exact.depth > 0).sum() < 0.15
    error = (noisy.depth - exact.depth)[kept]
    depth = exact.depth[kept]
    sigma = noise.sigma_base + noise.sigma_quadratic * (depth - 0.4) ** 2
    assert 0.8 < np.std(error / sigma) < 1.2


def test_mjx_camera_sees_what_the_c_camera_sees(scene):
    """mjx.ray (the JAX path) and mj_multiRay hit the same geoms at the same depths, parked objects and
    a removed object included (its pixels show what lies behind it)."""
    config = camera.CameraConfig(width=80, height=60)
    removed = scene_lib.remove_object(scene, int(np.flatnonzero(scene.present)[0]), settle=False)
    for s in (scene, removed):
        c, j = camera.observe(s, config), camera.observe(s, config, backend="mjx")
        np.testing.assert_array_equal(j.labels, c.labels)
        np.testing.assert_allclose(j.depth, c.depth, atol=1e-5)
    with pytest.raises(ValueError, match="camera backend"):
        camera.observe(scene, config, backend="gpu")


def test_camera_config_errors():
    with pytest.raises(ValueError, match="lookat"):
        camera.CameraConfig(position=(0, 0, 1), lookat=(0, 0, 0))
    with pytest.raises(ValueError, match="dropout"):
        camera.DepthNoise(dropout=1.0)


def test_gripper_geoms_match_the_sgjax_gripper_boxes(scene):
    """The simulated gripper frame is the sgjax gripper frame: placed by (pose, width), its MuJoCo
    boxes coincide with sgjax.geometry.gripper.gripper_boxes."""
    spec = GripperSpec()
    pose = np.eye(4)
    pose[:3, :3] = Rotation.from_euler("xyz", [0.3, -1.1, 2.0]).as_matrix()
    pose[:3, 3] = [0.1, -0.2, 0.4]
    width = 0.05
    lay = trial_contract.layout(scene)
    state = trial_contract.initial_states(scene, trial_contract.make_schedule(pose[None], [width], spec), lay)[0]
    data = mujoco.MjData(scene.model)
    mujoco.mj_setState(scene.model, data, state, scene_lib.STATE_SPEC)
    data.qpos[lay.gripper_qpos : lay.gripper_qpos + 3] = pose[:3, 3]  # the grasp pose, not the pre-grasp
    mujoco.mj_forward(scene.model, data)
    boxes = gripper_boxes(pose, width, spec)
    for i, name in enumerate([*gripper_model.FINGER_GEOMS, gripper_model.PALM_GEOM]):
        geom = mujoco.mj_name2id(scene.model, mujoco.mjtObj.mjOBJ_GEOM, name)
        np.testing.assert_allclose(data.geom_xpos[geom], boxes.centre[i], atol=1e-6)
        np.testing.assert_allclose(data.geom_xmat[geom].reshape(3, 3), boxes.rotation[i], atol=1e-6)
        np.testing.assert_allclose(scene.model.geom_size[geom], boxes.half_extents[i], atol=1e-7)
