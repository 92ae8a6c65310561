"""MuJoCo side of sgjax: objects, tabletop scenes, the depth camera and batched grasp trials.

Imports `sgjax` (e.g. the gripper spec); never imported by it.
"""
