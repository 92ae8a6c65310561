"""One real frame, ready for the planner: points, per-point object labels, the table, the camera.

    frame = Frame.from_depth("depth.png", "intrinsics.json", depth_scale=1000)          # camera frame
    frame = Frame.from_depth(depth_m, K, extrinsics=T, masks=ids, workspace=roi)        # world frame
    frame.points, frame.labels, frame.table.plane, frame.camera_position, frame.object_ids

Labels: objects 1..K (from `masks`, their instance ids, or from clustering the points above the table,
`sgjax.perception.segment`), TABLE (-1) for the table, OTHER (-2) for the rest. Frame: without extrinsics
everything is in the camera's (OpenCV: x right, y down, z forward) and the table's normal is "up"; with
a camera-to-world `extrinsics` everything is in the world's and the table is looked for within 30 degrees
of world +z. Errors are `PerceptionError` (a ValueError) with one line naming the problem.
"""

from __future__ import annotations

import dataclasses
import functools
import os
from collections.abc import Iterator

import numpy as np

from sgjax.perception.camera import (Intrinsics, existing_file, read_extrinsics, read_intrinsics, rigid_extrinsics,
                                     to_world)
from sgjax.perception.depth import back_project, read_depth
from sgjax.perception.segment import (OTHER, TABLE, SegmentConfig, height_threshold, parted_labels, plane_basis,
                                      segment_finer, segment_with_joined, table_noise)
from sgjax.perception.table import TablePlane, fit_table
from sgjax.utils.threads import one_blas_thread

MIN_TABLE_SHARE = 0.05  # a plane holding fewer of the frame's points is not taken for the table
PLAUSIBLE_DEPTH = (0.1, 10.0)  # metres: a median depth outside this looks like a wrong depth_scale
WORLD_TABLE_TILT_DEG = 30.0


class PerceptionError(ValueError):
    """A frame that cannot be used: the message names the problem in one line."""


