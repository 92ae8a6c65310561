"""A real frame's front end (`sgjax.perception`): calibration files, depth images, back-projection and
the table plane, against a synthetic pinhole camera looking down at a table with a box on it."""

from __future__ import annotations

import json

import numpy as np
import pytest
from PIL import Image

from sgjax.perception import Intrinsics, back_project, fit_table, read_depth, read_extrinsics, read_intrinsics, to_world

K = Intrinsics(fx=600.0, fy=610.0, cx=159.5, cy=119.5, width=320, height=240)


def tilted_camera():
    """A camera 0.6 m above a table z = 0, looking down and 30 deg forward: camera-to-world [4, 4]."""
    tilt = np.deg2rad(30.0)
    # Camera axes in the world: x right, y down (in the image), z forward (the viewing ray).
    z = np.array([0.0, np.sin(tilt), -np.cos(tilt)])
    x = np.array([1.0, 0.0, 0.0])
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, y, z], axis=1)
    T[:3, 3] = (0.0, -0.3, 0.6)
    return T


def render(T, box=((0.0, 0.05, 0.0), (0.06, 0.04, 0.05))):
    """The depth image [H, W] (metres) of the table z = 0 and an axis-aligned box (centre, half sizes) on it."""
    v, u = np.mgrid[0:K.height, 0:K.width]
    rays = np.stack([(u - K.cx) / K.fx, (v - K.cy) / K.fy, np.ones_like(u, float)], -1)  # camera frame, z = 1
    world = rays @ T[:3, :3].T  # ray directions in the world
    origin = T[:3, 3]
    t_table = -origin[2] / world[..., 2]
    depth = np.where(t_table > 0, t_table, np.inf)
    centre, half = np.asarray(box[0]), np.asarray(box[1])
    lo, hi = centre - half + (0, 0, half[2]), centre + half + (0, 0, half[2])
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (lo - origin) / world, (hi - origin) / world
    near, far = np.minimum(t1, t2).max(-1), np.maximum(t1, t2).min(-1)
    hit = (near <= far) & (near > 0)
    return np.where(hit, np.minimum(depth, near), depth)  # t along a z = 1 ray is the depth


def test_back_projection_inverts_the_pinhole_model():
    depth = np.zeros((K.height, K.width), np.float32)
    depth[10, 20], depth[200, 300], depth[119, 159] = 0.5, 1.25, 2.0
    points, pixels = back_project(depth, K)
    assert len(points) == 3 and pixels.tolist() == [[10, 20], [119, 159], [200, 300]]
    u = K.fx * points[:, 0] / points[:, 2] + K.cx
    v = K.fy * points[:, 1] / points[:, 2] + K.cy
    np.testing.assert_allclose(np.c_[v, u], pixels, atol=1e-9)
    np.testing.assert_allclose(points[:, 2], [0.5, 2.0, 1.25])
    assert len(back_project(depth, K, max_depth=1.5)[0]) == 2
    with pytest.raises(ValueError, match="the depth image is 20x10 pixels but the intrinsics are for 320x240"):
        back_project(np.ones((10, 20)), K)


def test_depth_files_read_in_metres(tmp_path):
    metres = render(tilted_camera())
    metres = np.where(np.isfinite(metres) & (metres < 3.0), metres, 0.0)
    png = tmp_path / "depth.png"
    Image.fromarray(np.round(metres * 1000).astype(np.uint16)).save(png)
    np.testing.assert_allclose(read_depth(png), metres, atol=5e-4 + 1e-6)
    np.testing.assert_allclose(read_depth(png, depth_scale=4000.0), read_depth(png) / 4, atol=1e-6)
    np.save(tmp_path / "depth.npy", np.where(metres > 0, metres, np.nan))  # NaN: no depth
    np.testing.assert_allclose(read_depth(tmp_path / "depth.npy"), metres, atol=1e-6)
    np.savez(tmp_path / "frame.npz", depth=metres, rgb=np.zeros((2, 2, 3)))
    np.testing.assert_allclose(read_depth(tmp_path / "frame.npz"), metres, atol=1e-6)
    np.save(tmp_path / "bad.npy", -metres)
    with pytest.raises(ValueError, match="negative depths"):
        read_depth(tmp_path / "bad.npy")
    with pytest.raises(ValueError, match="depth_scale must be a number > 0"):
        read_depth(png, depth_scale=0)
    with pytest.raises(FileNotFoundError, match="no such depth image"):
        read_depth(tmp_path / "none.png")


