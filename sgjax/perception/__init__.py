"""A real camera's frame in: depth image and calibration -> a point cloud, the table plane.

    K = read_intrinsics("camera.json")                  # JSON {"K": 3x3} | {"fx","fy","cx","cy"}, ROS YAML, 3x3 .npy
    depth = read_depth("depth.png", depth_scale=1000)   # 16-bit PNG (units per metre) or float .npy/.npz (metres)
    points, pixels = back_project(depth, K)             # camera frame (OpenCV: x right, y down, z forward)
    table = fit_table(points, viewpoint=(0, 0, 0))      # RANSAC plane, normal towards the camera
    frame = Frame.from_depth(depth, K, masks=None)      # all of it: points, object labels (clusters), table

Without extrinsics everything stays in the camera frame and the table plane defines "up"; with a
camera-to-world `read_extrinsics(...)` matrix the points go to the world frame (`to_world`).
Plain NumPy over arrays; files are read with Pillow and PyYAML.
"""

from sgjax.perception.camera import Intrinsics, read_extrinsics, read_intrinsics, to_world
from sgjax.perception.depth import back_project, read_depth
from sgjax.perception.frame import Frame, PerceptionError, read_image
from sgjax.perception.segment import OTHER, TABLE, SegmentConfig, segment_objects
from sgjax.perception.table import TablePlane, fit_table

__all__ = ["OTHER", "TABLE", "Frame", "Intrinsics", "PerceptionError", "SegmentConfig", "TablePlane", "back_project",
           "fit_table", "read_depth", "read_extrinsics", "read_image", "read_intrinsics", "segment_objects", "to_world"]
