"""Stage 1 of SuperGrasp: superquadric similarity matching (paper Sec. IV-A, IV-B).

`ems` (superquadric recovery from a partial cloud), `primitives` (the primitive shapes and their
template grasps), `database` (the primitive database), `matching` (similarity matching and grasp
transfer), `filters` (the coarse filters (i)-(iv)), `pipeline` (`Stage1`: cloud -> candidate grasps).
Imports `sgjax.geometry` and `sgjax.utils`, never Stage 2.
"""
