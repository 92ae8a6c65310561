"""Pictures of clouds with gripper outlines (matplotlib, headless), shared by the CLI and the benchmark."""

from __future__ import annotations

import os

import numpy as np

from sgjax.utils.files import atomic_write
from sgjax.geometry.gripper import GripperSpec


def gripper_outline(pose: np.ndarray, width: float, spec: GripperSpec = GripperSpec()) -> np.ndarray:
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


def draw_grasps(
    path: str | os.PathLike,
    points: np.ndarray,
    poses: np.ndarray | None = None,
    widths: np.ndarray | None = None,
    scene_points: np.ndarray | None = None,
    scores: np.ndarray | None = None,
    spec: GripperSpec = GripperSpec(),
    max_grasps: int = 20,
    title: str | None = None,
) -> None:
    """Write a PNG: the object cloud points[N, 3] (and scene_points[S, 3] in grey) with the first
    `max_grasps` grasps (poses [M, 4, 4], widths [M]) drawn as outlines, coloured by `scores` [M]
    (default: by order), from an oblique and a top view. The file is written atomically."""
    # The object API (Figure), not pyplot: no global backend switch, so a notebook's inline plots keep
    # working after a picture is written.
    from matplotlib import colormaps
    from matplotlib.figure import Figure

    points = np.asarray(points, np.float64).reshape(-1, 3)
    poses = np.zeros((0, 4, 4)) if poses is None else np.asarray(poses, np.float64)[:max_grasps]
    widths = np.zeros(0) if widths is None else np.asarray(widths, np.float64)[:max_grasps]
    if len(poses) != len(widths):
        raise ValueError(f"got {len(poses)} poses but {len(widths)} widths")
    colour_of = np.linspace(1.0, 0.0, max(len(poses), 1)) if scores is None else np.asarray(scores)[: len(poses)]
    cmap = colormaps["viridis"]

    fig = Figure(figsize=(10, 5))
    for k, (elev, azim) in enumerate([(35, -60), (89, -90)]):
        ax = fig.add_subplot(1, 2, k + 1, projection="3d")
        if scene_points is not None and len(scene_points):
            s = np.asarray(scene_points).reshape(-1, 3)
            s = s[:: max(1, len(s) // 8000)]
            ax.scatter(*s.T, s=0.5, c="0.75", depthshade=False)
        ax.scatter(*points.T, s=1.5, c="tab:red", depthshade=False)
        segments = [gripper_outline(p, w, spec) for p, w in zip(poses, widths)]
        for seg, c in zip(segments, colour_of):
            for a, b in seg:
                ax.plot(*np.stack([a, b]).T, color=cmap(float(c)), linewidth=1.2)
        every = np.concatenate([points] + [s.reshape(-1, 3) for s in segments])
        centre, half = every.mean(0), 0.55 * np.max(every.max(0) - every.min(0))
        ax.set_xlim(centre[0] - half, centre[0] + half)
        ax.set_ylim(centre[1] - half, centre[1] + half)
        ax.set_zlim(centre[2] - half, centre[2] + half)
        ax.set_box_aspect((1, 1, 1))
        ax.view_init(elev=elev, azim=azim)
        ax.set_xlabel("x")
        ax.set_ylabel("y")
        ax.set_zlabel("z")
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    atomic_write(path, lambda tmp: fig.savefig(tmp, dpi=110))