@dataclasses.dataclass(frozen=True, eq=False)
class Frame:
    """A depth frame's scene: points [N, 3] (metres, `frame` coordinates), labels int32 [N] (module
    doc), pixels int [N, 2] (row, column of each point), table (its plane in the same frame, normal
    towards the camera), camera_position [3], intrinsics, extrinsics [4, 4] camera-to-world or None,
    image_size (height, width), segmentation "masks" | "clusters"; joined_labels int32 [N]: with
    clusters, the coarser hypothesis in which crease-cut fragments have joined their neighbour
    (`sgjax.perception.segment.segment_with_joined`; a planner that finds no grasp tries it), else None;
    segment: the segmentation's settings (`finer` segments with them again)."""

    points: np.ndarray
    labels: np.ndarray
    pixels: np.ndarray
    table: TablePlane
    camera_position: np.ndarray
    intrinsics: Intrinsics
    extrinsics: np.ndarray | None
    image_size: tuple[int, int]
    segmentation: str
    joined_labels: np.ndarray | None = None
    segment: SegmentConfig = SegmentConfig()

    @property
    def frame(self) -> str:
        """"world" with extrinsics, else "camera"."""
        return "camera" if self.extrinsics is None else "world"

    @property
    def object_ids(self) -> list[int]:
        """The objects' labels, ascending."""
        return [int(i) for i in np.unique(self.labels[self.labels > 0])]

    def object_points(self, object_id: int) -> np.ndarray:
        """[n, 3] the points of object `object_id`."""
        return self.points[self.labels == object_id]

    @property
    def planned(self) -> np.ndarray:
        """bool [N]: the points a planner is handed (`table_and_objects`), those of the table and the objects."""
        return self.labels != OTHER

    def table_and_objects(self) -> tuple[np.ndarray, np.ndarray]:
        """What a planner is handed: the points [M, 3] of the table and the objects and their labels [M]
        (TABLE, 1..K); the rest (noise above the table, anything below or beyond it) would be taken for
        obstacles. The joined hypothesis': `frame.joined().table_and_objects()`."""
        keep = self.planned
        return self.points[keep], self.labels[keep]

    def joined(self) -> Frame:
        """This frame with the joined hypothesis as its labels (segmentation "joined clusters"; ValueError
        when there is none)."""
        if self.joined_labels is None:
            raise ValueError("this frame has no joined hypothesis (its objects come from masks)")
        return dataclasses.replace(self, labels=self.joined_labels, joined_labels=None, segmentation="joined clusters")

    @property
    def has_joined(self) -> bool:
        """Whether the joined hypothesis differs from the labels (else planning on it changes nothing)."""
        return self.joined_labels is not None and not np.array_equal(self.joined_labels, self.labels)

    def finer(self) -> Frame:
        """This clustered frame segmented again with the finer crease test (`segment.segment_finer`: a pile
        left as one cluster cut into its objects), segmentation "finer clusters", no joined hypothesis;
        ValueError for a frame whose objects come from masks."""
        return dataclasses.replace(self, labels=self._finer_labels, joined_labels=None, segmentation="finer clusters")

    def parted(self) -> Frame:
        """This clustered frame with each cluster that the finer hypothesis cuts into two or more sizeable
        pieces replaced by them (`segment.parted_labels`: touching objects merged into one cut apart),
        segmentation "parted clusters", no joined hypothesis; ValueError for a frame whose objects come
        from masks."""
        return dataclasses.replace(self, labels=self._parted_labels, joined_labels=None, segmentation="parted clusters")

    @functools.cached_property
    def _parted_labels(self) -> np.ndarray:
        # Once per frame: the harness asks for the hypotheses again when the first plan gives no grasp.
        return parted_labels(self.points, self.labels, self._finer_labels, self.segment.part_points)

    @functools.cached_property
    def _finer_labels(self) -> np.ndarray:
        # Once per frame: both `finer` and `parted` need it (cached_property writes past the frozen dataclass).
        if self.segmentation != "clusters":
            raise ValueError(f"only a clustered frame has a finer hypothesis (this one's objects: {self.segmentation})")
        heights = self.table.heights  # the fit's, of these points (None: computed again)
        with one_blas_thread():
            return segment_finer(self.points, self.pixels, self.image_size, self.table, self.camera_position,
                                 _pixel_angle(self.intrinsics), self.segment,
                                 height=heights if heights is not None and len(heights) == len(self.points) else None)

    def hypotheses(self) -> Iterator[Frame]:
        """The labellings a planner tries in turn until one gives a grasp, as frames (a generator: each is
        made only when asked for), each only when its labels differ from all before it: with clusters, the
        parted one (`parted`), this frame, its joined hypothesis (`joined`), the finer one (`finer`); with
        masks, this frame alone."""
        if self.segmentation != "clusters":
            yield self
            return
        parted = self.parted()
        tried = [self.labels]
        if not np.array_equal(parted.labels, self.labels):
            tried.append(parted.labels)
            yield parted
        yield self
        for make in ([self.joined] if self.joined_labels is not None else []) + [self.finer]:
            frame = make()
            if not any(np.array_equal(frame.labels, labels) for labels in tried):
                tried.append(frame.labels)
                yield frame

    def label_image(self) -> np.ndarray:
        """[H, W] int32 the label of each pixel; OTHER where the frame has no point."""
        image = np.full(self.image_size, OTHER, np.int32)
        image[self.pixels[:, 0], self.pixels[:, 1]] = self.labels
        return image

    def table_frame(self) -> np.ndarray:
        """[4, 4] the table's frame in this frame's coordinates: z the table's normal (up, towards the
        camera), x the camera's right (its x axis) laid into the table, the origin the camera's foot on
        the table. A planner that expects z up plans in it (`sgjax.grasping.plan_frame`)."""
        n = self.table.normal
        right = np.eye(3)[0] if self.extrinsics is None else self.extrinsics[:3, 0]
        x = right - (right @ n) * n
        if np.linalg.norm(x) < 1e-6:  # the camera's x along the normal: any direction in the plane
            x = plane_basis(n)[0]
        x /= np.linalg.norm(x)
        pose = np.eye(4)
        pose[:3, :3] = np.stack([x, np.cross(n, x), n], axis=1)
        pose[:3, 3] = self.camera_position - self.table.height(self.camera_position[None])[0] * n
        return pose

    @classmethod
    def from_depth(cls, depth, intrinsics, depth_scale: float = 1000.0, extrinsics=None, masks=None,
                   workspace=None, segment: SegmentConfig = SegmentConfig(), seed: int = 0) -> Frame:
        """A frame from a depth image and its calibration.

        depth: a file (16-bit PNG in 1/depth_scale metres, .npy/.npz in metres; `read_depth`) or an
        array [H, W] (float: metres; integer: units of 1/depth_scale metres); 0, NaN: no depth.
        intrinsics: an `Intrinsics`, a 3x3 matrix or a file (`read_intrinsics`). extrinsics: None, a
        camera-to-world [4, 4] or a file. masks: None (cluster the points above the table), or instance
        ids [H, W] (0 = background) or a PNG of them. workspace: None, or bool [H, W] (or a PNG, nonzero
        = in) of the pixels to use. seed: the table fit's. -> Frame; PerceptionError for unusable input."""
        # The front end's matrix products are thin ([N, 3] by [3, k]): BLAS threads gain nothing on them and,
        # beside other busy processes, spin and wait (a frame's whole front end 3.4x slower beside three
        # jobs; docs/real-camera.md), so it runs on one.
        with one_blas_thread():
            return cls._from_depth(depth, intrinsics, depth_scale, extrinsics, masks, workspace, segment, seed)

    @classmethod
    def _from_depth(cls, depth, intrinsics, depth_scale: float, extrinsics, masks, workspace, segment: SegmentConfig,
                    seed: int) -> Frame:
        scaled = _is_path(depth) and str(depth).lower().endswith(".png") or np.asarray(depth).dtype.kind in "ui"
        depth = _depth(depth, depth_scale)
        if not isinstance(intrinsics, Intrinsics):
            intrinsics = read_intrinsics(intrinsics) if _is_path(intrinsics) else Intrinsics.from_matrix(intrinsics)
        if extrinsics is not None:
            try:
                extrinsics = read_extrinsics(extrinsics) if _is_path(extrinsics) else rigid_extrinsics(extrinsics)
            except ValueError as exc:
                raise PerceptionError(str(exc)) from None
        size = depth.shape
        if intrinsics.width is not None and (intrinsics.height, intrinsics.width) != size:
            raise PerceptionError(f"the depth image is {size[1]}x{size[0]} pixels but the intrinsics are for "
                                  f"{intrinsics.width}x{intrinsics.height}")
        valid = depth > 0
        if not valid.any():
            raise PerceptionError("the depth image has no valid pixel (all zero, NaN or inf)")
        median = float(np.median(depth[::4, ::4][valid[::4, ::4]])) if valid[::4, ::4].any() else float(np.median(depth[valid]))
        if not PLAUSIBLE_DEPTH[0] <= median <= PLAUSIBLE_DEPTH[1]:
            hint = f"is depth_scale ({depth_scale:g} units per metre) right?" if scaled else "is the depth in metres?"
            raise PerceptionError(f"the median depth is {median:.4g} m, outside {PLAUSIBLE_DEPTH[0]}-{PLAUSIBLE_DEPTH[1]} m: "
                                  f"{hint}")
        if workspace is not None:
            workspace = _image(workspace, size, "workspace mask") != 0
            depth = np.where(workspace, depth, 0.0)
            if not (depth > 0).any():
                raise PerceptionError("the workspace mask holds no pixel with depth")
        ids = None if masks is None else _image(masks, size, "masks")
        points, pixels = back_project(depth, intrinsics)
        camera_position = np.zeros(3)
        up = None
        if extrinsics is not None:
            points, camera_position, up = to_world(points, extrinsics), extrinsics[:3, 3].copy(), (0.0, 0.0, 1.0)
        try:
            table = fit_table(points, viewpoint=camera_position, seed=seed, up=up,
                              max_tilt_deg=None if up is None else WORLD_TABLE_TILT_DEG)
        except ValueError as exc:
            raise PerceptionError(f"no table plane found: {exc}") from None
        if table.inliers.mean() < MIN_TABLE_SHARE:
            raise PerceptionError(f"no table plane found: the largest plane holds {100 * table.inliers.mean():.1f} % of "
                                  f"the points (< {100 * MIN_TABLE_SHARE:.0f} %)")
        joined = None
        if ids is None:
            (labels, joined), how = segment_with_joined(points, pixels, size, table, camera_position,
                                                        _pixel_angle(intrinsics), segment,
                                                        height=table.heights), "clusters"
        else:
            labels, how = _mask_labels(ids, pixels, table.heights, segment), "masks"
        return cls(points, labels, pixels, table, camera_position, intrinsics, extrinsics, size, how, joined, segment)


