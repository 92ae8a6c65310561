"""Geometry of the gripper spec: closing/enlarged regions, refinement poses, collision boxes."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sgjax.geometry.gripper import (
    GripperSpec,
    check_width,
    closing_region,
    collides_with_points,
    deepened_pose,
    enlarged_region_poses,
    gripper_boxes,
    hand_boxes,
    hand_samples,
    in_box,
    near_grasps,
    points_in_closing_region,
    points_in_enlarged_region,
    refined_pose,
    refined_poses,
    to_gripper_frame,
    to_world,
    width_in_range,
)
from sgjax.geometry.rotations import random_rotation
from sgjax.geometry.superquadric import pose_matrix

SPEC = GripperSpec()
WIDTH = 0.06  # closing region |x| <= 0.03, |y| <= 0.01, 0 <= z <= 0.05


def random_pose(seed: int, shape: tuple[int, ...] = ()) -> jax.Array:
    k1, k2 = jax.random.split(jax.random.PRNGKey(seed))
    rotation = random_rotation(k1, shape)
    translation = jax.random.uniform(k2, (*shape, 3), minval=-0.5, maxval=0.5)
    return pose_matrix(rotation, translation)


def rot_z_np(deg: float) -> np.ndarray:
    c, s = np.cos(np.deg2rad(deg)), np.sin(np.deg2rad(deg))
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


# Gripper-frame points 3 mm inside / outside each face of the closing region (WIDTH = 0.06).
INSIDE = np.array(
    [
        [0.0, 0.0, 0.025],
        [0.027, 0.0, 0.025],
        [-0.027, 0.0, 0.025],
        [0.0, 0.007, 0.025],
        [0.0, -0.007, 0.025],
        [0.0, 0.0, 0.003],
        [0.0, 0.0, 0.047],
        [0.027, -0.007, 0.047],
    ]
)
OUTSIDE = np.array(
    [
        [0.033, 0.0, 0.025],
        [-0.033, 0.0, 0.025],
        [0.0, 0.013, 0.025],
        [0.0, -0.013, 0.025],
        [0.0, 0.0, -0.003],
        [0.0, 0.0, 0.053],
        [0.033, 0.013, 0.053],
    ]
)


def local_grid(n: int = 4000, seed: int = 0) -> np.ndarray:
    """Uniform gripper-frame points in a box around the gripper's closing and enlarged regions."""
    rng = np.random.default_rng(seed)
    return rng.uniform([-0.05, -0.03, -0.01], [0.05, 0.03, 0.07], (n, 3))


def test_closing_region_box():
    centre, half = closing_region(SPEC, WIDTH)
    np.testing.assert_allclose(centre, [0.0, 0.0, 0.025], atol=1e-7)
    np.testing.assert_allclose(half, [0.03, 0.01, 0.025], atol=1e-7)
    centre, half = closing_region(SPEC, jnp.array([0.02, 0.08]))
    assert centre.shape == half.shape == (2, 3)
    np.testing.assert_allclose(half[:, 0], [0.01, 0.04], atol=1e-7)


@pytest.mark.parametrize("seed", [None, 1, 2])
def test_points_in_closing_region_exact(seed):
    pose = jnp.eye(4) if seed is None else random_pose(seed)
    points = to_world(jnp.asarray(np.concatenate([INSIDE, OUTSIDE]), jnp.float32), pose)
    expected = np.r_[np.ones(len(INSIDE), bool), np.zeros(len(OUTSIDE), bool)]
    np.testing.assert_array_equal(points_in_closing_region(points, pose, WIDTH, SPEC), expected)


def test_classification_invariant_under_rigid_motion():
    pose = random_pose(3)
    points = to_world(jnp.asarray(local_grid(2000), jnp.float32), pose)
    before = points_in_closing_region(points, pose, WIDTH, SPEC)
    before_enlarged = points_in_enlarged_region(points, pose, WIDTH, SPEC)
    motion = random_pose(5)
    moved_points = to_world(points, motion)
    moved_pose = motion @ pose
    assert 0 < int(before.sum()) < len(points)
    np.testing.assert_array_equal(points_in_closing_region(moved_points, moved_pose, WIDTH, SPEC), before)
    np.testing.assert_array_equal(points_in_enlarged_region(moved_points, moved_pose, WIDTH, SPEC), before_enlarged)


