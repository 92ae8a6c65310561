"""Stage 2 of SuperGrasp: evaluation and refinement of the candidates (paper Sec. IV-C, IV-D).

`pointnet2` (the PointNet++ backbone), `ernet` (E-RNet), `pointnetgpd` (the PointNetGPD baseline's
network). Imports `sgjax.geometry` and `sgjax.utils`, never Stage 1.
"""
