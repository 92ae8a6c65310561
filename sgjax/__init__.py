"""sgjax: SuperGrasp (single-view grasping via superquadric similarity matching, evaluation and refinement) in JAX.

The library layer: pure JAX/NumPy math, no simulator. See README.md for the command line. This module
is the one public door: a notebook imports from `sgjax` what it needs. The subpackages follow the paper:

    sgjax.utils      atomic files, the cache directory
    sgjax.geometry   rotations, superquadrics, point clouds, the gripper, synthetic clouds
    sgjax.stage1     EMS fitting, primitives, the primitive database, matching, coarse filters, Stage1
    sgjax.stage2     PointNet++, E-RNet, PointNetGPD, region crops, checkpoints
    sgjax.policy     the decision policy: pure functions over scored candidates
    sgjax.planner    Stage 1 -> Stage 2 -> one grasp (`Planner`, `plan`)
    sgjax.presets    named planner configurations (`sgjax.presets.get("paper")`)
"""

from sgjax.geometry.gripper import GripperSpec
from sgjax.geometry.pointcloud import CloudError, describe_status, load_cloud, pad_clouds
from sgjax.geometry.superquadric import Superquadric
from sgjax.stage1.ems import EMSConfig, FitResult, fit_superquadric, fit_superquadrics

__version__ = "0.1.0"

# Stage 1, Stage 2 and the planner pull in Flax, trimesh and the primitive database: import them on
# first use only, so `import sgjax` stays as cheap as the fitting it offers eagerly.
_LAZY = {
    "Stage1": "sgjax.stage1.pipeline",
    "Stage1Config": "sgjax.stage1.pipeline",
    "Candidates": "sgjax.stage1.pipeline",
    "generate_candidates": "sgjax.stage1.pipeline",
    "DBConfig": "sgjax.stage1.database",
    "PrimitiveDB": "sgjax.stage1.database",
    "load_database": "sgjax.stage1.database",
    "build_database": "sgjax.stage1.database",
    "ERNet": "sgjax.stage2.ernet",
    "ERNetConfig": "sgjax.stage2.ernet",
    "Planner": "sgjax.planner",
    "PlannerConfig": "sgjax.planner",
    "plan": "sgjax.planner",
    "load_default_model": "sgjax.stage2.ernet",  # the shipped E-RNet
}


def __getattr__(name: str):
    if name in _LAZY:
        import importlib

        value = getattr(importlib.import_module(_LAZY[name]), name)
        globals()[name] = value  # later look-ups skip __getattr__
        return value
    raise AttributeError(f"module 'sgjax' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))


__all__ = [
    "Candidates",
    "CloudError",
    "DBConfig",
    "EMSConfig",
    "ERNet",
    "ERNetConfig",
    "FitResult",
    "GripperSpec",
    "Planner",
    "PlannerConfig",
    "PrimitiveDB",
    "Stage1",
    "Stage1Config",
    "Superquadric",
    "build_database",
    "describe_status",
    "fit_superquadric",
    "fit_superquadrics",
    "generate_candidates",
    "load_cloud",
    "load_database",
    "load_default_model",
    "pad_clouds",
    "plan",
]
