"""Objects without masks: the points above the table, segmented into instances.

Region growing on the image grid (as in Uckermann, Haschke & Ritter, IROS 2012, and PCL's
organised segmentation): two neighbouring pixels above the table belong to one object when their points
are within a distance tolerance of each other and no concave crease runs between the surfaces on either
side of them (LCCP's convexity test on smoothed normals, Stein et al., CVPR 2014): objects piled
against each other meet in a concave crease or a jump in depth. Clusters of fewer than `min_points`
points are dropped (noise, flying pixels). Only what stands on the table counts: points that, dropped
along the table's normal, fall outside the table's visible extent (the robot's stand, a wall, a shelf
beyond the edge) are background, as is a cluster whose surface goes on below the table (a stand right
beside it, its legs) and anything below the table. Touching objects without
a crease still merge and an object seen in two pieces (an occluder in front of it) splits:
docs/real-camera.md measures how often on simulated frames. A sensor's noise also makes creases where
there are none, on a small object's studs or rim, and cuts it into pieces; `segment_with_joined` also
gives a second, coarser hypothesis in which every cluster of fewer than `fragment_points` points that
creases alone part from others has joined the one it shares the most crease links with
(`merge_fragments`). It is a fallback: a planner that finds no grasp on the first labelling tries it
(`sgjax.grasping.plan_frame`, the benchmark's harness); as the only labelling it cost grasp success
(docs/experiments.md, 2026-12-06). `segment_finer` gives the third, finer one: the same growing with a
sharper crease test (`finer_concave_deg`), which cuts touching objects apart that meet in a shallow crease
(a pile left as one cluster, too large for any grasp) and cuts curved objects into more pieces; the
planner's last resort, when neither of the others gave a grasp (docs/experiments.md, 2026-12-07).
`parted_labels` takes from it only the clusters it cuts into two or more sizeable pieces (touching objects
merged into one, whose grasps would close on both) and leaves the rest as segmented: a planner's first
labelling (docs/experiments.md, 2026-12-07).
"""

from __future__ import annotations

import dataclasses
import itertools

import numpy as np

from sgjax.perception.table import TablePlane

TABLE = -1  # label of table points
DEEP = 0.015  # metres below the table: a surface reaching this deep goes on below the table
OTHER = -2  # label of everything else that is no object: below or beyond the table, too small, too high
NEIGHBOURS = ((0, 1), (1, 0))  # (rows, columns) to a pixel's right and its lower neighbour: the links tested


@dataclasses.dataclass(frozen=True)
class SegmentConfig:
    """tolerance: the largest step (metres) between neighbouring pixels of one object (grown with the
    sensor's noise and with grazing x the pixel's footprint, `link_tolerance`); concave_deg: a concave crease sharper than this between the
    surfaces on either side of two neighbours separates them (touching objects meet in one);
    normal_window, normal_span: the smoothing of the normals (pixels); fragment_points: in the joined
    hypothesis (`segment_with_joined`), a cluster of fewer points that only concave creases part from
    others joins the one it shares the most crease links with (0: the same as the first);
    finer_concave_deg: the crease angle of the finer hypothesis (`segment_finer`); part_points: the
    parted hypothesis (`parted_labels`) cuts a cluster that the finer one cuts into two or more pieces of
    at least this many points; min_points:
    smaller clusters are dropped (noise, flying pixels); min_height: points less than this above the
    table are table, unless the table's own noise is larger (then 3 sigma of it, estimated from the
    frame); max_height: points higher above the table are background."""

    tolerance: float = 0.004
    grazing: float = 6.0
    concave_deg: float = 30.0
    normal_window: int = 7
    normal_span: int = 3
    fragment_points: int = 200
    finer_concave_deg: float = 15.0
    part_points: int = 200
    min_points: int = 50
    min_height: float = 0.004
    max_height: float = 0.5

    def __post_init__(self):
        if not (self.tolerance > 0 and self.min_height >= 0 and self.max_height > self.min_height):
            raise ValueError(f"need tolerance > 0 and 0 <= min_height < max_height, got {self.tolerance}, "
                             f"{self.min_height}, {self.max_height}")
        if self.min_points < 1 or self.normal_window < 1 or self.normal_span < 1:
            raise ValueError(f"need min_points, normal_window and normal_span >= 1, got {self.min_points}, "
                             f"{self.normal_window} and {self.normal_span}")
        if self.part_points < 1:
            raise ValueError(f"need part_points >= 1, got {self.part_points}")
        if self.fragment_points < 0:
            raise ValueError(f"need fragment_points >= 0 (0: no joining), got {self.fragment_points}")
        if not (self.grazing > 0 and 0 < self.concave_deg <= 180):
            raise ValueError(f"need grazing > 0 and 0 < concave_deg <= 180, got {self.grazing} and {self.concave_deg}")
        if not 0 < self.finer_concave_deg <= self.concave_deg:
            raise ValueError(f"need 0 < finer_concave_deg <= concave_deg ({self.concave_deg}), got {self.finer_concave_deg}")