def test_intrinsics_from_every_format(tmp_path):
    (tmp_path / "k.json").write_text(json.dumps({"K": K.K.tolist(), "width": 320, "height": 240}))
    (tmp_path / "f.json").write_text(json.dumps({"fx": 600, "fy": 610, "cx": 159.5, "cy": 119.5}))
    (tmp_path / "ros.yaml").write_text(
        "image_width: 320\nimage_height: 240\ncamera_name: rs\ncamera_matrix:\n  rows: 3\n  cols: 3\n"
        f"  data: {K.K.reshape(-1).tolist()}\ndistortion_model: plumb_bob\n")
    np.save(tmp_path / "k.npy", K.K)
    assert read_intrinsics(tmp_path / "k.json") == K == read_intrinsics(tmp_path / "ros.yaml")
    assert read_intrinsics(tmp_path / "f.json") == Intrinsics(600, 610, 159.5, 119.5)
    assert read_intrinsics(tmp_path / "k.npy").K.tolist() == K.K.tolist()
    (tmp_path / "miss.json").write_text(json.dumps({"fx": 600, "cx": 1}))
    with pytest.raises(ValueError, match=r"miss.json: missing field\(s\) fy, cy"):
        read_intrinsics(tmp_path / "miss.json")
    (tmp_path / "neg.json").write_text(json.dumps({"fx": -1, "fy": 1, "cx": 1, "cy": 1}))
    with pytest.raises(ValueError, match="neg.json: intrinsics: fx and fy must be > 0"):
        read_intrinsics(tmp_path / "neg.json")
    (tmp_path / "other.yaml").write_text("foo: 1\n")
    with pytest.raises(ValueError, match="no 'camera_matrix'"):
        read_intrinsics(tmp_path / "other.yaml")


def test_extrinsics_are_checked_rigid(tmp_path):
    T = tilted_camera()
    (tmp_path / "t.json").write_text(json.dumps(T.tolist()))
    np.save(tmp_path / "t.npy", T)
    np.testing.assert_array_equal(read_extrinsics(tmp_path / "t.json"), read_extrinsics(tmp_path / "t.npy"))
    bad = T.copy()
    bad[:3, :3] *= 1.1
    np.save(tmp_path / "scaled.npy", bad)
    with pytest.raises(ValueError, match="not a proper rotation"):
        read_extrinsics(tmp_path / "scaled.npy")


