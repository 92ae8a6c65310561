"""sgjax: SuperGrasp (single-view grasping via superquadric similarity matching, evaluation and refinement) in JAX.

The library layer: pure JAX/NumPy math, no simulator. See README.md for the command line.
"""

from sgjax.ems import EMSConfig, FitResult, fit_superquadric, fit_superquadrics
from sgjax.pointcloud import CloudError, describe_status, load_cloud, pad_clouds
from sgjax.superquadric import Superquadric

__version__ = "0.1.0"

__all__ = [
    "CloudError",
    "EMSConfig",
    "FitResult",
    "Superquadric",
    "describe_status",
    "fit_superquadric",
    "fit_superquadrics",
    "load_cloud",
    "pad_clouds",
]
