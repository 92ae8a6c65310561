"""Depth images: read from files, back-projected to camera-frame points."""

from __future__ import annotations

import os

import numpy as np

from sgjax.perception.camera import Intrinsics, existing_file


def read_depth(path: str | os.PathLike, depth_scale: float = 1000.0) -> np.ndarray:
    """A depth image [H, W] in metres (float32; 0 where the sensor gave no depth) from a 16-bit PNG
    (`depth_scale`: its units per metre, 1000 = millimetres, a RealSense's and a Kinect's default) or a
    float `.npy` / `.npz` (its only array, or the one named "depth") already in metres. NaN and inf
    read as no depth; negative depths are refused."""
    path, suffix = existing_file(path, "depth image")
    if not (np.isfinite(depth_scale) and depth_scale > 0):
        raise ValueError(f"depth_scale must be a number > 0 (units per metre), got {depth_scale}")
    if suffix == ".png":
        from PIL import Image

        try:
            with Image.open(path) as image:
                raw = np.asarray(image)
        except OSError as exc:  # Pillow's UnidentifiedImageError among them
            raise ValueError(f"{path}: cannot read the depth PNG ({exc})") from None
        if raw.ndim != 2 or raw.dtype.kind not in "ui":
            raise ValueError(f"{path}: a depth PNG must be one 16-bit (or 8-bit) channel, got {raw.dtype} {raw.shape}")
        depth = raw.astype(np.float64) / depth_scale
    elif suffix in (".npy", ".npz"):
        loaded = np.load(path, allow_pickle=False)
        if suffix == ".npz":
            names = list(loaded.files)
            if "depth" not in names and len(names) != 1:
                raise ValueError(f"{path}: an .npz depth needs one array or one named 'depth', got {names}")
            loaded = loaded["depth" if "depth" in names else names[0]]
        depth = np.asarray(loaded, np.float64)
        if depth.ndim != 2:
            raise ValueError(f"{path}: a depth image must be 2-D [H, W] (metres), got shape {depth.shape}")
    else:
        raise ValueError(f"{path}: depth must be a 16-bit .png or a float .npy/.npz, got {suffix or 'no suffix'}")
    depth = np.where(np.isfinite(depth), depth, 0.0)
    if (depth < 0).any():
        raise ValueError(f"{path}: {int((depth < 0).sum())} negative depths")
    return depth.astype(np.float32)


def back_project(depth: np.ndarray, intrinsics: Intrinsics, min_depth: float = 0.0,
                 max_depth: float = np.inf) -> tuple[np.ndarray, np.ndarray]:
    """Camera-frame points of depth [H, W] (metres; 0 = none): a pixel (u, v) at depth z is
    (z (u - cx) / fx, z (v - cy) / fy, z). Only pixels with min_depth < z <= max_depth are kept.
    -> (points [N, 3] float64, pixels [N, 2] int (row v, column u)), in row-major pixel order."""
    depth = np.asarray(depth, np.float64)
    if depth.ndim != 2:
        raise ValueError(f"depth must be [H, W], got shape {depth.shape}")
    h, w = depth.shape
    if intrinsics.width is not None and (intrinsics.width, intrinsics.height) != (w, h):
        raise ValueError(f"the depth image is {w}x{h} pixels but the intrinsics are for "
                         f"{intrinsics.width}x{intrinsics.height}")
    # Flat indices and whole columns: NumPy gathers and fills narrow [N, 3] arrays a column at a time faster.
    index = np.flatnonzero(np.isfinite(depth) & (depth > min_depth) & (depth <= max_depth))
    v = index // w  # not np.divmod: NumPy divides by a scalar fast (libdivide) but takes a remainder ~4x slower
    u = index - v * w
    z = depth.reshape(-1)[index]
    points = np.empty((len(index), 3))
    points[:, 0] = z * (u - intrinsics.cx) / intrinsics.fx
    points[:, 1] = z * (v - intrinsics.cy) / intrinsics.fy
    points[:, 2] = z
    pixels = np.empty((len(index), 2), index.dtype)
    pixels[:, 0], pixels[:, 1] = v, u
    return points, pixels

