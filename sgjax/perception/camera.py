"""Camera calibration from files: pinhole intrinsics and a camera-to-world pose."""

from __future__ import annotations

import dataclasses
import json
import os

import numpy as np


@dataclasses.dataclass(frozen=True)
class Intrinsics:
    """A pinhole camera (OpenCV convention: x right, y down, z forward; pixels (u, v) = (column, row)).

    fx, fy: focal lengths in pixels; cx, cy: principal point in pixels; width, height: the image size
    in pixels, None when the calibration does not say (then any depth image size is accepted)."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int | None = None
    height: int | None = None

    def __post_init__(self):
        for name in ("fx", "fy", "cx", "cy"):
            value = getattr(self, name)
            if not np.isfinite(value):
                raise ValueError(f"intrinsics: {name} must be a finite number, got {value}")
        if self.fx <= 0 or self.fy <= 0:
            raise ValueError(f"intrinsics: fx and fy must be > 0 pixels, got {self.fx} and {self.fy}")
        for name in ("width", "height"):
            value = getattr(self, name)
            if value is not None and (int(value) != value or value < 1):
                raise ValueError(f"intrinsics: {name} must be a positive integer, got {value}")

    @property
    def K(self) -> np.ndarray:
        """The 3x3 camera matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @classmethod
    def from_matrix(cls, K, width: int | None = None, height: int | None = None) -> Intrinsics:
        """From a 3x3 camera matrix [[fx, s, cx], [0, fy, cy], [0, 0, 1]] (skew s must be 0)."""
        K = np.asarray(K, np.float64)
        if K.shape != (3, 3) or not np.all(np.isfinite(K)):
            raise ValueError(f"intrinsics: K must be a finite 3x3 matrix, got shape {K.shape}")
        if abs(K[0, 1]) > 1e-9 or np.any(np.abs(K[2] - (0.0, 0.0, 1.0)) > 1e-9) or abs(K[1, 0]) > 1e-9:
            raise ValueError(f"intrinsics: K must be [[fx, 0, cx], [0, fy, cy], [0, 0, 1]], got {K.tolist()}")
        return cls(float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]), _size(width), _size(height))


def _size(value) -> int | None:
    return None if value is None else int(value)


def existing_file(path: str | os.PathLike, what: str) -> tuple[str, str]:
    """path as a string and its lower-case suffix; FileNotFoundError naming `what` when it is no file."""
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise FileNotFoundError(f"{path}: no such {what}")
    return path, os.path.splitext(path)[1].lower()


def read_intrinsics(path: str | os.PathLike) -> Intrinsics:
    """Intrinsics from a file: JSON `{"K": 3x3}` or `{"fx", "fy", "cx", "cy"}` (optional "width",
    "height"), a ROS CameraInfo YAML (camera_calibration's `camera_matrix: {rows, cols, data}`,
    `image_width`, `image_height`; or a `K` list of 9), or a 3x3 `.npy`. Errors name the file and field."""
    path, suffix = existing_file(path, "intrinsics file")
    try:
        if suffix == ".npy":
            return Intrinsics.from_matrix(np.load(path, allow_pickle=False))
        if suffix == ".json":
            with open(path) as f:
                data = json.load(f)
            return _from_mapping(data, path)
        if suffix in (".yaml", ".yml"):
            import yaml

            with open(path) as f:
                data = yaml.safe_load(f)
            return _from_ros(data, path)
    except ValueError as exc:
        if str(exc).startswith(path):
            raise
        raise ValueError(f"{path}: {exc}") from None
    raise ValueError(f"{path}: intrinsics must be .json, .yaml/.yml (ROS CameraInfo) or a 3x3 .npy, got {suffix or 'no suffix'}")


