"""The Stage-2 scene cloud: the one description of the cloud the Stage-2 networks crop from.

E-RNet is trained on crops of this cloud (`train.label`) and must see the same point density when it
plans (`sgjax.planner`), as must the baselines that share its scorer (`eval.baselines`): all of them
build the cloud from one `SceneCloudConfig`. The benchmark's and labelling's workspace crop comes from
the simulated scene (`envs.scene.stage2_scene_cloud`), since sgjax knows no workspace.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from sgjax.geometry import pointcloud

Bounds = tuple[tuple[float, float, float], tuple[float, float, float]]


@dataclasses.dataclass(frozen=True)
class SceneCloudConfig:
    """How an observed scene becomes the fixed-size Stage-2 cloud (hashable).

    max_points: the cloud's fixed size (padded and masked).
    voxel: one point per voxel of this side (m) before the subsample; 0: no voxel grid.
    bounds: optional axis-aligned crop ((lo x, y, z), (hi x, y, z)); None: no crop.
    """

    max_points: int = 32768
    voxel: float = 0.003
    bounds: Bounds | None = None

    def __post_init__(self):
        if self.max_points < 1:
            raise ValueError(f"SceneCloudConfig.max_points must be >= 1, got {self.max_points}")
        if self.voxel < 0:
            raise ValueError(f"SceneCloudConfig.voxel must be >= 0 (0: no voxel grid), got {self.voxel}")
        if self.bounds is not None:
            lo, hi = (tuple(float(v) for v in b) for b in self.bounds)
            if len(lo) != 3 or len(hi) != 3 or not all(a < b for a, b in zip(lo, hi)):
                raise ValueError(f"bounds must be ((lo x, y, z), (hi x, y, z)) with lo < hi, got {self.bounds}")
            object.__setattr__(self, "bounds", (lo, hi))  # tuples of floats keep the config hashable

    def make(
        self, points: np.ndarray, labels: np.ndarray | None = None, seed: int = 0
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """points [N, 3] world (labels [N] or None) -> (points [max_points, 3] float32, mask [max_points],
        labels [max_points] int32 or None): crop, voxel grid, seeded subsample (`pointcloud.scene_cloud`)."""
        return pointcloud.scene_cloud(points, self.max_points, self.voxel, labels, self.bounds, seed)
