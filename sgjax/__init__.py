"""sgjax: SuperGrasp (single-view grasping via superquadric similarity matching, evaluation and refinement) in JAX.

The library layer: pure JAX/NumPy math, no simulator. See README.md for the command line.
"""

from sgjax.ems import EMSConfig, FitResult, fit_superquadric, fit_superquadrics
from sgjax.pointcloud import CloudError, describe_status, load_cloud, pad_clouds
from sgjax.superquadric import Superquadric

__version__ = "0.1.0"

# The planner pulls in Flax and the primitive database: import it on first use only.
_LAZY = {"plan": "sgjax.planner", "Planner": "sgjax.planner", "PlannerConfig": "sgjax.planner",
         "generate_candidates": "sgjax.stage1", "Stage1": "sgjax.stage1"}


def __getattr__(name: str):
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'sgjax' has no attribute {name!r}")


__all__ = [
    "CloudError",
    "Planner",
    "PlannerConfig",
    "Stage1",
    "EMSConfig",
    "FitResult",
    "Superquadric",
    "describe_status",
    "fit_superquadric",
    "fit_superquadrics",
    "generate_candidates",
    "load_cloud",
    "pad_clouds",
    "plan",
]