def test_frame_round_trip():
    pose = random_pose(6)
    local = jnp.asarray(local_grid(100), jnp.float32)
    np.testing.assert_allclose(to_gripper_frame(to_world(local, pose), pose), local, atol=1e-6)
    # The pose's columns are the gripper axes: a point on +z lies along the approach direction.
    world = to_world(jnp.array([[0.0, 0.0, 0.1]]), pose)
    np.testing.assert_allclose(world[0], pose[:3, 3] + 0.1 * pose[:3, 2], atol=1e-6)


def test_refined_poses_deepen_then_rotate_about_approach():
    pose = random_pose(7)
    deep = deepened_pose(pose, SPEC)
    np.testing.assert_allclose(deep[:3, :3], pose[:3, :3], atol=1e-7)
    np.testing.assert_allclose(deep[:3, 3], pose[:3, 3] + 0.008 * pose[:3, 2], atol=1e-6)
    variants = refined_poses(pose, SPEC)
    assert variants.shape == (3, 4, 4)
    for v, deg in enumerate([-15.0, 0.0, 15.0]):
        one = refined_pose(pose, v, SPEC)
        np.testing.assert_allclose(one, variants[v], atol=1e-6)
        # Same origin as the deepened pose, rotated about its z axis by exactly deg.
        np.testing.assert_allclose(one[:3, 3], deep[:3, 3], atol=1e-6)
        np.testing.assert_allclose(one[3], [0, 0, 0, 1])
        relative = np.asarray(deep[:3, :3]).T @ np.asarray(one[:3, :3])
        np.testing.assert_allclose(relative, rot_z_np(deg), atol=1e-5)
        np.testing.assert_allclose(one[:3, 2], pose[:3, 2], atol=1e-6)  # approach axis unchanged
        angle = np.degrees(np.arccos(np.clip((np.trace(relative) - 1) / 2, -1, 1)))
        assert abs(angle - abs(deg)) < 1e-2
    enlarged = enlarged_region_poses(pose, SPEC)
    assert enlarged.shape == (4, 4, 4)
    np.testing.assert_allclose(enlarged[0], pose)
    np.testing.assert_allclose(enlarged[1:], variants)
    # A traced variant index gives the same poses as the Python int.
    traced = jax.jit(refined_pose, static_argnames="spec")(pose, jnp.array(2), spec=SPEC)
    np.testing.assert_allclose(traced, variants[2], atol=1e-6)


def test_enlarged_region_is_the_union_and_strictly_larger():
    pose = random_pose(8)
    points = to_world(jnp.asarray(local_grid(6000, seed=1), jnp.float32), pose)
    enlarged = np.asarray(points_in_enlarged_region(points, pose, WIDTH, SPEC))
    parts = [np.asarray(points_in_closing_region(points, p, WIDTH, SPEC)) for p in enlarged_region_poses(pose, SPEC)]
    for part in parts:
        assert part.any()
        assert not (part & ~enlarged).any(), "a closing region pokes out of the enlarged region"
        assert enlarged.sum() > part.sum()
    np.testing.assert_array_equal(enlarged, np.any(parts, axis=0))

    # Beyond the fingertips but within the deepened region; and beside the fingers, reached only by +15 deg.
    beyond_tip = np.array([0.0, 0.0, SPEC.finger_length + 0.004])
    beside = np.array([0.025, 0.015, 0.03])
    special = to_world(jnp.asarray(np.stack([beyond_tip, beside]), jnp.float32), pose)
    np.testing.assert_array_equal(points_in_closing_region(special, pose, WIDTH, SPEC), [False, False])
    np.testing.assert_array_equal(points_in_enlarged_region(special, pose, WIDTH, SPEC), [True, True])
    per_variant = [np.asarray(points_in_closing_region(special, refined_pose(pose, v, SPEC), WIDTH, SPEC)) for v in range(3)]
    np.testing.assert_array_equal(np.stack(per_variant), [[True, False], [True, False], [True, True]])


def test_gripper_boxes_layout():
    boxes = gripper_boxes(jnp.eye(4), WIDTH, SPEC)
    assert boxes.centre.shape == (3, 3) and boxes.rotation.shape == (3, 3, 3) and boxes.half_extents.shape == (3, 3)
    np.testing.assert_allclose(boxes.centre, [[-0.035, 0, 0.025], [0.035, 0, 0.025], [0, 0, -0.01]], atol=1e-7)
    np.testing.assert_allclose(boxes.half_extents, [[0.005, 0.01, 0.025], [0.005, 0.01, 0.025], [0.05, 0.015, 0.01]])
    pose = random_pose(9)
    posed = gripper_boxes(pose, WIDTH, SPEC)
    np.testing.assert_allclose(posed.rotation, np.broadcast_to(pose[:3, :3], (3, 3, 3)), atol=1e-7)
    np.testing.assert_allclose(posed.centre, to_world(boxes.centre, pose), atol=1e-6)


