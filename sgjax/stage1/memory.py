"""Stage 1 across the plans of one scene: an object whose cloud has not changed keeps its candidates.

In a decluttering episode most objects are untouched by each grasp, yet every plan would fit, match,
transfer and filter all of them again. A `Stage1Memory`, handed by the caller to `Planner.plan` for
the plans of one scene, keeps each object's Stage-1 result with the cloud it was computed from; when
the same label comes back with the same cloud (`sgjax.geometry.pointcloud.same_cloud` within
`PlannerConfig.reuse_tolerance`), the planner only tests those candidates against today's obstacles
(`Stage1.rescene`: filter (iv), since neighbours come and go) instead of running Stage 1 again.

The caller owns the memory and starts a new one (or calls `forget`) for a new scene, like the memory of
failed grasps (`avoid`): plans with the same memory, seeds and observations give the same grasps.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Hashable

import numpy as np

from sgjax.geometry.pointcloud import same_cloud
from sgjax.stage1.pipeline import Candidates


@dataclasses.dataclass
class Stage1Memory:
    """Stage-1 results by (Stage-1 setup, object label), each with the cloud it came from.

    reused, computed: how many object results `recall` handed back / were stored since the last
    `forget` (what a user reads to see how much the memory saved)."""

    entries: dict = dataclasses.field(default_factory=dict)
    reused: int = 0
    computed: int = 0

    def recall(self, setup: Hashable, label: int, cloud: np.ndarray, tolerance: float) -> Candidates | None:
        """The stored result of `label` under `setup` when its cloud [N, 3] is the same as now within
        tolerance (metres), else None."""
        entry = self.entries.get((setup, int(label)))
        if entry is None or not same_cloud(entry[0], cloud, tolerance):
            return None
        self.reused += 1
        return entry[1]

    def remember(self, setup: Hashable, label: int, cloud: np.ndarray, candidates: Candidates) -> None:
        """Store a fresh Stage-1 result of `label` (one without `before_scene`, e.g. of a bad cloud, is not kept)."""
        self.computed += 1
        if candidates.before_scene is None:
            self.entries.pop((setup, int(label)), None)
        else:
            self.entries[(setup, int(label))] = (np.array(cloud, np.float64), candidates)

    def forget(self) -> None:
        """Drop everything (a new scene)."""
        self.entries.clear()
        self.reused = self.computed = 0