def _from_mapping(data, path: str) -> Intrinsics:
    if not isinstance(data, dict):
        raise ValueError(f"{path}: expected a JSON object with 'K' or 'fx', 'fy', 'cx', 'cy'")
    size = {k: data.get(k) for k in ("width", "height")}
    if "K" in data:
        if np.size(data["K"]) != 9:
            raise ValueError(f"{path}: 'K' must be a 3x3 matrix (or 9 numbers)")
        return Intrinsics.from_matrix(np.asarray(data["K"], np.float64).reshape(3, 3), **size)
    missing = [k for k in ("fx", "fy", "cx", "cy") if k not in data]
    if missing:
        raise ValueError(f"{path}: missing field(s) {', '.join(missing)} (or give 'K')")
    return Intrinsics(*(float(data[k]) for k in ("fx", "fy", "cx", "cy")), **{k: _size(v) for k, v in size.items()})


def _from_ros(data, path: str) -> Intrinsics:
    if not isinstance(data, dict):
        raise ValueError(f"{path}: expected a CameraInfo mapping")
    size = {"width": data.get("image_width", data.get("width")), "height": data.get("image_height", data.get("height"))}
    if "camera_matrix" in data:
        matrix = data["camera_matrix"]
        values = matrix.get("data") if isinstance(matrix, dict) else matrix
    elif "K" in data or "k" in data:
        values = data.get("K", data.get("k"))
    else:
        raise ValueError(f"{path}: no 'camera_matrix' (camera_calibration) or 'K' (CameraInfo) field")
    if values is None or np.size(values) != 9:
        raise ValueError(f"{path}: the camera matrix must hold 9 numbers")
    return Intrinsics.from_matrix(np.asarray(values, np.float64).reshape(3, 3), **size)


def read_extrinsics(path: str | os.PathLike) -> np.ndarray:
    """A camera-to-world pose [4, 4] from JSON (a 4x4 list, or {"T": 4x4}) or `.npy`; its rotation must
    be proper (orthonormal, determinant +1, within 1e-3) and its last row (0, 0, 0, 1)."""
    path, suffix = existing_file(path, "extrinsics file")
    if suffix == ".npy":
        T = np.load(path, allow_pickle=False)
    elif suffix == ".json":
        try:
            with open(path) as f:
                data = json.load(f)
        except json.JSONDecodeError as exc:
            raise ValueError(f"{path}: not valid JSON ({exc})") from None
        T = data.get("T", data.get("camera_to_world")) if isinstance(data, dict) else data
    else:
        raise ValueError(f"{path}: extrinsics must be .json or .npy, got {suffix or 'no suffix'}")
    try:
        return rigid_extrinsics(T)
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from None


def rigid_extrinsics(T) -> np.ndarray:
    """T as a float64 camera-to-world [4, 4], checked: numeric, finite, its rotation proper (orthonormal,
    determinant +1, within 1e-3) and its last row (0, 0, 0, 1); ValueError naming what is wrong."""
    try:
        T = np.asarray(T, np.float64)
    except (TypeError, ValueError):
        raise ValueError("extrinsics are not a numeric 4x4 matrix") from None
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise ValueError(f"extrinsics must be a finite 4x4 camera-to-world matrix, got shape {T.shape}")
    R = T[:3, :3]
    if np.abs(R @ R.T - np.eye(3)).max() > 1e-3 or abs(np.linalg.det(R) - 1.0) > 1e-3:
        raise ValueError("the extrinsics' rotation is not a proper rotation (orthonormal, det +1)")
    if np.abs(T[3] - (0.0, 0.0, 0.0, 1.0)).max() > 1e-9:
        raise ValueError(f"the extrinsics' last row must be (0, 0, 0, 1), got {T[3].tolist()}")
    return T


def to_world(points: np.ndarray, camera_to_world: np.ndarray) -> np.ndarray:
    """Camera-frame points [N, 3] in the world frame of camera_to_world [4, 4] -> [N, 3]."""
    T = np.asarray(camera_to_world, np.float64)
    return np.asarray(points, np.float64) @ T[:3, :3].T + T[:3, 3]
