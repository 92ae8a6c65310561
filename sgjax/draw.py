"""Pictures of clouds and depth images with gripper outlines (matplotlib, headless), shared by the CLI and
the benchmark.

    draw_grasps(path, object_points, poses, widths, scene_points=cloud, up=table_normal)   # two 3D views
    draw_on_image(path, depth, K, poses_in_camera, widths, labels_image=labels)         # on the image

Every picture is written atomically with matplotlib's object API (a `Figure`, never pyplot), so a
notebook's inline plots keep working after a picture is written.
"""

from __future__ import annotations

import os

import numpy as np

from sgjax.geometry.gripper import GripperSpec, closing_centre
from sgjax.utils.files import atomic_write

DEFAULT_SPEC = GripperSpec()
Z_UP = (0.0, 0.0, 1.0)


def gripper_outline(pose: np.ndarray, width: float, spec: GripperSpec = DEFAULT_SPEC) -> np.ndarray:
    """Line segments of a parallel-jaw gripper drawn as in the paper's figures: [5, 2, 3] world points.

    Two fingers (palm-side face to fingertip, at x = -+w/2), the bar joining them, and a stem of the
    palm's depth along -z (where the arm would attach).
    """
    w, length, depth = 0.5 * float(width), spec.finger_length, spec.palm_size[2]
    local = np.array(
        [
            [[-w, 0, 0], [-w, 0, length]],
            [[w, 0, 0], [w, 0, length]],
            [[-w, 0, 0], [w, 0, 0]],
            [[0, 0, -depth], [0, 0, 0]],
            [[-w, 0, length], [-w, 0, length]],  # a dot at the fingertip keeps the 3D limits honest
        ]
    )
    pose = np.asarray(pose, np.float64)
    return local @ pose[:3, :3].T + pose[:3, 3]


def up_rotation(up=Z_UP) -> np.ndarray:
    """[3, 3] a rotation R with R @ up / |up| = (0, 0, 1): rows x', y', up of a right-handed frame whose x'
    is the coordinate axis least aligned with up, made perpendicular to it (the identity for up = +z).
    ValueError for an up that is zero, not finite or not 3 numbers."""
    u = np.asarray(up, np.float64)
    length = float(np.linalg.norm(u)) if u.shape == (3,) else float("nan")
    if not (np.isfinite(length) and length > 0):
        raise ValueError(f"up must be a finite non-zero 3-vector, got {up!r}")
    u = u / length
    x = np.eye(3)[int(np.argmin(np.abs(u)))]
    x = x - (x @ u) * u
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(u, x), u])


def _grasp_arrays(poses, widths, scores, max_grasps: int):
    poses = np.zeros((0, 4, 4)) if poses is None else np.asarray(poses, np.float64).reshape(-1, 4, 4)[:max_grasps]
    widths = np.zeros(0) if widths is None else np.asarray(widths, np.float64).reshape(-1)[:max_grasps]
    if len(poses) != len(widths):
        raise ValueError(f"got {len(poses)} poses but {len(widths)} widths")
    colour_of = np.linspace(1.0, 0.0, max(len(poses), 1)) if scores is None else np.asarray(scores, np.float64)[: len(poses)]
    return poses, widths, colour_of


