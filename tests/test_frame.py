"""A real frame in (`sgjax.perception.Frame`): the table, the objects found by segmentation or given as
masks, the frames' conventions and the bad inputs, on a synthetic pinhole camera over a finite table
with boxes on it and a robot's stand beyond its edge."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from sgjax.perception import OTHER, TABLE, Frame, Intrinsics, PerceptionError, SegmentConfig, to_world

K = Intrinsics(fx=300.0, fy=300.0, cx=199.5, cy=149.5, width=400, height=300)
TABLE_HALF = 0.3  # the table top: |x|, |y| <= 0.3 at z = 0; a floor at z = -0.7 around it
# Boxes (centre of the bottom face, half sizes): two apart, one flat (8 mm), a tall one with a short one
# pushed against its side (they touch along a concave crease), and the robot's stand off the table.
SEPARATE = [((-0.12, 0.0, 0.0), (0.03, 0.03, 0.04)), ((0.17, 0.02, 0.0), (0.025, 0.04, 0.03)),
            ((0.0, -0.1, 0.0), (0.04, 0.03, 0.004))]
TOUCHING = [((-0.03, 0.1, 0.0), (0.03, 0.03, 0.06)), ((0.03 + 0.025, 0.1, 0.0), (0.025, 0.03, 0.025))]
STAND = ((0.45, 0.0, -0.7), (0.1, 0.1, 0.48))  # its top 0.26 m above the table, beyond its +x edge


def camera_pose():
    """Camera-to-world [4, 4]: 0.55 m above the table, 0.45 m in front of it, looking at its centre."""
    eye, target = np.array([0.0, -0.45, 0.55]), np.zeros(3)
    z = (target - eye) / np.linalg.norm(target - eye)
    x = np.cross(z, (0.0, 0.0, 1.0))
    x /= np.linalg.norm(x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, np.cross(z, x), z], axis=1)
    T[:3, 3] = eye
    return T


def camera_rays(T=None):
    """(rays [H, W, 3] in the world, each the direction of its pixel with unit camera z (t along it is the
    depth), the camera's origin [3]) of the camera at camera-to-world T (None: `camera_pose()`)."""
    T = camera_pose() if T is None else T
    v, u = np.mgrid[0:K.height, 0:K.width]
    return np.stack([(u - K.cx) / K.fx, (v - K.cy) / K.fy, np.ones_like(u, float)], -1) @ T[:3, :3].T, T[:3, 3]


def render(boxes, T=None, stand=True):
    """(depth [H, W] metres, ids [H, W]: box k + 1, 0 elsewhere) of the table, the floor, the boxes."""
    rays, origin = camera_rays(T)
    with np.errstate(divide="ignore", invalid="ignore"):
        depth = np.full(rays.shape[:2], np.inf)
        for height, extent in ((0.0, TABLE_HALF), (-0.7, np.inf)):
            t = (height - origin[2]) / rays[..., 2]
            at = origin + t[..., None] * rays
            depth = np.where((t > 0) & (np.abs(at[..., :2]).max(-1) <= extent) & (t < depth), t, depth)
        ids = np.zeros(depth.shape, int)
        for k, (centre, half) in enumerate(list(boxes) + ([STAND] if stand else [])):
            centre, half = np.asarray(centre), np.asarray(half)
            lo, hi = centre - half + (0, 0, half[2]), centre + half + (0, 0, half[2])
            t1, t2 = (lo - origin) / rays, (hi - origin) / rays
            near, far = np.minimum(t1, t2).max(-1), np.maximum(t1, t2).min(-1)
            hit = (near <= far) & (near > 0) & (near < depth)
            depth = np.where(hit, near, depth)
            ids = np.where(hit, k + 1 if k < len(boxes) else 0, ids)
    ids = np.where(np.isfinite(depth), ids, 0)
    return np.where(np.isfinite(depth), depth, 0.0), ids  # t along a z = 1 ray is the depth


def truth_of(frame, ids):
    return ids[frame.pixels[:, 0], frame.pixels[:, 1]]


@pytest.mark.parametrize("world", [False, True])
def test_clusters_find_each_object_on_the_table_and_not_the_stand(world):
    depth, ids = render(SEPARATE + TOUCHING)
    frame = Frame.from_depth(depth, K, extrinsics=camera_pose() if world else None)
    assert frame.frame == ("world" if world else "camera") and frame.segmentation == "clusters"
    truth = truth_of(frame, ids)
    assert len(frame.object_ids) == 5  # the flat box too, the touching pair apart, not the stand
    for k in range(1, 6):
        found, counts = np.unique(frame.labels[truth == k], return_counts=True)
        label = found[np.argmax(counts)]
        assert label > 0 and counts.max() >= 0.85 * (truth == k).sum(), k  # one cluster holds the box...
        assert np.mean(truth[frame.labels == label] == k) >= 0.98, k  # ...and little else
    stand = np.linalg.norm(frame.points - frame.points.mean(0), axis=1) >= 0  # every point
    world_points = to_world(frame.points, camera_pose()) if not world else frame.points
    stand = (world_points[:, 0] > TABLE_HALF + 0.01) & (world_points[:, 2] > 0.01)
    assert stand.sum() > 100 and np.all(frame.labels[stand] == OTHER)
    table = (np.abs(world_points[:, 2]) < 1e-6) & (truth == 0)
    assert np.mean(frame.labels[table] == TABLE) > 0.99
    assert np.all(frame.labels[world_points[:, 2] < -0.5] == OTHER)  # the floor


def test_the_joined_hypothesis_gives_the_pieces_a_crease_cuts_off_back():
    """Creases cut small pieces off the boxes' sides (dropped as too small, or small objects of their own);
    the joined hypothesis gives them back to their box, and the touching pair, parted by a crease too, stays
    apart. With masks there is none."""
    depth, ids = render(SEPARATE + TOUCHING)
    frame = Frame.from_depth(depth, K, extrinsics=camera_pose())
    truth = truth_of(frame, ids)
    assert frame.has_joined and frame.joined().segmentation == "joined clusters" and frame.joined().joined_labels is None
    kept = {}
    for name, labels in (("first", frame.labels), ("joined", frame.joined_labels)):
        assert len(np.unique(labels[labels > 0])) == 5
        kept[name] = []
        for k in range(1, 6):
            found, counts = np.unique(labels[truth == k], return_counts=True)
            label = found[np.argmax(counts)]
            assert np.mean(truth[labels == label] == k) >= 0.98, (name, k)
            kept[name].append(counts.max() / np.sum((truth == k) & (labels != TABLE)))
    assert min(kept["joined"]) >= 0.97
    assert sum(kept["joined"]) > sum(kept["first"]) + 0.05  # pieces the joining gave back
    points, labels = frame.joined().table_and_objects()
    assert len(points) == len(labels) and set(np.unique(labels)) == {TABLE, 1, 2, 3, 4, 5}
    # fragment_points 0: the joined hypothesis is the first one.
    same = Frame.from_depth(depth, K, extrinsics=camera_pose(), segment=SegmentConfig(fragment_points=0))
    assert not same.has_joined and np.array_equal(same.labels, frame.labels)
    masked = Frame.from_depth(depth, K, extrinsics=camera_pose(), masks=ids)
    assert masked.joined_labels is None and not masked.has_joined
    with pytest.raises(ValueError, match="no joined hypothesis"):
        masked.joined()


def render_wedges(wedges):
    """(depth, ids) as `render` (the table, the floor, the stand) with prisms instead of boxes: (x0, x1, y0, y1,
    a, b) stands on the table over x0..x1, y0..y1 with its top at z = a + b (x - x0)."""
    depth, ids = render([])
    rays, origin = camera_rays()
    depth = np.where(depth > 0, depth, np.inf)
    with np.errstate(divide="ignore", invalid="ignore"):
        for k, (x0, x1, y0, y1, a, b) in enumerate(wedges):
            normal = np.array([-b, 0.0, 1.0])  # of the top: z - b x = a - b x0
            t = (a - b * x0 - normal @ origin) / (rays @ normal)
            at = origin + t[..., None] * rays
            best = np.where((t > 0) & (at[..., 0] >= x0) & (at[..., 0] <= x1) & (at[..., 1] >= y0) & (at[..., 1] <= y1),
                            t, np.inf)
            for axis, value, (lo, hi) in ((0, x0, (y0, y1)), (0, x1, (y0, y1)), (1, y0, (x0, x1)), (1, y1, (x0, x1))):
                t = (value - origin[axis]) / rays[..., axis]
                at = origin + t[..., None] * rays
                side = ((t > 0) & (at[..., 1 - axis] >= lo) & (at[..., 1 - axis] <= hi) & (at[..., 2] >= 0)
                        & (at[..., 2] <= a + b * (at[..., 0] - x0)))
                best = np.where(side & (t < best), t, best)
            nearer = best < depth
            depth, ids = np.where(nearer, best, depth), np.where(nearer, k + 1, ids)
    return np.where(np.isfinite(depth), depth, 0.0), ids


def test_the_finer_and_parted_hypotheses_part_objects_that_meet_in_a_shallow_crease():
    """Two prisms whose tops meet in a valley of 24 deg (each tilted 12 deg), the second set back 2 cm: a
    crease too shallow for the first labelling (30 deg), so they come out as one object; the finer
    hypothesis (15 deg) parts them, each whole. The parted one takes that cut (two sizeable pieces), keeps
    the same points as objects and is the first the frame offers a planner, the clusters as segmented
    next. With masks there is neither."""
    tilt = np.tan(np.deg2rad(12.0))
    depth, ids = render_wedges([(-0.07, 0.0, -0.03, 0.03, 0.03 + 0.07 * tilt, -tilt),
                                (0.0, 0.07, -0.01, 0.05, 0.03, tilt)])
    frame = Frame.from_depth(depth, K, extrinsics=camera_pose())
    truth = truth_of(frame, ids)
    (merged,) = frame.object_ids
    # (its lowest 4 mm count as table, some 60 points along its outline as no object: 10-15 % of it)
    assert all(np.mean(frame.labels[truth == k] == merged) > 0.8 for k in (1, 2))
    finer, parted = frame.finer(), frame.parted()
    assert finer.segmentation == "finer clusters" and finer.joined_labels is None and len(finer.object_ids) == 2
    assert parted.segmentation == "parted clusters" and parted.joined_labels is None and len(parted.object_ids) == 2
    for cut in (finer, parted):
        for k in (1, 2):
            found, counts = np.unique(cut.labels[truth == k], return_counts=True)
            label = found[np.argmax(counts)]
            assert label > 0 and counts.max() > 0.8 * np.sum(truth == k) and np.all(truth[cut.labels == label] == k)
        np.testing.assert_array_equal(cut.labels[truth <= 0], frame.labels[truth <= 0])  # the table, the rest as before
    np.testing.assert_array_equal(parted.labels > 0, frame.labels > 0)
    order = [h.segmentation for h in frame.hypotheses()]
    assert order[:2] == ["parted clusters", "clusters"] and len(order) == len(set(order))
    # Pieces smaller than part_points: nothing is cut, the clusters come first, the finer ones last.
    whole = Frame.from_depth(depth, K, extrinsics=camera_pose(), segment=SegmentConfig(part_points=100000))
    assert np.array_equal(whole.parted().labels, whole.labels)
    order = [h.segmentation for h in whole.hypotheses()]
    assert order[0] == "clusters" and order[-1] == "finer clusters" and "parted clusters" not in order
    # A finer crease angle equal to the first's: the finer hypothesis is the first, and not offered again.
    same = Frame.from_depth(depth, K, extrinsics=camera_pose(), segment=SegmentConfig(finer_concave_deg=30.0))
    assert np.array_equal(same.finer().labels, same.labels)
    order = [h.segmentation for h in same.hypotheses()]
    assert order[0] == "clusters" and "finer clusters" not in order and "parted clusters" not in order
    masked = Frame.from_depth(depth, K, extrinsics=camera_pose(), masks=ids)
    assert [h.segmentation for h in masked.hypotheses()] == ["masks"]
    for other in (masked.finer, masked.parted):
        with pytest.raises(ValueError, match="only a clustered frame"):
            other()


def test_plan_frame_takes_its_grasp_from_the_parted_hypothesis_or_else_the_finer_one(small_db):
    """Two 6 x 10 cm prisms in a shallow valley come out as one 12 x 10 cm object, wider than the gripper
    opens from every side: no grasp on it (nor on the joined hypothesis). The parted hypothesis, planned
    first, cuts them apart; where it does not (part_points above either prism's size), plan_frame moves on
    to the finer one, which does. Either way the grasp lies on one prism, named by that frame's labels."""
    from sgjax.grasping import plan_frame
    from sgjax.planner import Planner

    tilt = np.tan(np.deg2rad(12.0))
    depth, ids = render_wedges([(-0.06, 0.0, -0.05, 0.05, 0.03 + 0.06 * tilt, -tilt),
                                (0.0, 0.06, -0.03, 0.07, 0.03, tilt)])
    planner = Planner(db=small_db)
    for segment, labelling in ((SegmentConfig(), "parted clusters"), (SegmentConfig(part_points=100000), "finer clusters")):
        frame = Frame.from_depth(depth, K, extrinsics=camera_pose(), segment=segment)
        assert len(frame.object_ids) == 1
        result = plan_frame(planner, frame)
        # plan_frame moves on only when a labelling gives no grasp: for the finer one, the first (and the joined) gave none.
        assert result.frame.segmentation == labelling and len(result.frame.object_ids) == 2
        (grasp,) = result.grasps
        on = truth_of(result.frame, ids)[result.frame.labels == grasp.object]
        assert np.all(on == on[0]) and on[0] in (1, 2)
        assert np.linalg.norm(result.frame.object_points(grasp.object) - grasp.center, axis=1).min() < 0.02


def test_camera_and_world_frames_agree():
    depth, _ = render(SEPARATE)
    camera = Frame.from_depth(depth, K)
    world = Frame.from_depth(depth, K, extrinsics=camera_pose())
    np.testing.assert_array_equal(camera.labels, world.labels)
    np.testing.assert_allclose(to_world(camera.points, camera_pose()), world.points, atol=1e-9)
    np.testing.assert_allclose(world.camera_position, camera_pose()[:3, 3])
    np.testing.assert_allclose(camera.camera_position, 0.0)
    np.testing.assert_allclose(world.table.plane, (0, 0, 1, 0), atol=1e-4)  # world z up, the table z = 0
    # The table frame: z the table's normal (towards the camera), origin on the table below the camera.
    for frame in (camera, world):
        T = frame.table_frame()
        np.testing.assert_allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-9)
        assert np.linalg.det(T[:3, :3]) == pytest.approx(1.0)
        np.testing.assert_allclose(T[:3, 2], frame.table.normal, atol=1e-9)
        assert frame.table.height(T[None, :3, 3])[0] == pytest.approx(0.0, abs=1e-9)
    ref = camera.table_frame()
    np.testing.assert_allclose(camera_pose() @ ref, world.table_frame(), atol=1e-6)


