"""The geometry both stages stand on: rotations, superquadrics, point clouds, the gripper, synthetic data.

`rotations` (SO(3) helpers), `superquadric` (the primitive shape, paper Sec. III), `pointcloud`
(loading, padding, scene clouds), `gripper` (`GripperSpec`, frames, closing / enlarged regions, boxes;
paper Fig. 5), `synthetic` (sampled superquadric clouds for tests and benchmarks). Imports only
`sgjax.utils`.
"""