@pytest.mark.parametrize("seed", [0, 1])
def test_the_table_is_found_with_its_normal_towards_the_camera(seed):
    """In the camera frame (no extrinsics) the fit's plane is the true table's, seen from the camera,
    with sensor noise and a box on it; with the extrinsics it is z = 0, normal up."""
    T = tilted_camera()
    depth = render(T)
    depth = np.where(np.isfinite(depth) & (depth < 2.0), depth, 0.0)
    depth = depth + np.random.default_rng(seed).normal(0, 0.001, depth.shape) * (depth > 0)
    points, _ = back_project(depth, K)
    table = fit_table(points, seed=seed)
    # The true table in the camera frame: world z = 0 -> n_c = R^T e_z, d = t_z.
    truth = np.r_[T[:3, :3].T @ (0, 0, 1.0), T[2, 3]]
    assert np.degrees(np.arccos(np.clip(table.normal @ truth[:3], -1, 1))) < 1.0
    assert abs(table.plane[3] - truth[3]) < 0.003 and table.rms < 0.0025
    world = to_world(points, T)
    on_box = world[:, 2] > 0.01
    assert on_box.sum() > 500 and len(points) > 0.9 * K.width * K.height  # the box and the table in view
    assert not table.inliers[on_box].any() and table.inliers[world[:, 2] < 0.002].mean() > 0.95
    np.testing.assert_allclose(table.height(points)[on_box], world[on_box, 2], atol=0.006)
    up = fit_table(world, viewpoint=T[:3, 3], seed=seed, max_tilt_deg=10.0, up=(0, 0, 1))
    np.testing.assert_allclose(up.normal, (0, 0, 1), atol=0.01)
    assert fit_table(points, seed=seed).plane == table.plane  # the same seed, the same plane
    # The heights it leaves are the points' heights over its plane.
    np.testing.assert_array_equal(table.heights, table.height(points))
    # Points that are not finite take no part: the rest's plane; they are no inliers.
    broken = points.copy()
    broken[::97, 1], broken[1::97, 2] = np.nan, np.inf
    spoilt = fit_table(broken, seed=seed)
    assert np.degrees(np.arccos(np.clip(spoilt.normal @ truth[:3], -1, 1))) < 1.0
    assert not spoilt.inliers[::97].any() and not spoilt.inliers[1::97].any()
    with pytest.raises(ValueError, match="at least 3 finite points"):
        fit_table(points[:2])


def test_the_front_end_runs_blas_on_one_thread_and_gives_it_back():
    """`one_blas_thread` (what Frame.from_depth runs in) holds every loaded BLAS to one thread and
    restores the previous counts on exit, also when the body raises."""
    from threadpoolctl import threadpool_info

    from sgjax.utils.threads import one_blas_thread

    def blas() -> list[int]:
        return [lib["num_threads"] for lib in threadpool_info() if lib["user_api"] == "blas"]

    import scipy.linalg

    np.ones((64, 3)) @ np.ones((3, 3))  # NumPy's BLAS is loaded, and SciPy's own (whichever loads first)
    scipy.linalg.blas.dgemm(1.0, np.ones((4, 3)), np.ones((3, 3)))
    before = blas()
    assert before
    with pytest.raises(RuntimeError):
        with one_blas_thread():
            assert blas() == [1] * len(before)
            raise RuntimeError("inside")
    assert blas() == before


def test_point_in_convex_polygon_matches_every_edges_half_plane():
    """`in_convex_polygon`'s one-edge test (the wedge facing each point) against the definition: inside
    a counter-clockwise convex polygon <=> on the left of every edge."""
    from scipy.spatial import ConvexHull

    from sgjax.perception.segment import in_convex_polygon

    rng = np.random.default_rng(3)
    for _ in range(50):
        cloud = rng.normal(size=(int(rng.integers(3, 200)), 2)) * rng.uniform(0.1, 2.0, 2) + rng.normal(size=2)
        corners = cloud[ConvexHull(cloud).vertices]
        points = rng.normal(size=(2000, 2)) * 2.0 + corners.mean(0)
        edges = np.roll(corners, -1, 0) - corners
        left = (edges[:, 0] * (points[:, None, 1] - corners[:, 1]) - edges[:, 1] * (points[:, None, 0] - corners[:, 0]))
        expected = np.all(left >= 0, axis=1)
        got = in_convex_polygon(points, corners)
        assert got.any() and (~got).any()
        np.testing.assert_array_equal(got, expected)