@pytest.mark.parametrize("seed", [None, 10])
def test_collision_with_fingers_and_palm(seed):
    pose = jnp.eye(4) if seed is None else random_pose(seed)
    local = {
        "left_finger": [-0.035, 0.0, 0.025],
        "right_finger": [0.035, 0.008, 0.045],
        "palm": [0.0, 0.0, -0.01],
        "between_fingers": [0.0, 0.0, 0.025],
        "near_inner_face": [0.027, 0.0, 0.025],
        "beyond_tips": [0.035, 0.0, 0.053],
        "outside_outer_face": [-0.042, 0.0, 0.025],
    }
    world = {k: to_world(jnp.array([v], jnp.float32), pose) for k, v in local.items()}

    def hits(name, margin=0.0, mask=None):
        return bool(collides_with_points(world[name], mask, pose, WIDTH, SPEC, margin))

    assert hits("left_finger") and hits("right_finger") and hits("palm")
    assert not hits("between_fingers") and not hits("near_inner_face") and not hits("beyond_tips")
    assert not hits("outside_outer_face") and hits("outside_outer_face", margin=0.003)
    assert not hits("left_finger", mask=jnp.array([False]))
    cloud = jnp.concatenate([world["between_fingers"], world["near_inner_face"], world["left_finger"]])
    assert bool(collides_with_points(cloud, jnp.array([True, True, True]), pose, WIDTH, SPEC))
    assert not bool(collides_with_points(cloud, jnp.array([True, True, False]), pose, WIDTH, SPEC))


def test_vmap_over_64_grasps_matches_loop():
    batch, n = 64, 96
    poses = random_pose(11, (batch,))
    widths = jax.random.uniform(jax.random.PRNGKey(12), (batch,), minval=0.01, maxval=SPEC.max_opening)
    # Even grasps get points strictly between the fingers, odd ones points reaching into the fingers.
    unit = np.random.default_rng(13).uniform([-1.0, -1.0, 0.0], [1.0, 1.0, 1.0], (batch, n, 3))
    reach = np.where(np.arange(batch) % 2 == 0, 0.95, 1.5)
    scale = np.stack([0.5 * np.asarray(widths) * reach, np.full(batch, 0.02), np.full(batch, 0.07)], -1)
    points = to_world(jnp.asarray(unit * scale[:, None, :], jnp.float32), poses)
    masks = jnp.asarray(np.random.default_rng(14).random((batch, n)) < 0.5)

    closing = jax.jit(functools.partial(points_in_closing_region, spec=SPEC))
    enlarged = jax.jit(functools.partial(points_in_enlarged_region, spec=SPEC))
    collide = jax.jit(functools.partial(collides_with_points, spec=SPEC))
    got_closing = jax.vmap(closing)(points, poses, widths)
    got_enlarged = jax.vmap(enlarged)(points, poses, widths)
    got_collide = jax.vmap(collide)(points, masks, poses, widths)
    assert got_closing.shape == got_enlarged.shape == (batch, n) and got_collide.shape == (batch,)
    for i in range(batch):
        np.testing.assert_array_equal(got_closing[i], closing(points[i], poses[i], widths[i]))
        np.testing.assert_array_equal(got_enlarged[i], enlarged(points[i], poses[i], widths[i]))
        assert bool(got_collide[i]) == bool(collide(points[i], masks[i], poses[i], widths[i]))
    # Plain broadcasting over the batch axis agrees with vmap too.
    np.testing.assert_array_equal(points_in_closing_region(points, poses, widths, SPEC), got_closing)
    np.testing.assert_array_equal(collides_with_points(points, masks, poses, widths, SPEC), got_collide)
    assert got_closing.any() and not got_closing.all()
    assert not got_collide[::2].any() and got_collide[1::2].any()
    # One shared cloud against all grasps broadcasts to [B, N].
    assert points_in_enlarged_region(points[0], poses, widths, SPEC).shape == (batch, n)


