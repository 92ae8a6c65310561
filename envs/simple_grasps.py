"""Analytic top-down grasps from an object's settled pose: smoke tests and benchmarks without Stage 1.

For an object resting on the table, the two mesh axes closest to horizontal are candidate closing
directions; a top-down grasp (approach straight down) closes across one of them, centred on the
object's visible extent, with the paper's contact clearance delta on each side.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from envs import scene as scene_lib


def object_vertices(scene: scene_lib.Scene, index: int) -> np.ndarray:
    """[V, 3] world-frame vertices of object `index`'s visual mesh at the settled pose."""
    pose = scene.object_poses()[index]
    mesh = scene_lib._load_mesh(scene.assets[index].visual_path)
    rotation = Rotation.from_quat(np.roll(pose[3:], -1)).as_matrix()
    return mesh.vertices @ rotation.T + pose[:3]


def top_down_pose(vertices: np.ndarray, closing: np.ndarray, tips: float, spec) -> tuple[np.ndarray | None, float]:
    """A straight-down grasp closing along the horizontal part of `closing` [3], centred on the
    vertices' [V, 3] extent, fingertips at height `tips` -> (pose [4, 4] or None if `closing` is
    vertical, the vertices' extent along the closing axis)."""
    x = np.array([closing[0], closing[1], 0.0])
    if np.linalg.norm(x) < 1e-6:
        return None, 0.0
    x /= np.linalg.norm(x)
    z = np.array([0.0, 0.0, -1.0])
    y = np.cross(z, x)
    along_x, along_y = vertices @ x, vertices @ y
    centre = 0.5 * (along_x.max() + along_x.min()) * x + 0.5 * (along_y.max() + along_y.min()) * y
    pose = np.eye(4)
    pose[:3, :3] = np.stack([x, y, z], axis=1)
    pose[:3, 3] = [centre[0], centre[1], tips + spec.finger_length]
    return pose, float(along_x.max() - along_x.min())


def top_down_grasps(
    scene: scene_lib.Scene, index: int, depth: float = 0.03, table_clearance: float = 0.01
) -> tuple[np.ndarray, np.ndarray]:
    """Top-down grasps of object `index` closing across its two most horizontal mesh axes.

    depth: how far below the object's top the fingertips go (limited to table_clearance above the
    table). Returns poses[G, 4, 4] and widths[G] (extent + 2 * contact_threshold); axes whose width
    exceeds max_opening are left out, so G is 0, 1 or 2.
    """
    spec = scene.gripper
    rotation = Rotation.from_quat(np.roll(scene.object_poses()[index, 3:], -1)).as_matrix()
    vertices = object_vertices(scene, index)
    top = vertices[:, 2].max()
    tips = max(top - depth, table_clearance)
    vertical = int(np.argmax(np.abs(rotation[2])))
    poses, widths = [], []
    for axis in (a for a in range(3) if a != vertical):
        pose, extent = top_down_pose(vertices, rotation[:, axis], tips, spec)
        width = extent + 2 * spec.contact_threshold
        if pose is None or width > spec.max_opening:
            continue
        poses.append(pose)
        widths.append(width)
    return np.reshape(poses, (-1, 4, 4)), np.asarray(widths)