def test_image_clusters_match_the_definition_pair_by_pair():
    """`image_clusters` (links labelled on a grid of twice the resolution) against its definition,
    written out pixel pair by pair with a union-find: the same partition of the member pixels, with and
    without the crease test, and the same pairs parted by a crease."""
    from sgjax.perception.segment import image_clusters, smooth_normals

    rng = np.random.default_rng(5)
    h, w, span = 23, 31, 2
    for trial in range(6):
        # Two tilted planes at different depths with noise: some steps link, some do not, some creases bend.
        yy, xx = np.mgrid[:h, :w].astype(np.float32)
        depth = np.where(xx < w // 2, 1.0 + 0.01 * yy, 1.05 - 0.02 * xx / w) + rng.normal(0, 0.002, (h, w))
        image = np.stack([xx * 0.003, yy * 0.003, depth]).astype(np.float32)  # channel-first [3, h, w]
        member = rng.random((h, w)) < 0.8
        normals = smooth_normals(image, np.ones((h, w), bool), np.zeros(3), 3, span)
        tolerance = np.full((h, w), 0.004, np.float32)
        for concave_deg in (30.0, 180.0):
            creases: list = []
            got = image_clusters(image, member, normals, tolerance, concave_deg, span, creases)
            parent = list(range(h * w))
            parted = set()

            def find(i):
                while parent[i] != i:
                    parent[i] = parent[parent[i]]
                    i = parent[i]
                return i

            for r in range(h):
                for c in range(w):
                    for dr, dc in ((0, 1), (1, 0)):
                        r2, c2 = r + dr, c + dc
                        if r2 >= h or c2 >= w or not (member[r, c] and member[r2, c2]):
                            continue
                        if np.sum((image[:, r, c] - image[:, r2, c2]) ** 2) > tolerance[r, c] ** 2:
                            continue
                        ra, ca = min(max(r - dr * span, 0), h - 1), min(max(c - dc * span, 0), w - 1)
                        rb, cb = min(r2 + dr * span, h - 1), min(c2 + dc * span, w - 1)
                        na, nb = normals[:, ra, ca], normals[:, rb, cb]
                        if na @ nb < np.cos(np.deg2rad(concave_deg)) and (na - nb) @ (image[:, ra, ca] - image[:, rb, cb]) < 0:
                            parted.add((r * w + c, r2 * w + c2))
                            continue
                        parent[find(r * w + c)] = find(r2 * w + c2)
            expected = np.array([find(i) for i in range(h * w)]).reshape(h, w)
            assert np.array_equal(got >= 0, member)
            pairs = {(int(a), int(b)) for a, b in zip(got[member], expected[member])}
            # One-to-one: each found component is one expected component and back.
            assert len(pairs) == len({a for a, _ in pairs}) == len({b for _, b in pairs}), (trial, concave_deg)
            assert 1 < len(pairs) < member.sum()
            # The pairs a crease parted, as merge_fragments gets them.
            found = {(int(a), int(b)) for first, second in creases for a, b in zip(first, second)}
            assert found == parted and (len(parted) > 0) == (concave_deg < 180.0)


def test_what_goes_on_below_the_table_is_the_members_linked_to_points_below_it():
    """`_continues_below` (the members' components and creases joined with the band and the points below
    over a graph) against its definition: the components of members, band and points below linked without
    the crease test (`image_clusters` at 180 deg, checked pair by pair above) that hold a point below."""
    from sgjax.perception.segment import DEEP, _continues_below, image_clusters, smooth_normals, within_tolerance

    rng = np.random.default_rng(11)
    h, w, span, threshold = 23, 31, 2, 0.004
    table_normal = np.array([1.0, 0.0, 0.0])  # most normals here face the camera: the band is not empty
    some, whole = 0, 0
    for trial in range(12):
        yy, xx = np.mgrid[:h, :w].astype(np.float32)
        depth = np.where(xx < w // 2, 1.0 + 0.01 * yy, 1.05 - 0.02 * xx / w) + rng.normal(0, 0.002, (h, w))
        image = np.stack([xx * 0.003, yy * 0.003, depth]).astype(np.float32)
        valid = rng.random((h, w)) < 0.95
        image[:, ~valid] = 0.0
        normals = smooth_normals(image, valid, np.zeros(3), 3, span)
        tolerance = np.full((h, w), 0.004, np.float32)
        kind = rng.random((h, w))
        member = valid & (kind < 0.55)
        level = np.where(member, 0.05, np.where(kind < 0.55 + 0.1 * (trial % 3), -0.03, 0.0))
        level[~valid] = 0.0
        creases: list = []
        components = image_clusters(image, member, normals, tolerance, 30.0, span, creases)
        got = _continues_below(valid, member, components, creases, level, normals, within_tolerance(image, tolerance),
                               threshold, table_normal)
        under = valid & (level <= -DEEP) & (level >= -0.05)
        band = valid & (level > -DEEP) & (level <= threshold) & (np.abs(np.einsum("khw,k->hw", normals, table_normal))
                                                                 < np.cos(np.deg2rad(45.0)))
        linked = image_clusters(image, member | band | under, normals, tolerance, 180.0, span)
        expected = member & np.isin(linked, linked[under]) if under.any() else np.zeros((h, w), bool)
        np.testing.assert_array_equal(got, expected)
        some += 0 < got.sum() < member.sum()
        whole += len(creases) > 0
    assert some >= 3 and whole >= 3  # members both ways, and creases the graph had to bridge


def test_fragments_join_the_neighbour_they_share_the_most_creases_with():
    """`merge_fragments` on a hand-made partition: a fragment joins the component it shares the most crease
    links with, a group of fragments still too small goes on with the links of its parts, large components
    and an unlinked fragment stay, and fragment_points 0 changes nothing."""
    from sgjax.perception.segment import merge_fragments

    # One row of pixels per component is enough: components are labels, creases flat index pairs.
    sizes = {1: 300, 2: 20, 3: 300, 4: 30, 5: 10}  # 2, 4, 5 are fragments below 200
    components = np.concatenate([np.full(n, k) for k, n in sizes.items()] + [np.full(7, -1)])[None]
    first_pixel = {k: int(np.flatnonzero(components[0] == k)[0]) for k in sizes}

    def links(x, y, n):
        return (np.full(n, first_pixel[x]), np.full(n, first_pixel[y]))

    # 2 shares 5 links with 1 and 2 with 3; 5 shares 3 with 2 only; 4 shares none with anyone.
    creases = [links(2, 1, 5), links(3, 2, 2), links(5, 2, 3)]
    got = merge_fragments(components, creases, 200)[0]
    assert set(np.unique(got[components[0] == 2])) == set(np.unique(got[components[0] == 1]))  # 2 -> 1
    assert set(np.unique(got[components[0] == 5])) == set(np.unique(got[components[0] == 1]))  # 5 -> 2 -> 1
    assert len(set(got[components[0] == 1]) | set(got[components[0] == 3]) | set(got[components[0] == 4])) == 3
    assert np.array_equal(got < 0, components[0] < 0)
    # 2 with more links to 3 than to 1 joins 3, and 5 with it.
    creases = [links(2, 1, 2), links(3, 2, 4), links(5, 2, 3), links(5, 1, 1)]
    got = merge_fragments(components, creases, 200)[0]
    assert got[first_pixel[2]] == got[first_pixel[3]] == got[first_pixel[5]] != got[first_pixel[1]]
    # 2 and 5 first join each other (their best links); as a group still too small, they then join the
    # component their links together favour: 3 (2 + 2 links), where 2 alone favoured 1 (3 against 2).
    creases = [links(2, 5, 10), links(2, 1, 3), links(2, 3, 2), links(5, 3, 2)]
    got = merge_fragments(components, creases, 200)[0]
    assert got[first_pixel[2]] == got[first_pixel[3]] == got[first_pixel[5]] != got[first_pixel[1]]
    # Large enough, the pair stays as it is after its first merge.
    got = merge_fragments(components, creases, 25)[0]
    assert got[first_pixel[2]] == got[first_pixel[5]] not in (got[first_pixel[1]], got[first_pixel[3]])
    np.testing.assert_array_equal(merge_fragments(components, creases, 0), components)


def test_specks_above_the_table_are_no_object_but_an_object_is():
    """Pixels above the table in blocks too sparse, or in a group of blocks holding fewer than min_points
    pixels in all, cannot form a kept cluster and are dropped before the box is chosen; an object's are kept."""
    from sgjax.perception.segment import _in_object_blocks

    rows, cols = np.mgrid[100:110, 200:210]  # an object: 100 pixels, 4 blocks
    obj = np.stack([rows.ravel(), cols.ravel()], 1)
    speck = np.array([[3, 3], [3, 5], [4, 4], [5, 3], [5, 5], [6, 6], [2, 2]])  # 7 pixels: one dense block
    group = np.concatenate([speck + [0, 8 * k] for k in range(3)])  # three such blocks side by side: 21 < 50
    sparse = np.array([[300, 600], [302, 602], [304, 604], [306, 606], [301, 605]])  # 5 pixels: a block < 50 / 8
    big = np.concatenate([speck + [400, 8 * k] for k in range(8)])  # eight dense blocks in a row: 56 >= 50
    pixels = np.concatenate([obj, group + [0, 400], sparse, big])
    kept, blocks = _in_object_blocks(pixels[:, 0], pixels[:, 1], (480, 640), 50)
    n = np.cumsum([len(obj), len(group), len(sparse), len(big)])
    assert kept[:n[0]].all() and not kept[n[0]:n[2]].any() and kept[n[2]:].all()
    # The same pixels one by one: the rule does not depend on what else is above the table elsewhere.
    for part in np.split(np.arange(len(pixels)), n[:-1]):
        assert np.array_equal(_in_object_blocks(pixels[part, 0], pixels[part, 1], (480, 640), 50)[0], kept[part])
    # The blocks it gives are those that hold the pixels it keeps.
    held = np.zeros_like(blocks)
    held[pixels[kept, 0] // 8, pixels[kept, 1] // 8] = True
    np.testing.assert_array_equal(blocks, held)


@pytest.mark.parametrize("n", [1, 2, 7, 300])
def test_the_lowest_node_of_each_set_matches_a_graphs_connected_components(n):
    """`_lowest_in_set` (pointer doubling over a graph of one edge per node) against scipy's connected
    components of the same undirected graph, relabelled by each set's lowest node."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    from sgjax.perception.segment import _lowest_in_set

    rng = np.random.default_rng(n)
    for _ in range(20):
        target = rng.integers(0, n, n)
        alone = rng.random(n) < 0.3
        target[alone] = np.flatnonzero(alone)  # nodes without an edge point at themselves
        _, sets = connected_components(coo_matrix((np.ones(n), (np.arange(n), target)), shape=(n, n)), directed=False)
        lowest = np.array([np.flatnonzero(sets == sets[i])[0] for i in range(n)])
        np.testing.assert_array_equal(_lowest_in_set(target), lowest)


def test_far_apart_groups_are_looked_at_in_boxes_of_their_own():
    """`_boxes`: each group of pixels above the table gets the box of its pixels and the margin around them;
    groups whose boxes would overlap share one; every pixel lies in exactly one box."""
    from sgjax.perception.segment import _boxes

    objects = np.stack(np.mgrid[200:260, 250:330].reshape(2, -1), 1)  # the objects near the image's middle
    stand = np.stack(np.mgrid[0:60, 600:640].reshape(2, -1), 1)  # a robot's stand in a corner
    near = np.stack(np.mgrid[262:270, 340:350].reshape(2, -1), 1)  # a piece within the objects' margin
    pixels = np.concatenate([objects, stand, near])
    def blocks(pixels):
        held = np.zeros((61, 81), bool)
        held[pixels[:, 0] // 8, pixels[:, 1] // 8] = True
        return held

    boxes = _boxes(pixels[:, 0], pixels[:, 1], blocks(pixels), (480, 640), 10)
    assert [(lo.tolist(), hi.tolist()) for lo, hi in boxes] == [([0, 590], [70, 640]), ([190, 240], [280, 360])]
    inside = [((pixels >= lo) & (pixels < hi)).all(1) for lo, hi in boxes]
    assert (np.sum(inside, 0) == 1).all()
    # One group alone: its bounding box and the margin, clipped to the image.
    [(lo, hi)] = _boxes(stand[:, 0], stand[:, 1], blocks(stand), (480, 640), 10)
    assert lo.tolist() == [0, 590] and hi.tolist() == [70, 640]


def test_segmentation_takes_the_heights_the_table_fit_left():
    """`segment_with_joined(..., height=)`: the fit's own heights give the labels the plane's heights give;
    heights of another length are refused, naming the problem."""
    from sgjax.perception.segment import segment_with_joined

    depth = render(tilted_camera())
    depth = np.where(np.isfinite(depth) & (depth < 2.0), depth, 0.0)
    points, pixels = back_project(depth, K)
    table = fit_table(points)
    args = (points, pixels, (K.height, K.width), table, np.zeros(3), 1.0 / K.fx)
    plain = segment_with_joined(*args)
    assert plain[0].max() >= 1  # the box (at least)
    given = segment_with_joined(*args, height=table.heights)
    np.testing.assert_array_equal(given[0], plain[0])
    np.testing.assert_array_equal(given[1], plain[1])
    with pytest.raises(ValueError, match="height must be"):
        segment_with_joined(*args, height=table.heights[:-1])


def test_parted_labels_cut_only_clusters_the_finer_test_cuts_into_sizeable_pieces():
    """Cluster 1 (two blobs 10 cm apart) is cut by the finer labels into pieces of 300 and 250 points and
    a speck of 20 beside the second: it becomes two objects, the speck joining the piece it lies next to.
    Cluster 2 is cut into 400 points and a 150-point sliver (under part_points): it stays whole. The
    table and everything else keep their labels."""
    from sgjax.perception.segment import OTHER, TABLE, parted_labels

    rng = np.random.default_rng(0)
    a, b = rng.normal(0, 0.01, (300, 3)), rng.normal(0, 0.01, (250, 3)) + [0.1, 0, 0]
    speck = rng.normal(0, 0.002, (20, 3)) + [0.12, 0, 0]
    c, sliver = rng.normal(0, 0.01, (400, 3)) + [0, 0.3, 0], rng.normal(0, 0.01, (150, 3)) + [0.05, 0.3, 0]
    table, other = rng.normal(0, 0.1, (500, 3)) - [0, 0, 0.2], rng.normal(0, 0.1, (30, 3)) + [0, 0, 0.6]
    points = np.concatenate([a, b, speck, c, sliver, table, other])
    labels = np.concatenate([np.full(570, 1), np.full(550, 2), np.full(500, TABLE), np.full(30, OTHER)]).astype(np.int32)
    # The finer test: cluster 1 in three pieces (ids 4, 7, 9), cluster 2 in two (5, 6); the speck's
    # points partly dropped (OTHER), as segment_finer drops pieces under min_points.
    finer = np.concatenate([np.full(300, 7), np.full(250, 4), np.r_[np.full(12, 9), np.full(8, OTHER)],
                            np.full(400, 5), np.full(150, 6), np.full(500, TABLE), np.full(30, OTHER)]).astype(np.int32)
    out = parted_labels(points, labels, finer, part_points=200)
    assert out.dtype == np.int32 and out.shape == labels.shape
    first, second = out[:300], out[300:570]
    assert len(np.unique(first)) == 1 and len(np.unique(second)) == 1 and first[0] != second[0]
    assert first[0] > 2 and second[0] > 2  # fresh ids, above every label of the first labelling
    np.testing.assert_array_equal(out[570:], labels[570:])  # cluster 2, the table and the rest as they were
    # A part_points above the second piece's size: nothing is cut.
    np.testing.assert_array_equal(parted_labels(points, labels, finer, part_points=260), labels)