def test_spec_is_hashable_static_argument():
    assert hash(GripperSpec()) == hash(GripperSpec())
    wide = GripperSpec(finger_width=0.04, palm_size=[0.1, 0.05, 0.02])
    assert isinstance(wide.palm_size, tuple)
    fn = jax.jit(points_in_closing_region, static_argnames="spec")
    point = jnp.array([[0.0, 0.015, 0.025]])
    assert not bool(fn(point, jnp.eye(4), WIDTH, spec=SPEC)[0])
    assert bool(fn(point, jnp.eye(4), WIDTH, spec=wide)[0])


def test_width_checks():
    np.testing.assert_array_equal(width_in_range(jnp.array([-0.001, 0.0, 0.05, 0.08, 0.081, jnp.nan]), SPEC),
                                  [False, True, True, True, False, False])
    np.testing.assert_allclose(check_width([0.0, 0.04, 0.08], SPEC), [0.0, 0.04, 0.08])
    with pytest.raises(ValueError, match=r"within \[0, 0.08\].*0.09 at index \(1,\)"):
        check_width([0.02, 0.09], SPEC)
    with pytest.raises(ValueError, match="within"):
        check_width(-0.01, SPEC)
    with pytest.raises(ValueError, match="nan"):
        check_width([np.nan], SPEC)


def test_bad_shapes_raise_clear_errors():
    points, pose = jnp.zeros((5, 3)), jnp.eye(4)
    with pytest.raises(ValueError, match=r"points must have shape \[\.\.\., N, 3\], got \(5, 2\)"):
        points_in_closing_region(jnp.zeros((5, 2)), pose, WIDTH, SPEC)
    with pytest.raises(ValueError, match=r"points must have shape"):
        points_in_enlarged_region(jnp.zeros(3), pose, WIDTH, SPEC)
    with pytest.raises(ValueError, match=r"pose must have shape \[\.\.\., 4, 4\], got \(3, 4\)"):
        points_in_closing_region(points, jnp.zeros((3, 4)), WIDTH, SPEC)
    with pytest.raises(ValueError, match=r"width of shape \(3,\) does not broadcast"):
        points_in_closing_region(points, jnp.broadcast_to(pose, (2, 4, 4)), jnp.zeros(3), SPEC)
    with pytest.raises(ValueError, match=r"mask must have shape \[\.\.\., N\] with N=5"):
        collides_with_points(points, jnp.ones(4, bool), pose, WIDTH, SPEC)
    with pytest.raises(ValueError, match=r"pose must have shape"):
        jax.jit(enlarged_region_poses, static_argnames="spec")(jnp.eye(3), spec=SPEC)
    with pytest.raises(ValueError, match=r"variant must be in \[0, 3\)"):
        refined_pose(pose, 3, SPEC)
    with pytest.raises(ValueError, match="finger_length must be positive"):
        GripperSpec(finger_length=0.0)
    with pytest.raises(ValueError, match="narrower than the open fingers"):
        GripperSpec(palm_size=(0.05, 0.03, 0.02))


def test_local_regions_agree_with_world_boxes():
    from sgjax.geometry.gripper import collides_with_points, local_regions, points_in_closing_region, to_gripper_frame

    rng = np.random.default_rng(3)
    spec = GripperSpec()
    pose = np.eye(4, dtype=np.float32)
    pose[:3, :3] = np.linalg.qr(rng.normal(size=(3, 3)))[0] * np.array([1, 1, 1])
    if np.linalg.det(pose[:3, :3]) < 0:
        pose[:3, 0] *= -1
    pose[:3, 3] = [0.1, -0.2, 0.3]
    pts = (pose[:3, 3] + rng.uniform(-0.07, 0.07, (4000, 3))).astype(np.float32)
    width = 0.05
    closing, gripper = local_regions(to_gripper_frame(jnp.asarray(pts), jnp.asarray(pose)), width, spec)
    np.testing.assert_array_equal(np.asarray(closing), np.asarray(points_in_closing_region(pts, pose, width, spec)))
    assert 0 < int(np.sum(closing)) and 0 < int(np.sum(gripper))
    for i in np.flatnonzero(np.asarray(gripper))[:20]:  # each hit collides on its own, each miss does not
        assert bool(collides_with_points(pts[i : i + 1], None, pose, width, spec))
    for i in np.flatnonzero(~np.asarray(gripper))[:20]:
        assert not bool(collides_with_points(pts[i : i + 1], None, pose, width, spec))