def _cloud_views(fig, slots, points, poses, widths, scene_points, colour_of, spec, up) -> None:
    """Two 3D views (oblique, top) of points and grasp outlines, rotated so that `up` is drawn upwards."""
    from matplotlib import colormaps

    cmap = colormaps["viridis"]
    rotation = up_rotation(up)
    identity = np.array_equal(rotation, np.eye(3))
    turn = (lambda a: a) if identity else (lambda a: np.asarray(a, np.float64) @ rotation.T)
    points = turn(np.asarray(points, np.float64).reshape(-1, 3))
    scene = None
    if scene_points is not None and len(scene_points):
        scene = np.asarray(scene_points).reshape(-1, 3)
        scene = turn(scene[:: max(1, len(scene) // 8000)])
    segments = [turn(gripper_outline(p, w, spec)) for p, w in zip(poses, widths)]
    every = np.concatenate([points] + [s.reshape(-1, 3) for s in segments])
    box = None
    if len(every):  # a cube around the points and the grasps; the scene only where it falls inside
        centre, half = every.mean(0), 0.55 * np.max(every.max(0) - every.min(0))
        box = (centre, half if half > 0 else 0.05)
        if scene is not None:
            scene = scene[np.all(np.abs(scene - box[0]) <= box[1], axis=1)]
    for slot, (elev, azim) in zip(slots, [(35, -60), (89, -90)]):
        ax = fig.add_subplot(slot, projection="3d")
        if scene is not None and len(scene):
            ax.scatter(*scene.T, s=0.5, c="0.75", depthshade=False)
        ax.scatter(*points.T, s=1.5, c="tab:red", depthshade=False)
        for seg, c in zip(segments, colour_of):
            for a, b in seg:
                ax.plot(*np.stack([a, b]).T, color=cmap(float(c)), linewidth=1.2)
        if box is not None:
            (cx, cy, cz), half = box
            ax.set_xlim(cx - half, cx + half)
            ax.set_ylim(cy - half, cy + half)
            ax.set_zlim(cz - half, cz + half)
        ax.set_box_aspect((1, 1, 1))
        ax.view_init(elev=elev, azim=azim)
        names = ("x", "y", "z") if identity else ("x'", "y'", "up")
        ax.set_xlabel(names[0])
        ax.set_ylabel(names[1])
        if elev > 80:  # the top view looks down the vertical axis: its ticks would pile up in one corner
            ax.set_zticks([])
        else:
            ax.set_zlabel(names[2])


def draw_grasps(
    path: str | os.PathLike,
    points: np.ndarray,
    poses: np.ndarray | None = None,
    widths: np.ndarray | None = None,
    scene_points: np.ndarray | None = None,
    scores: np.ndarray | None = None,
    spec: GripperSpec = DEFAULT_SPEC,
    max_grasps: int = 20,
    title: str | None = None,
    up=Z_UP,
) -> None:
    """Write a PNG: the object cloud points[N, 3] (and scene_points[S, 3] in grey) with the first
    `max_grasps` grasps (poses [M, 4, 4], widths [M]) drawn as outlines, coloured by `scores` [M]
    (default: by order), from an oblique and a top view. up [3]: the direction drawn upwards (default
    +z, a world frame's); a camera-frame cloud passes its table's normal: points and outlines are
    rotated by `up_rotation(up)` before plotting (axes x', y', up). The file is written atomically."""
    from matplotlib.figure import Figure

    up_rotation(up)  # a bad `up` fails before any drawing
    poses, widths, colour_of = _grasp_arrays(poses, widths, scores, max_grasps)
    fig = Figure(figsize=(10, 5))
    _cloud_views(fig, (121, 122), points, poses, widths, scene_points, colour_of, spec, up)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    atomic_write(path, lambda tmp: fig.savefig(tmp, dpi=110))


def project(points: np.ndarray, intrinsics: np.ndarray) -> np.ndarray:
    """Camera-frame points [..., 3] (OpenCV: x right, y down, z forward) -> pixel coordinates [..., 2]
    (u column, v row; pixel (row r, column c) is centred at (c, r), OpenCV's and imshow's convention);
    NaN for points at or behind the camera (z <= 1 mm)."""
    p = np.asarray(points, np.float64)
    K = np.asarray(intrinsics, np.float64)
    z = p[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = np.stack([K[0, 0] * p[..., 0] / z + K[0, 2], K[1, 1] * p[..., 1] / z + K[1, 2]], -1)
    return np.where((z > 1e-3)[..., None], uv, np.nan)


def _image_view(ax, image, K, poses, widths, labels_image, colour_of, spec, names, cmap_name: str, tint: bool) -> None:
    """The image through colour map `cmap_name` (a depth image: near bright, no depth black), objects (labels
    > 0) tinted (with `tint`) and outlined, grasp outlines projected with K, each named at its tool-centre point."""
    from matplotlib import colormaps

    image = np.asarray(image, np.float64)
    valid = np.isfinite(image) & (image > 0)
    shown = np.zeros(image.shape)
    if valid.any():
        lo, hi = np.percentile(image[valid], [1, 99])
        shown = np.where(valid, 1.0 - 0.8 * np.clip((image - lo) / max(hi - lo, 1e-9), 0, 1), 0.0)
    rgb = colormaps[cmap_name](shown)
    rgb[~valid] = (0.0, 0.0, 0.0, 1.0)
    ax.imshow(rgb, interpolation="nearest")
    if labels_image is not None:
        labels = np.asarray(labels_image)
        if labels.shape != image.shape:
            raise ValueError(f"labels_image is {labels.shape}, the image {image.shape}")
        ids = np.unique(labels[labels > 0])
        tab = colormaps["tab20"]
        overlay = np.zeros((*labels.shape, 4))
        for k, i in enumerate(ids if tint else ()):
            overlay[labels == i] = (*tab(k % 20)[:3], 0.4)
        edge = np.zeros(labels.shape, bool)  # pixels whose right or lower neighbour has another label
        edge[:, :-1] |= labels[:, :-1] != labels[:, 1:]
        edge[:-1] |= labels[:-1] != labels[1:]
        edge &= labels > 0
        overlay[edge] = (1.0, 1.0, 1.0, 0.9)
        ax.imshow(overlay, interpolation="nearest")
        for k, i in enumerate(ids):
            rows, cols = np.nonzero(labels == i)
            ax.text(cols.mean(), rows.mean(), str(int(i)), color="white", fontsize=7, ha="center", va="center")
    cmap = colormaps["viridis"]
    for g, (pose, width, c) in enumerate(zip(poses, widths, colour_of)):
        uv = project(gripper_outline(pose, width, spec), K)
        colour = cmap(float(c))
        for a, b in uv[:4]:
            if np.isfinite(a).all() and np.isfinite(b).all():
                ax.plot([a[0], b[0]], [a[1], b[1]], color=colour, linewidth=2.0)
        tcp = project(closing_centre(pose, spec, np), K)  # the tool-centre point
        if np.isfinite(tcp).all():
            ax.plot(*tcp, "o", color=colour, markersize=3)
            if names is not None:
                ax.annotate(names[g], tcp, xytext=(4, -4), textcoords="offset points", color=colour, fontsize=7)
    ax.set_xlim(-0.5, image.shape[1] - 0.5)
    ax.set_ylim(image.shape[0] - 0.5, -0.5)
    ax.set_axis_off()


def draw_on_image(
    path: str | os.PathLike,
    image: np.ndarray,
    intrinsics: np.ndarray,
    poses: np.ndarray | None = None,
    widths: np.ndarray | None = None,
    labels_image: np.ndarray | None = None,
    scores: np.ndarray | None = None,
    names: list[str] | None = None,
    spec: GripperSpec = DEFAULT_SPEC,
    max_grasps: int = 20,
    title: str | None = None,
    cmap: str = "gray",
    tint: bool = True,
    points: np.ndarray | None = None,
    scene_points: np.ndarray | None = None,
    frame_poses: np.ndarray | None = None,
    up=Z_UP,
) -> None:
    """Write a PNG of an image [H, W] (a depth image in metres, 0 or NaN = none, drawn grey: near bright)
    with the first `max_grasps` grasps (poses [M, 4, 4] in the CAMERA frame, OpenCV axes; widths [M])
    projected by intrinsics K [3, 3] (OpenCV convention: pixel (row r, column c) is centred at (c, r)):
    fingers, bar and stem, a dot at the tool-centre point and `names` [M] beside it, coloured by `scores`
    [M] (default: by order). cmap: the image's matplotlib colour map (near bright, no depth black).
    labels_image [H, W] (optional): pixels with a label > 0 are outlined, numbered and (with `tint`) tinted
    per label.

    With `points` [N, 3] (and `scene_points` [S, 3]) two 3D views follow the image, as `draw_grasps`
    draws them: points and `frame_poses` [M, 4, 4] (default: `poses`) in the cloud's frame, `up` the
    direction drawn upwards there (a camera frame's table normal; +z in a world frame). The file is
    written atomically."""
    from matplotlib.figure import Figure

    up_rotation(up)
    image = np.asarray(image)
    if image.ndim != 2:
        raise ValueError(f"image must be [H, W], got shape {image.shape}")
    K = np.asarray(intrinsics, np.float64)
    if K.shape != (3, 3):
        raise ValueError(f"intrinsics must be a 3x3 matrix, got shape {K.shape}")
    poses, widths, colour_of = _grasp_arrays(poses, widths, scores, max_grasps)
    names = None if names is None else list(names)[: len(poses)]
    h, w = image.shape
    if points is None:
        fig = Figure(figsize=(7.0, 7.0 * h / w + 0.4))
        ax = fig.add_subplot(111)
    else:
        fig = Figure(figsize=(15, 5))
        ax = fig.add_subplot(131)
    _image_view(ax, image, K, poses, widths, labels_image, colour_of, spec, names, cmap, tint)
    if points is not None:
        frame_poses = poses if frame_poses is None else np.asarray(frame_poses, np.float64).reshape(-1, 4, 4)[:max_grasps]
        if len(frame_poses) != len(poses):
            raise ValueError(f"got {len(poses)} poses but {len(frame_poses)} frame_poses")
        _cloud_views(fig, (132, 133), points, frame_poses, widths, scene_points, colour_of, spec, up)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    atomic_write(path, lambda tmp: fig.savefig(tmp, dpi=110))