def _pixel_angle(intrinsics: Intrinsics) -> float:
    """Radians per pixel (the larger of the two axes'): the segmentation's link tolerance scales with it."""
    return 1.0 / min(intrinsics.fx, intrinsics.fy)


def _is_path(value) -> bool:
    return isinstance(value, (str, os.PathLike))


def _depth(depth, depth_scale: float) -> np.ndarray:
    if _is_path(depth):
        return read_depth(depth, depth_scale).astype(np.float64)
    depth = np.asarray(depth)
    if depth.ndim != 2:
        raise PerceptionError(f"a depth image must be [H, W], got shape {depth.shape}")
    if depth.dtype.kind in "ui":
        if not (np.isfinite(depth_scale) and depth_scale > 0):
            raise PerceptionError(f"depth_scale must be a number > 0 (units per metre), got {depth_scale}")
        depth = depth / float(depth_scale)
    elif depth.dtype.kind != "f":
        raise PerceptionError(f"a depth image must hold numbers, got {depth.dtype}")
    depth = np.where(np.isfinite(depth), depth, 0.0).astype(np.float64)
    if (depth < 0).any():
        raise PerceptionError(f"the depth image holds {int((depth < 0).sum())} negative depths")
    return depth


def read_image(path: str | os.PathLike, what: str = "image") -> np.ndarray:
    """A per-pixel image (masks' instance ids, a workspace mask) from a PNG or a `.npy`; errors name the
    file and `what` it was to be."""
    path, suffix = existing_file(path, what)
    if suffix == ".npy":
        return np.load(path, allow_pickle=False)
    from PIL import Image

    try:
        with Image.open(path) as image:
            return np.asarray(image)
    except OSError as exc:  # Pillow's UnidentifiedImageError among them
        raise PerceptionError(f"{path}: cannot read the {what} ({exc})") from None