def test_frames_match_the_matrix_formula_batched():
    from sgjax.geometry.rotations import points_from_frame, points_to_frame

    poses = np.asarray(random_pose(11, (5,)), np.float64)
    pts = np.random.default_rng(0).uniform(-0.3, 0.3, (7, 3))
    local = np.asarray(points_to_frame(jnp.asarray(pts, jnp.float32), jnp.asarray(poses[:, :3, :3], jnp.float32),
                                       jnp.asarray(poses[:, :3, 3], jnp.float32)))
    expected = (pts[None] - poses[:, None, :3, 3]) @ poses[:, :3, :3]  # R^T (p - t), row form
    assert local.shape == (5, 7, 3)
    np.testing.assert_allclose(local, expected, atol=1e-6)
    back = points_from_frame(jnp.asarray(expected, jnp.float32), jnp.asarray(poses[:, :3, :3], jnp.float32),
                             jnp.asarray(poses[:, :3, 3], jnp.float32))
    np.testing.assert_allclose(np.asarray(back), np.broadcast_to(pts, (5, 7, 3)), atol=1e-6)


def test_swept_hand_is_the_union_of_hand_positions_along_the_approach():
    from sgjax.geometry.gripper import local_regions

    rng = np.random.default_rng(4)
    local = jnp.asarray(rng.uniform([-0.06, -0.03, -0.12], [0.06, 0.03, 0.07], (20000, 3)), jnp.float32)
    sweep, width = 0.05, 0.05
    _, swept = local_regions(local, width, SPEC, 0.005, sweep)
    # The hand backed off by d sees every point d further along +z; many small steps cover the sweep.
    union = np.zeros(len(local), bool)
    for d in np.linspace(0.0, sweep, 101):
        union |= np.asarray(local_regions(local.at[:, 2].add(d), width, SPEC, 0.005)[1])
    np.testing.assert_array_equal(np.asarray(swept), union)
    _, still = local_regions(local, width, SPEC, 0.005)
    assert np.sum(swept) > np.sum(np.asarray(still)) > 0  # the sweep reaches points the grasp alone does not


def test_segment_regions_are_local_regions_along_the_segments():
    from sgjax.geometry.gripper import local_regions, segment_regions

    rng = np.random.default_rng(5)
    local = jnp.asarray(rng.uniform([-0.07, -0.03, -0.12], [0.07, 0.03, 0.07], (3000, 3)), jnp.float32)
    direction = rng.normal(size=(3000, 3))
    direction[:300, 1:] = 0.0  # axis-parallel segments take the slab test's zero-component branch
    direction = jnp.asarray(direction / np.linalg.norm(direction, axis=1, keepdims=True), jnp.float32)
    width, margin, sweep, length = 0.05, 0.005, 0.05, 0.03
    for got, want in zip(segment_regions(local, direction, 0.0, width, SPEC, margin, sweep),
                         local_regions(local, width, SPEC, margin, sweep)):
        np.testing.assert_array_equal(np.asarray(got), np.asarray(want))
    # A segment meets a box exactly when some point along it lies inside: sample them densely.
    closing, hand = (np.asarray(r) for r in segment_regions(local, direction, length, width, SPEC, margin, sweep))
    dense_c, dense_h = np.zeros(len(local), bool), np.zeros(len(local), bool)
    for t in np.linspace(0.0, length, 601):
        c, h = local_regions(local + t * direction, width, SPEC, margin, sweep)
        dense_c |= np.asarray(c)
        dense_h |= np.asarray(h)
    # Dense sampling may miss a corner clipped by less than its 0.05 mm step; nothing more.
    assert np.sum(closing != dense_c) <= 2 and np.sum(hand != dense_h) <= 2
    assert np.all(dense_c <= closing) and np.all(dense_h <= hand)
    still = np.asarray(local_regions(local, width, SPEC, margin, sweep)[1])
    assert np.sum(hand) > np.sum(still)  # the segments reach boxes their start points miss