def table_noise(height: np.ndarray) -> float:
    """A robust standard deviation (1.4826 x the median absolute deviation) of the heights [N] of the
    points within 2 cm of the table: the sensor's noise on it (metres); 0 without such points."""
    height = height[:: max(1, len(height) // 20000)]  # 20k of a frame's heights pin the spread down
    near = height[np.abs(height) <= 0.02]
    if not len(near):
        return 0.0
    return float(1.4826 * np.median(np.abs(near - np.median(near))))


def height_threshold(noise: float, config: SegmentConfig = SegmentConfig()) -> float:
    """The height (metres) below which a point is table, for a sensor whose noise on the table is `noise`
    (metres, `table_noise`): max(min_height, 3 x noise)."""
    return max(config.min_height, 3.0 * noise)


def link_tolerance(distance: np.ndarray, pixel_angle: float, noise: float, config: SegmentConfig = SegmentConfig()
                   ) -> np.ndarray:
    """The largest step (metres) between neighbouring pixels of one surface, for pixels at `distance`
    [...] metres from the camera, pixel_angle (radians per pixel, 1 / f) and a sensor whose noise on the
    table is `noise` (metres): the largest of `tolerance`, 4 x noise (two noisy neighbours differ by
    sqrt(2) sigma on average) and `grazing` pixel footprints (a surface seen at a grazing angle, up to
    arccos(1 / grazing), must not fall apart into strips)."""
    return np.maximum(max(config.tolerance, 4.0 * noise), config.grazing * pixel_angle * distance)


def plane_basis(normal: np.ndarray) -> np.ndarray:
    """Two unit vectors [2, 3] spanning the plane of normal [3] (any orthonormal pair)."""
    n = np.asarray(normal, np.float64) / np.linalg.norm(normal)
    helper = np.eye(3)[int(np.argmin(np.abs(n)))]
    e1 = np.cross(n, helper)
    e1 /= np.linalg.norm(e1)
    return np.stack([e1, np.cross(n, e1)])


def table_extent(table_points: np.ndarray, normal: np.ndarray, cell: float = 0.005) -> np.ndarray:
    """The table's visible extent: the corners [C, 2] (counter-clockwise, in `plane_basis(normal)`
    coordinates) of the convex hull of the points at table height [T, 3] that form the table: on a
    grid of `cell` metres, the 8-connected pieces of at least a tenth of the largest one's cells (other
    surfaces that cross the table's height, a stand's side, make small pieces apart from it). Empty
    [0, 2] when they span no area."""
    from scipy.ndimage import label
    from scipy.spatial import ConvexHull, QhullError

    if len(table_points) < 3:
        return np.zeros((0, 2))
    # 50k of a frame's table points still mark every cell (a far 5 mm cell holds a few pixels).
    flat = table_points[:: max(1, len(table_points) // 50000)] @ plane_basis(normal).T
    # A column at a time: NumPy reduces over the long axis of an [N, 2] array some 30x slower.
    origin = np.array([flat[:, 0].min(), flat[:, 1].min()])
    cell_row, cell_col = (np.floor((flat[:, k] - origin[k]) / cell).astype(np.int64) for k in range(2))
    occupied = np.zeros((cell_row.max() + 1, cell_col.max() + 1), bool)
    occupied[cell_row, cell_col] = True
    pieces, _ = label(occupied, structure=np.ones((3, 3)))
    sizes = np.bincount(pieces.ravel())[1:]
    table = np.isin(pieces, np.flatnonzero(sizes >= 0.1 * sizes.max()) + 1)
    # The hull of the table's cells is the hull of each grid row's first and last one.
    rows = np.flatnonzero(table.any(1))
    first = np.argmax(table[rows], axis=1)
    last = table.shape[1] - 1 - np.argmax(table[rows, ::-1], axis=1)
    ends = np.concatenate([np.stack([rows, first], 1), np.stack([rows, last], 1)])
    corners = (ends + 0.5) * cell + origin
    try:
        return corners[ConvexHull(corners).vertices]  # counter-clockwise in 2-D
    except QhullError:  # the table's points on a line: no extent
        return np.zeros((0, 2))


def over_table(points: np.ndarray, corners: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """Which points [N, 3], dropped along normal [3], fall inside the table's extent (`table_extent`'s
    corners [C, 2]) -> bool [N]."""
    if len(corners) < 3 or not len(points):
        return np.zeros(len(points), bool)
    return in_convex_polygon(points @ plane_basis(normal).T, corners)


def in_convex_polygon(points: np.ndarray, corners: np.ndarray) -> np.ndarray:
    """Which 2-D points [N, 2] lie inside (or on) the convex polygon of corners [C, 2] (counter-clockwise,
    C >= 3) -> bool [N]. Points inside the polygon's inscribed circle about the corners' mean are in and
    points outside its bounding box out, without more ado (most of a frame's points, in a small share of
    the time); each other point is tested against the one edge facing it from that mean (its wedge, by a
    binary search on the angle about it): N log C, where a general point-in-polygon test costs N x C (a
    table's extent has tens of corners)."""
    centre = corners.mean(0)  # inside a convex polygon
    # A column at a time: NumPy is slow over narrow [N, 2] arrays.
    x, y = points[:, 0] - centre[0], points[:, 1] - centre[1]
    edges = np.roll(corners, -1, 0) - corners
    # The distance from the centre to the nearest edge's line, a thousandth short, so that no point
    # the edge test would put on the boundary counts as inside the circle.
    radius = 0.999 * np.min((edges[:, 0] * (centre[1] - corners[:, 1]) - edges[:, 1] * (centre[0] - corners[:, 0]))
                            / np.hypot(edges[:, 0], edges[:, 1]))
    inside = x * x + y * y < radius * radius
    low, high = corners.min(0) - centre, corners.max(0) - centre
    rest = np.flatnonzero(~inside & (x >= low[0]) & (x <= high[0]) & (y >= low[1]) & (y <= high[1]))
    angle = np.arctan2(corners[:, 1] - centre[1], corners[:, 0] - centre[0])
    start = int(np.argmin(angle))  # counter-clockwise from the smallest angle: increasing angles
    corners, angle = np.roll(corners, -start, 0), np.roll(angle, -start)
    px, py = points[rest, 0], points[rest, 1]
    wedge = np.searchsorted(angle, np.arctan2(py - centre[1], px - centre[0]), side="right") - 1
    a, b = corners[wedge], corners[(wedge + 1) % len(corners)]  # wedge -1: between the last corner and the first
    inside[rest] = (b[:, 0] - a[:, 0]) * (py - a[:, 1]) - (b[:, 1] - a[:, 1]) * (px - a[:, 0]) >= 0
    return inside


def point_image(points: np.ndarray, index: np.ndarray, image_size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """points [N, 3] at flat pixel indices [N] (row x W + column) as a channel-first image [3, H, W]
    (x, y, z planes) and its validity bool [H, W]."""
    # float32: a tenth of a micrometre, and half the memory traffic; channel-first, so that each
    # coordinate is one contiguous [H, W] plane (NumPy is several times slower over a strided one).
    image = np.zeros((3, *image_size), np.float32)
    valid = np.zeros(image_size, bool)
    for k in range(3):
        image[k].reshape(-1)[index] = points[:, k]
    valid.reshape(-1)[index] = True
    return image, valid


def smooth_normals(image: np.ndarray, valid: np.ndarray, viewpoint, window: int, span: int) -> np.ndarray:
    """Unit surface normals [3, H, W] (channel-first) of a point image [3, H, W] whose invalid pixels
    hold 0, as `point_image` leaves them (its valid [H, W] pixels averaged over window x window,
    tangents over +-span pixels): sensor noise on one pixel tilts a normal by tens of degrees, these by
    a few. Each normal points out of its surface, towards viewpoint [3] (the camera)."""
    from scipy.ndimage import uniform_filter

    weight = uniform_filter(valid.astype(np.float32), window)
    inverse = 1.0 / np.maximum(weight, 1e-9)
    # Channel by channel (x, y, z as contiguous [H, W] planes): the mean point, its tangents along rows
    # and columns, their cross product.
    # (An invalid pixel's point is 0, as `point_image` leaves it: it adds nothing to the sums.)
    mean = [uniform_filter(image[k], window) * inverse for k in range(3)]
    du = [np.zeros_like(inverse) for _ in range(3)]
    dv = [np.zeros_like(inverse) for _ in range(3)]
    for k in range(3):
        np.subtract(mean[k][:, 2 * span:], mean[k][:, :-2 * span], out=du[k][:, span:-span])
        np.subtract(mean[k][2 * span:], mean[k][:-2 * span], out=dv[k][span:-span])
    n = [du[1] * dv[2] - du[2] * dv[1], du[2] * dv[0] - du[0] * dv[2], du[0] * dv[1] - du[1] * dv[0]]
    view = np.asarray(viewpoint, np.float32)
    towards = sum(n[k] * (view[k] - image[k]) for k in range(3))
    length = np.sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2])
    scale = np.where(towards < 0, np.float32(-1), np.float32(1)) / np.maximum(length, 1e-12)
    return np.stack([n[k] * scale for k in range(3)])


def _dot(a, b) -> np.ndarray:
    """The dot products [...] of two channel-first arrays [3, ...] (or a vector [3]) over their first axis
    (a sum of three products: faster than np.sum or np.einsum over an axis of 3)."""
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def within_tolerance(image: np.ndarray, tolerance: np.ndarray) -> list[np.ndarray]:
    """Whether each pixel of a point image [3, H, W] and its right, then its lower neighbour lie within the
    first one's `tolerance` [H, W] of each other -> [bool [H, W - 1], bool [H - 1, W]] (the neighbour pairs
    in the order of `NEIGHBOURS`)."""
    h, w = tolerance.shape
    close = []
    for dr, dc in NEIGHBOURS:
        first, second = np.s_[:h - dr, :w - dc], np.s_[dr:, dc:]
        # Dense over the box, a plane at a time: cheaper than gathering the members' points.
        step = [image[k][first] - image[k][second] for k in range(3)]
        close.append(_dot(step, step) <= tolerance[first] ** 2)
    return close


def image_clusters(image: np.ndarray, member: np.ndarray, normals: np.ndarray, tolerance: np.ndarray,
                   concave_deg: float, span: int, creases: list | None = None, close: list | None = None) -> np.ndarray:
    """Connected components [H, W] (int, -1 off `member`) of the member pixels of a point image [3, H, W]
    with normals [3, H, W] (channel-first, as `point_image` and `smooth_normals` give them), where two
    4-neighbours are joined when they lie within the first one's `tolerance` [H, W] of each other and no concave
    crease runs between the surfaces on their two sides (the normals `span` pixels before the first and
    after the second; LCCP's test: (n_a - n_b) . (p_a - p_b) < 0, and the normals more than concave_deg
    apart). creases: a list that receives the pairs a crease parted, as (first, second) flat pixel
    indices int [L] each (`merge_fragments`, `_continues_below`). close: `within_tolerance(image, tolerance)`
    when the caller has it already."""
    from scipy.ndimage import label

    h, w = member.shape
    flat_image, flat_normals = image.reshape(3, -1), normals.reshape(3, -1)
    cos_concave = np.cos(np.deg2rad(concave_deg))
    # The components are labelled on a grid of twice the resolution: pixels at even (row, column), the
    # link between two neighbours on the cell between them (scipy's `label`, 4-connected: some 2x
    # faster than a sparse graph's connected components).
    grid = np.zeros((2 * h - 1, 2 * w - 1), bool)
    grid[::2, ::2] = member
    if close is None:
        close = within_tolerance(image, tolerance)
    for (dr, dc), near in zip(NEIGHBOURS, close):
        first, second = np.s_[:h - dr, :w - dc], np.s_[dr:, dc:]
        linked = member[first] & member[second] & near
        r, c = np.nonzero(linked)
        if cos_concave > -1.0:  # at 180 deg no crease separates (cos < -1 never holds): skip the normals
            a = np.clip(r - dr * span, 0, h - 1) * w + np.clip(c - dc * span, 0, w - 1)
            b = np.clip(r + dr * (span + 1), 0, h - 1) * w + np.clip(c + dc * (span + 1), 0, w - 1)
            na, nb = flat_normals[:, a], flat_normals[:, b]
            # The convexity test only for the pairs whose normals are more than concave_deg apart.
            bent = np.flatnonzero(_dot(na, nb) < cos_concave)
            concave = np.zeros(len(r), bool)
            concave[bent] = _dot(na[:, bent] - nb[:, bent], flat_image[:, a[bent]] - flat_image[:, b[bent]]) < 0
            if creases is not None:
                creases.append((r[concave] * w + c[concave], (r[concave] + dr) * w + c[concave] + dc))
            r, c = r[~concave], c[~concave]
        grid[2 * r + dr, 2 * c + dc] = True
    components, _ = label(grid)
    return np.where(member, components[::2, ::2], -1)


def merge_fragments(components: np.ndarray, creases: list, min_points: int) -> np.ndarray:
    """`image_clusters`' components [H, W] (-1 off the members) with their fragments merged: in rounds,
    every component of fewer than `min_points` pixels joins the one it shares the most crease links with
    (`creases`: image_clusters' (first, second) flat pixel index pairs; ties to the lower label), until
    no such component shares a crease with another. A merged group's links are those of its parts, so a
    group of fragments still too small goes on as one. -> int [H, W], -1 off the members. On a small
    object a sensor's noise makes spurious creases (studs, rims, handles) that cut it into pieces; two
    objects touching in a pile meet in a crease as well, but each is rarely that small."""
    if min_points <= 0 or not creases:
        return components
    flat = components.reshape(-1)
    first = flat[np.concatenate([pair[0] for pair in creases])]
    second = flat[np.concatenate([pair[1] for pair in creases])]
    n = int(flat.max()) + 1
    group = np.arange(n)  # each component's group so far
    pixels = np.bincount(flat[flat >= 0], minlength=n)  # per component
    size = pixels  # per group
    # Each round leaves fewer groups; a few settle a frame, the bound only caps a pathological one.
    for _ in range(32):
        a, b = group[first], group[second]
        apart = (a != b) & (first >= 0) & (second >= 0)
        small = size[group] < min_points  # per component: its group is too small
        # Both directions of each link whose source group is small: (source, target) as one integer.
        code = np.concatenate([a[apart & small[first]] * n + b[apart & small[first]],
                               b[apart & small[second]] * n + a[apart & small[second]]])
        if not len(code):
            break
        pairs, count = np.unique(code, return_counts=True)
        source = pairs // n
        target = pairs - source * n
        # Per source the target with the most links (ties: the lower label): sorted by source, then count
        # descending, then target; the first row of each source.
        order = np.lexsort((target, -count, source))
        source, target = source[order], target[order]
        best = np.flatnonzero(np.r_[True, source[1:] != source[:-1]])
        target_of = np.arange(n)
        target_of[source[best]] = target[best]
        # Relabel by each merged set's lowest group id, so labels stay those of image_clusters' components.
        group = _lowest_in_set(target_of)[group]
        size = np.bincount(group, weights=pixels, minlength=n)
    return np.where(components >= 0, group[np.maximum(components, 0)], -1)


def _lowest_in_set(target: np.ndarray) -> np.ndarray:
    """For a graph in which each node i [n] has one edge, to target[i] (itself: none), the lowest node of
    each node's connected set -> int [n]. Each such set holds one cycle (a node pointing at itself is
    one): by pointer doubling every node finds a node of its cycle and that cycle's lowest node (NumPy
    over [n] arrays, log n rounds; a sparse graph's connected components cost some 30x as much here)."""
    n = len(target)
    step, lowest = target.copy(), np.minimum(np.arange(n), target)
    # After k rounds step[i] is 2^k edges on from i and lowest[i] the lowest node on those 2^k + 1.
    for _ in range(max(1, int(n).bit_length())):
        lowest = np.minimum(lowest, lowest[step])
        step = step[step]
    # step[i] now lies on i's cycle (n edges on), and lowest there covers the whole cycle: one number per set.
    cycle = lowest[step]
    result = np.full(n, n)
    np.minimum.at(result, cycle, np.arange(n))
    return result[cycle]


def segment_objects(points: np.ndarray, pixels: np.ndarray, image_size: tuple[int, int], table: TablePlane,
                    viewpoint, pixel_angle: float, config: SegmentConfig = SegmentConfig()) -> np.ndarray:
    """Instance labels of a frame's points [N, 3] at pixels [N, 2] (row, column; in row-major order, as
    `back_project` gives them) of an image of image_size (H, W), seen from viewpoint [3] with
    pixel_angle radians per pixel (1 / f), over its table -> int32 [N]: objects 1..K (the largest
    first), TABLE (-1) for the table, OTHER (-2) for the rest (module doc)."""
    return _segment(points, pixels, image_size, table, viewpoint, pixel_angle, config, False)[0]


def segment_with_joined(points: np.ndarray, pixels: np.ndarray, image_size: tuple[int, int], table: TablePlane,
                        viewpoint, pixel_angle: float, config: SegmentConfig = SegmentConfig(), *,
                        height: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """`segment_objects`' labels int32 [N] and the joined hypothesis' int32 [N] (module doc: the
    crease-cut fragments joined, `merge_fragments` with config.fragment_points), numbered the same way,
    from one pass. height: the points' heights above the table [N] when the caller has them
    (`table.height(points)`; `fit_table` leaves them in `TablePlane.heights` for the points it fitted)."""
    return _segment(points, pixels, image_size, table, viewpoint, pixel_angle, config, True, height)


def segment_finer(points: np.ndarray, pixels: np.ndarray, image_size: tuple[int, int], table: TablePlane,
                  viewpoint, pixel_angle: float, config: SegmentConfig = SegmentConfig(), *,
                  height: np.ndarray | None = None) -> np.ndarray:
    """The finer hypothesis' labels int32 [N] (module doc): `segment_objects` with concave creases of
    config.finer_concave_deg parting neighbours. height: as `segment_with_joined`'s."""
    finer = dataclasses.replace(config, concave_deg=config.finer_concave_deg)
    return _segment(points, pixels, image_size, table, viewpoint, pixel_angle, finer, False, height)[0]


def parted_labels(points: np.ndarray, labels: np.ndarray, finer: np.ndarray, part_points: int) -> np.ndarray:
    """The parted hypothesis' labels int32 [N] (module doc): each cluster of `labels` [N] that the finer
    hypothesis' labels `finer` [N] cut into two or more pieces of at least `part_points` points is replaced
    by those pieces (fresh ids above the largest label), its other points (smaller pieces, points the
    finer test dropped) joining the piece of their nearest point among points [N, 3]; every other
    label as it was. So the same points are objects as in `labels`, and a cluster is cut only where the
    finer test finds two sizeable objects in it."""
    from scipy.spatial import cKDTree

    labels = np.asarray(labels, np.int32)
    out = labels.copy()
    fresh = int(labels.max(initial=0)) + 1
    for cluster in np.unique(labels[labels > 0]):
        rows = np.flatnonzero(labels == cluster)
        ids, counts = np.unique(finer[rows], return_counts=True)
        pieces = ids[(ids > 0) & (counts >= part_points)]
        if len(pieces) < 2:
            continue
        in_piece = np.isin(finer[rows], pieces)
        # Each piece a fresh id; the rest of the cluster to the piece of its nearest point.
        ids_of = np.searchsorted(pieces, finer[rows[in_piece]]) + fresh
        _, nearest = cKDTree(points[rows[in_piece]]).query(points[rows[~in_piece]])
        out[rows[in_piece]] = ids_of
        out[rows[~in_piece]] = ids_of[nearest]
        fresh += len(pieces)
    return out


def _segment(points, pixels, image_size, table: TablePlane, viewpoint, pixel_angle: float, config: SegmentConfig,
             joined: bool, height: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray | None]:
    points = np.asarray(points, np.float64)
    if len(pixels) > 1 and np.any(pixels[1:, 0] < pixels[:-1, 0]):
        raise ValueError("segment_objects: the pixels must come in row-major order (as back_project gives them)")
    if height is None:
        height = table.height(points)
    elif np.shape(height) != (len(points),):
        raise ValueError(f"height must be [N] for the {len(points)} points, got shape {np.shape(height)}")
    noise = table_noise(height)
    threshold = height_threshold(noise, config)
    labels = np.full(len(points), OTHER, np.int32)
    on_plane = np.abs(height) <= threshold
    labels[on_plane] = TABLE
    above = (height > threshold) & (height <= config.max_height)
    row, col = pixels[:, 0], pixels[:, 1]  # a column at a time: NumPy is slow over narrow [N, 2] arrays
    # Only what stands over the table's visible extent (not a wall, a stand or a shelf beyond its edge), in
    # blocks dense enough to be an object's (`_in_object_blocks`). (As indices: each step gathers a few of
    # the frame's points, not a mask over all of them.)
    above = np.flatnonzero(above)
    table_rows = np.flatnonzero(on_plane)
    table_rows = table_rows[:: max(1, len(table_rows) // 50000)]  # what table_extent keeps, gathered alone
    above = above[over_table(points[above], table_extent(points[table_rows], table.normal), table.normal)]
    kept, blocks = _in_object_blocks(row[above], col[above], image_size, config.min_points)
    above = above[kept]
    if not len(above):
        return labels, labels.copy() if joined else None
    # Only boxes of image rows and columns around the points above the table are looked at: one per group
    # of them far enough apart (the objects, a robot's stand at the image's edge), not one spanning both.
    component = np.empty(len(above), np.int64)  # per point above the table, numbered across the boxes
    merged = np.empty(len(above), np.int64) if joined else None
    below = np.empty(len(above), bool)
    count = 0
    for lo, hi in _boxes(row[above], col[above], blocks, image_size, config.normal_window + config.normal_span):
        # Points come in row-major pixel order (`back_project`), so a box's rows are one slice of them.
        rows = slice(*np.searchsorted(row, (lo[0], hi[0])))
        box = np.flatnonzero((col[rows] >= lo[1]) & (col[rows] < hi[1])) + rows.start
        inside = slice(*np.searchsorted(above, (rows.start, rows.stop)))
        inside = np.flatnonzero((col[above[inside]] >= lo[1]) & (col[above[inside]] < hi[1])) + inside.start
        member = np.zeros(len(box), bool)
        member[np.searchsorted(box, above[inside])] = True
        parts = _box_clusters(points[box], height[box], row[box] - lo[0], col[box] - lo[1], member,
                              (int(hi[0] - lo[0]), int(hi[1] - lo[1])), noise, threshold, table, viewpoint,
                              pixel_angle, config, joined)
        component[inside], below[inside] = parts[0] + count, parts[1]
        if joined:
            merged[inside] = parts[2] + count
        count += parts[3]
    first = labels.copy()
    first[above] = _numbered(component, below, config.min_points)
    if not joined:
        return first, None
    second = labels.copy()
    second[above] = _numbered(merged, below, config.min_points)
    return first, second


def _boxes(row: np.ndarray, col: np.ndarray, blocks: np.ndarray, image_size: tuple[int, int], margin: int) -> list:
    """The boxes [(lo (row, column), hi (row, column) exclusive)] that hold the pixels at (row [M], col [M])
    with `margin` pixels around each (clipped to the image): the bounding boxes of the groups of the 8x8-pixel
    blocks that hold them (bool [H / 8 + 1, W / 8 + 1], `_in_object_blocks`) whose margins overlap, boxes
    that overlap joined into one, in row-major order of their corners."""
    from scipy.ndimage import label, maximum_filter

    # Blocks grown by the margin (in blocks) and 8-connected: groups whose margins touch are one.
    near, count = label(maximum_filter(blocks, size=2 * -(-margin // 8) + 1), structure=np.ones((3, 3)))
    if count == 1:  # the common case: the objects alone
        lo = np.maximum([row.min() - margin, col.min() - margin], 0)
        return [(lo, np.minimum([row.max() + margin + 1, col.max() + margin + 1], image_size))]
    which = near[row >> 3, col >> 3]
    order = np.argsort(which, kind="stable")
    boxes = []
    for part in np.split(order, np.flatnonzero(np.diff(which[order])) + 1):
        lo = np.maximum([row[part].min() - margin, col[part].min() - margin], 0)
        hi = np.minimum([row[part].max() + margin + 1, col[part].max() + margin + 1], image_size)
        boxes.append((lo, hi))
    # Boxes of groups that lie apart may still overlap (an L-shaped group's box over another): join such a
    # pair, until none overlaps.
    while overlapping := next(((i, j) for i, j in itertools.combinations(range(len(boxes)), 2)
                               if (boxes[i][0] < boxes[j][1]).all() and (boxes[j][0] < boxes[i][1]).all()), None):
        i, j = overlapping
        boxes[i] = (np.minimum(boxes[i][0], boxes[j][0]), np.maximum(boxes[i][1], boxes[j][1]))
        del boxes[j]
    return sorted(boxes, key=lambda box: tuple(box[0]))


def _box_clusters(points: np.ndarray, height: np.ndarray, row: np.ndarray, col: np.ndarray, above: np.ndarray,
                  size: tuple[int, int], noise: float, threshold: float, table: TablePlane, viewpoint,
                  pixel_angle: float, config: SegmentConfig, joined: bool) -> tuple:
    """One box of `_segment`: its points [n, 3], heights [n] and (row, column) [n] in the box, which of them
    are above the table [n] -> (their components [m], whether each goes on below the table [m], the joined
    hypothesis' components [m] or None, the number of component labels used), for the m points above."""
    # Flat indices in the box: cheaper to gather and scatter with than (row, column) pairs.
    box_index = row * size[1] + col
    above_index = box_index[above]
    image, valid = point_image(points, box_index, size)
    member = np.zeros(size, bool)
    member.reshape(-1)[above_index] = True
    normals = smooth_normals(image, valid, viewpoint, config.normal_window, config.normal_span)
    ray = [image[k] - np.float32(viewpoint[k]) for k in range(3)]
    tolerance = link_tolerance(np.sqrt(_dot(ray, ray)), pixel_angle, noise, config).astype(np.float32)
    creases: list = []  # `_continues_below` and the joined hypothesis need them
    close = within_tolerance(image, tolerance)  # both linkings test the same neighbour pairs
    components = image_clusters(image, member, normals, tolerance, config.concave_deg, config.normal_span, creases,
                                close)
    level = np.zeros(member.shape)
    level.reshape(-1)[box_index] = height
    below = _continues_below(valid, member, components, creases, level, normals, close, threshold, table.normal)
    used = int(components.max()) + 1
    merged = merge_fragments(components, creases, config.fragment_points).reshape(-1)[above_index] if joined else None
    return components.reshape(-1)[above_index], below.reshape(-1)[above_index], merged, used


def _in_object_blocks(row: np.ndarray, col: np.ndarray, image_size: tuple[int, int], min_points: int
                      ) -> tuple[np.ndarray, np.ndarray]:
    """Which of the pixels above the table at (row [M], col [M]) may belong to an object -> (bool [M], the
    8x8-pixel blocks that hold them, bool [H / 8 + 1, W / 8 + 1]): those in blocks holding at least
    min_points / 8 of them, in a group of such blocks (8-connected) that holds at least min_points. Lone
    pixels (the noise's tail) are no object, and no cluster of min_points pixels spans two groups, so a
    smaller group would only give clusters that are dropped; without them the boxes `_segment` looks at are
    the objects', not the frame's (a stereo camera's noise on a far table scatters such specks over the
    whole image)."""
    from scipy.ndimage import label

    shape = (image_size[0] // 8 + 1, image_size[1] // 8 + 1)
    block = (row >> 3) * shape[1] + (col >> 3)  # (a shift: cheaper than NumPy's division)
    count = np.bincount(block, minlength=shape[0] * shape[1])
    dense = count >= max(1, min_points // 8)
    groups, _ = label(dense.reshape(shape), structure=np.ones((3, 3)))
    groups = groups.reshape(-1)
    total = np.bincount(groups, weights=np.where(dense, count, 0))
    total[0] = 0  # the blocks in no group
    kept = total[groups] >= min_points
    return kept[block], kept.reshape(shape)


def _numbered(components: np.ndarray, below: np.ndarray, min_points: int) -> np.ndarray:
    """Object labels int32 [M] of the points above the table from their components [M] (int, in the
    points' row-major order): 1..K for the clusters of at least min_points points none of which goes on
    below the table (`below` bool [M]), the largest first (ties by the first point, so the numbering is
    deterministic), OTHER for the rest."""
    _, first, cluster = np.unique(components, return_index=True, return_inverse=True)
    cluster = cluster.reshape(-1)
    sizes = np.bincount(cluster)
    grounded = np.bincount(cluster, weights=below, minlength=len(sizes)) == 0
    kept = np.flatnonzero((sizes >= min_points) & grounded)
    order = kept[np.lexsort((first[kept], -sizes[kept]))]
    new_id = np.full(len(sizes), OTHER, np.int32)
    new_id[order] = np.arange(1, len(order) + 1, dtype=np.int32)
    return new_id[cluster]


def _continues_below(valid, member, components, creases, level, normals, close, threshold, normal) -> np.ndarray:
    """Which member pixels [h, w] belong to a surface that goes on below the table (a robot's stand, a
    table leg, the table's own edge): linked (as in `image_clusters`, creases aside) through the points
    at table height that are not the table's top (normals more than 45 deg off its normal) to points
    1.5-5 cm below it (deeper than any sensor's noise on the table). Nothing standing on the table does
    that. components [h, w], creases: `image_clusters`' of the members; level [h, w]: heights above the
    table; close: `within_tolerance` of the point image."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    under = valid & (level <= -DEEP) & (level >= -0.05)
    if not under.any():
        return np.zeros(member.shape, bool)
    band = valid & (level > -DEEP) & (level <= threshold) & (np.abs(_dot(normals, np.asarray(normal, np.float32))) < np.cos(np.deg2rad(45.0)))
    # The members' links are known: their components and the pairs a crease parted. Only the links that
    # reach the band or the points below are tested here, and the components are joined over a graph
    # of the members' components and those pixels (labelling the whole box once more costs several
    # times as much).
    other = band | under  # no member is at table height or below
    h, w = member.shape
    flat = components.reshape(-1)
    n_components = int(flat.max()) + 1
    others = np.flatnonzero(other.reshape(-1))
    node = np.where(member.reshape(-1), flat, -1)
    node[others] = n_components + np.arange(len(others))
    reach = member | other
    first_nodes, second_nodes = [], []
    for (dr, dc), near in zip(NEIGHBOURS, close):
        first, second = np.s_[:h - dr, :w - dc], np.s_[dr:, dc:]
        linked = reach[first] & reach[second] & (other[first] | other[second]) & near
        r, c = np.nonzero(linked)
        first_nodes.append(node[r * w + c])
        second_nodes.append(node[(r + dr) * w + c + dc])
    for a, b in creases:
        first_nodes.append(flat[a])
        second_nodes.append(flat[b])
    first_nodes, second_nodes = np.concatenate(first_nodes), np.concatenate(second_nodes)
    n = n_components + len(others)
    graph = coo_matrix((np.ones(len(first_nodes)), (first_nodes, second_nodes)), shape=(n, n))
    _, group = connected_components(graph, directed=False)
    reaches_below = np.zeros(n, bool)
    reaches_below[group[node[np.flatnonzero(under.reshape(-1))]]] = True
    return member & reaches_below[group[np.maximum(components, 0)]]