def _image(value, size: tuple[int, int], what: str) -> np.ndarray:
    """An integer image [H, W] from an array or a PNG / .npy file, checked against the depth's size."""
    name = os.fspath(value) if _is_path(value) else f"the {what}"
    if _is_path(value):
        value = read_image(value, what)
    value = np.asarray(value)
    if value.ndim == 3 and value.shape[2] in (3, 4):  # an RGB(A) picture of it: every channel must agree
        if np.any(value[..., :3] != value[..., :1]):
            raise PerceptionError(f"{name}: expected one channel of ids, got a colour image")
        value = value[..., 0]
    if value.shape != size:
        raise PerceptionError(f"{name} is {value.shape[1] if value.ndim > 1 else '?'}x{value.shape[0]} "
                              f"pixels but the depth image is {size[1]}x{size[0]}")
    if value.dtype.kind not in "biu":
        raise PerceptionError(f"{name}: expected integer ids (or bool), got {value.dtype}")
    return value.astype(np.int64)


def _mask_labels(ids: np.ndarray, pixels: np.ndarray, height: np.ndarray, segment: SegmentConfig) -> np.ndarray:
    """Labels from instance ids of the points at pixels [N, 2], heights [N] above the table (the fit's
    `TablePlane.heights`): a masked pixel's id (> 0; a mask that strays more than the table's noise below
    the table is background there), else TABLE on the table and OTHER off it."""
    if (ids < 0).any():
        raise PerceptionError("masks: instance ids must be >= 0 (0 = background)")
    threshold = height_threshold(table_noise(height), segment)
    point_ids = ids[pixels[:, 0], pixels[:, 1]]
    labels = np.where(np.abs(height) <= threshold, TABLE, OTHER).astype(np.int32)
    obj = (point_ids > 0) & (height >= -threshold)
    labels[obj] = point_ids[obj]
    return labels