def test_near_grasps_is_the_same_grasp_up_to_the_jaw_symmetry():
    from scipy.spatial.transform import Rotation

    base = np.asarray(random_pose(7), np.float64)
    centre = base[:3, 3] + 0.5 * SPEC.finger_length * base[:3, 2]

    def moved(shift_world=(0.0, 0.0, 0.0), turn_local=None):
        """base turned by turn_local (about its closing-region centre) then shifted."""
        pose = base.copy()
        if turn_local is not None:
            pose[:3, :3] = base[:3, :3] @ turn_local
        pose[:3, 3] = centre + np.asarray(shift_world) - 0.5 * SPEC.finger_length * pose[:3, 2]
        return pose

    about = lambda axis, deg: Rotation.from_rotvec(np.deg2rad(deg) * np.asarray(axis, float)).as_matrix()
    poses = np.stack([
        moved(),                                   # the same pose
        moved((0.006, 0.0, 0.008)),                # 1 cm away: still the same grasp
        moved((0.0, 0.0, 0.0102)),                 # just over 1 cm
        moved(turn_local=about((0, 0, 1), 180)),   # the hand turned about its approach axis: the same jaw
        moved(turn_local=about((0, 0, 1), 194)),   # ... and 14 deg more
        moved(turn_local=about((1, 0, 0), 14)),    # tilted 14 deg
        moved(turn_local=about((1, 0, 0), 16)),    # tilted 16 deg
        moved(turn_local=about((0, 1, 0), 180)),   # the approach reversed: another grasp
        moved(turn_local=about((0, 0, 1), 90)),    # closing across: another grasp
    ])
    expected = [True, True, False, True, True, True, False, False, False]
    assert near_grasps(poses, base[None], SPEC, xp=np).tolist() == expected
    assert np.asarray(near_grasps(jnp.asarray(poses, jnp.float32), jnp.asarray(base[None], jnp.float32), SPEC)).tolist() == expected
    assert not near_grasps(poses, np.zeros((0, 4, 4)), SPEC, xp=np).any()  # nothing to avoid
    # Against several poses: near any one of them; looser tolerances take more.
    assert near_grasps(poses, np.stack([poses[2], poses[7]]), SPEC, xp=np)[[2, 7]].all()
    assert near_grasps(poses, base[None], SPEC, max_distance=0.02, max_angle_deg=20, xp=np)[[2, 6]].all()
    # A float32 pose is the same grasp as itself at any tolerance: its rotation, orthonormal only to
    # float32's precision and scaled here by 1 - 1e-6, once fell outside a hundredth of a degree.
    rough = np.asarray(base, np.float32).astype(np.float64)
    rough[:3, :3] *= 1.0 - 1e-6
    assert near_grasps(rough[None], rough[None], SPEC, max_distance=1e-4, max_angle_deg=0.01, xp=np)[0]
    assert not near_grasps(moved(turn_local=about((1, 0, 0), 0.2))[None], base[None], SPEC, max_distance=1e-4,
                           max_angle_deg=0.01, xp=np)[0]
    with pytest.raises(ValueError, match=r"\[K, 4, 4\] and \[F, 4, 4\]"):
        near_grasps(poses, base, SPEC, xp=np)


@pytest.mark.parametrize("sweep", [0.0, 0.05])
def test_hand_samples_fill_the_swept_hand_boxes(sweep):
    """Every sample lies in a finger or the palm (swept back by `sweep`), each box's corners are samples,
    neighbouring samples along an axis are at most `step` apart, and the count does not depend on the width."""
    spec, step = GripperSpec(), 0.006
    widths = np.array([0.0, 0.03, spec.max_opening], np.float32)
    points = np.asarray(hand_samples(spec, widths, sweep, step))
    assert points.shape[:1] == (3,) and points.shape[2] == 3
    for w, pts in zip(widths, points):
        boxes = hand_boxes(spec, float(w), 0.0, sweep)
        inside = np.zeros(len(pts), bool)
        for box in boxes:
            inside |= np.asarray(in_box(pts[:, 0], pts[:, 1], pts[:, 2], (np.add(box[0], -1e-6), np.add(box[1], 1e-6))))
        assert inside.all()
        for lo, hi in boxes:
            for corner in np.array(np.meshgrid(*zip(lo, hi), indexing="ij")).reshape(3, -1).T:
                assert np.min(np.linalg.norm(pts - corner, axis=1)) < 1e-6
            in_this = pts[np.all((pts >= np.add(lo, -1e-6)) & (pts <= np.add(hi, 1e-6)), axis=1)]
            for axis in range(3):
                gaps = np.diff(np.unique(np.round(in_this[:, axis], 6)))
                assert gaps.max() <= step + 1e-6
    with pytest.raises(ValueError, match="step"):
        hand_samples(spec, 0.05, sweep, 0.0)