def test_masks_give_their_ids_and_a_workspace_limits_the_frame(tmp_path):
    depth, ids = render(SEPARATE)
    masks = np.where(ids > 0, ids + 10, 0).astype(np.uint16)
    Image.fromarray(masks).save(tmp_path / "masks.png")
    frame = Frame.from_depth(depth, K, masks=tmp_path / "masks.png")
    assert frame.segmentation == "masks" and frame.object_ids == [11, 12, 13]
    truth = truth_of(frame, ids)
    assert np.all(frame.labels[truth > 0] == truth[truth > 0] + 10)
    workspace = np.zeros(depth.shape, bool)
    workspace[100:, : K.width // 2] = True  # the near left of the table (without it, the floor outsizes the table)
    left = Frame.from_depth(depth, K, workspace=workspace)
    assert np.all(left.pixels[:, 1] < K.width // 2) and np.all(left.pixels[:, 0] >= 100)
    assert 1 <= len(left.object_ids) < 3


def test_noisy_depth_still_finds_the_table_and_the_objects():
    depth, ids = render(SEPARATE)
    rng = np.random.default_rng(0)
    noisy = np.where(depth > 0, depth + rng.normal(0.0, 0.0015, depth.shape), 0.0)  # 1.5 mm, a RealSense's at 0.7 m
    frame = Frame.from_depth(noisy, K, extrinsics=camera_pose())
    np.testing.assert_allclose(frame.table.plane, (0, 0, 1, 0), atol=2e-3)
    truth = truth_of(frame, ids)
    assert len(frame.object_ids) == 3
    for k in (1, 2):  # the standing boxes whole; the 8 mm one rises barely above the noise
        found, counts = np.unique(frame.labels[truth == k], return_counts=True)
        assert found[np.argmax(counts)] > 0 and counts.max() >= 0.8 * (truth == k).sum()


def test_depth_in_the_wrong_unit_is_refused_by_name():
    depth, _ = render(SEPARATE)
    with pytest.raises(PerceptionError, match="median depth is .* is the depth in metres"):
        Frame.from_depth(depth * 1000.0, K)  # millimetres given as metres
    with pytest.raises(PerceptionError, match="median depth is .* is depth_scale .1 units per metre. right"):
        Frame.from_depth(np.round(depth * 1000).astype(np.uint16), K, depth_scale=1.0)
    frame = Frame.from_depth(np.round(depth * 1000).astype(np.uint16), K)  # raw 16-bit: depth_scale 1000
    assert len(frame.object_ids) == 3


@pytest.mark.parametrize("case, message", [
    ("zeros", "no valid pixel"), ("nan", "no valid pixel"), ("size", "intrinsics are for 400x300"),
    ("masks", "masks is 10x10 pixels but the depth image is 400x300"), ("workspace", "workspace mask holds no pixel"),
    ("no table", "no table plane found"), ("negative", "negative depths"), ("colour masks", "colour image"),
])
def test_bad_frames_get_one_clear_error(case, message):
    depth, _ = render(SEPARATE)
    kwargs = {}
    if case == "zeros":
        depth = np.zeros_like(depth)
    elif case == "nan":
        depth = np.full_like(depth, np.nan)
    elif case == "size":
        depth = depth[:, :-1]
    elif case == "masks":
        kwargs["masks"] = np.zeros((10, 10), int)
    elif case == "workspace":
        kwargs["workspace"] = np.zeros(depth.shape, bool)
    elif case == "no table":  # a ball: no plane holds 5 % of its points
        v, u = np.mgrid[0:K.height, 0:K.width]
        rays = np.stack([(u - K.cx) / K.fx, (v - K.cy) / K.fy, np.ones_like(u, float)], -1)
        a, b = np.sum(rays**2, -1), -2.0 * rays[..., 2] * 3.0  # centre (0, 0, 3), radius 0.6: |t r - c|^2 = 0.36
        disc = b**2 - 4 * a * (9.0 - 0.36)
        depth = np.where(disc > 0, (-b - np.sqrt(np.maximum(disc, 0))) / (2 * a), 0.0)
    elif case == "negative":
        depth[0, 0] = -1.0
    elif case == "colour masks":
        kwargs["masks"] = np.random.default_rng(0).integers(0, 3, (*depth.shape, 3))
    with pytest.raises(PerceptionError, match=message):
        Frame.from_depth(depth, K, **kwargs)


def test_segment_config_is_checked():
    with pytest.raises(ValueError, match="tolerance > 0"):
        SegmentConfig(tolerance=0.0)
    with pytest.raises(ValueError, match="min_points, normal_window and normal_span >= 1"):
        SegmentConfig(min_points=0)
    with pytest.raises(ValueError, match="0 < concave_deg <= 180"):
        SegmentConfig(concave_deg=0.0)
    with pytest.raises(ValueError, match="fragment_points >= 0"):
        SegmentConfig(fragment_points=-1)
    with pytest.raises(ValueError, match="finer_concave_deg <= concave_deg"):
        SegmentConfig(finer_concave_deg=40.0)
    with pytest.raises(ValueError, match="part_points >= 1"):
        SegmentConfig(part_points=0)
