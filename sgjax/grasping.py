"""Grasps for a real frame: the planner run on a `sgjax.perception.Frame`, grasps back in its frame.

    frame = Frame.from_depth("depth.png", "intrinsics.json")
    result = plan_frame(Planner(), frame, all_objects=True, top=3)
    for g in result.grasps:            # best first
        g.object, g.pose, g.width, g.score, g.kind, g.center, g.approach

The planner was built for a world whose z is up and whose table is z = 0 (the simulator's). A frame may
be the camera's (z forward), so the planner runs in the frame's table frame (`Frame.table_frame`: z the
table's normal, the table z = 0, filter (v)'s support plane) and every pose is mapped back.

Gripper frame of a pose (`sgjax.geometry.gripper`): z approaches (from the palm towards the object),
x closes (the fingers move along +-x), y = z x x; the origin is the centre of the closing region's
palm-side face, so the tool-centre point between the fingertips' middles is `center` = origin +
finger_length / 2 along z. A robot whose tool frame sits elsewhere composes its own offset.
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np

from sgjax.geometry.gripper import GripperSpec, closing_centre, near_grasps
from sgjax.perception.camera import to_world
from sgjax.perception.frame import Frame
from sgjax.planner import Plan, Planner

TABLE_PLANE = (0.0, 0.0, 1.0, 0.0)  # the table in its own frame
SCENE_MARGIN = 0.1  # metres of the frame kept around the objects for Stage 2


@dataclasses.dataclass(frozen=True, eq=False)
class Grasp:
    """One grasp in the frame's coordinates: object (its label), pose [4, 4] (gripper frame -> frame),
    width (m), score (the planner's), kind "evaluated" | "refined" (the planner's choice for the object)
    or "alternative" (the object's next candidates by E-RNet's evaluation score), center [3] (the
    closing region's centre, the tool-centre point), approach [3] (unit vector, the pose's z)."""

    object: int
    pose: np.ndarray
    width: float
    score: float
    kind: str
    center: np.ndarray
    approach: np.ndarray

    def to_dict(self) -> dict:
        r = lambda a: np.round(np.asarray(a, np.float64), 6).tolist()
        return {"object": int(self.object), "pose": r(self.pose), "width": round(float(self.width), 6),
                "score": round(float(self.score), 6), "kind": self.kind, "center": r(self.center),
                "approach": r(self.approach)}


@dataclasses.dataclass(frozen=True, eq=False)
class FramePlan:
    """grasps: best first (all objects' choices by score, then each object's alternatives by score);
    plans: the planner's `Plan` per planned object label (one entry, None, without `all_objects`), in
    the table frame; reasons: why an object got no grasp, by label ("scene" without `all_objects`);
    timing: wall seconds; frame: the frame whose labels the grasps' objects are (the one planned on, or
    the hypothesis of it that gave the grasps, `Frame.hypotheses`)."""

    grasps: list[Grasp]
    plans: dict
    reasons: dict
    timing: dict
    frame: Frame


def _grasp(label: int, pose_table: np.ndarray, width: float, score: float, kind: str, to_frame: np.ndarray,
           spec: GripperSpec) -> Grasp:
    pose = to_frame @ pose_table
    return Grasp(int(label), pose, float(width), float(score), kind, closing_centre(pose, spec, np), pose[:3, 2].copy())


def _alternatives(plan: Plan, chosen: np.ndarray, count: int, spec: GripperSpec) -> list[tuple]:
    """Up to `count` more (pose, width, score) of the plan's scored valid candidates on its target, by evaluation
    score, none the same grasp (`near_grasps`) as one already listed (chosen [1, 4, 4] first)."""
    scores = plan.scores
    if count <= 0 or not scores or not len(scores.get("eval_prob", ())):
        return []
    out, listed = [], [chosen]
    for row in np.argsort(-scores["eval_prob"], kind="stable"):
        if not scores["valid"][row] or row == plan.candidate_index or scores["target"][row] != plan.target:
            continue
        cands = plan.candidates[int(scores["object"][row])]
        k = int(scores["object_candidate"][row])
        pose = np.asarray(cands.poses[k], np.float64)
        if near_grasps(pose[None], np.concatenate(listed), spec, xp=np)[0]:
            continue
        out.append((pose, float(cands.widths[k]), float(scores["eval_prob"][row])))
        listed.append(pose[None])
        if len(out) == count:
            break
    return out


def plan_frame(planner: Planner, frame: Frame, all_objects: bool = False, top: int = 1, seed: int = 0,
               avoid=None) -> FramePlan:
    """Grasps for `frame`: the planner's best grasp over the scene (all_objects False) or for every object
    (True, one plan per object, the other objects its obstacles), each followed by up to top - 1
    alternatives on the same object. avoid [F, 4, 4] (frame coordinates) or None: grasps not to plan
    again (e.g. ones that failed). -> FramePlan (its grasps in the frame's coordinates).

    A clustered frame is planned on its hypotheses in turn (`Frame.hypotheses`; with `all_objects` the
    first only): the parted one (touching objects merged into one cluster cut apart where the finer crease
    test finds them), then, while a plan finds no grasp, the clusters as segmented, the joined one
    (crease-cut fragments joined to their neighbour), the finer one (a pile cut into its objects), as the
    benchmark's harness does; FramePlan.frame says which labels the grasps refer to."""
    if top < 1:
        raise ValueError(f"top must be >= 1, got {top}")
    hypotheses = frame.hypotheses()
    result = _plan_frame(planner, next(hypotheses), all_objects, top, seed, avoid)
    if all_objects or result.grasps:
        return result
    spent, reasons = result.timing["plan_s"], dict(result.reasons)
    for other in hypotheses:
        again = _plan_frame(planner, other, all_objects, top, seed, avoid)
        spent += again.timing["plan_s"]
        if again.grasps:
            return dataclasses.replace(again, timing={"plan_s": spent})
        reasons = {key: f"{why}; on the {other.segmentation}: {again.reasons.get(key, 'no grasp')}"
                   for key, why in reasons.items()}
    return dataclasses.replace(result, reasons=reasons, timing={"plan_s": spent})


def _plan_frame(planner: Planner, frame: Frame, all_objects: bool, top: int, seed: int, avoid) -> FramePlan:
    start = time.perf_counter()
    to_frame = frame.table_frame()
    to_table = np.linalg.inv(to_frame)
    points, labels = frame.table_and_objects()  # as the benchmark hands a frame to a method
    points = to_world(points, to_table)
    view = to_world(frame.camera_position[None], to_table)[0]
    if avoid is not None:
        avoid = to_table @ np.asarray(avoid, np.float64).reshape(-1, 4, 4)
    config = planner.config
    spec = config.spec
    changes = {"support_plane": TABLE_PLANE}
    if config.scene_cloud.bounds is None and (labels > 0).any():
        # E-RNet's scene cloud around the objects (as labelling crops it to the workspace), so that a
        # wide frame does not thin out the points its crops were trained on.
        lo, hi = points[labels > 0].min(0) - SCENE_MARGIN, points[labels > 0].max(0) + SCENE_MARGIN
        bounds = ((lo[0], lo[1], -0.01), (hi[0], hi[1], max(hi[2], 1.0)))
        changes["scene_cloud"] = dataclasses.replace(config.scene_cloud, bounds=bounds)
    planner.config = dataclasses.replace(config, **changes)
    try:
        if all_objects:
            plans = {label: planner.plan_masked(points, labels == label, view, seed, avoid) for label in frame.object_ids}
        else:
            plans = {None: planner.plan(points, labels, view, seed, avoid)}
    finally:
        planner.config = config
    chosen, others, reasons = [], [], {}
    for label, plan in plans.items():
        target = plan.target if label is None else label
        if plan.pose is None:
            reasons[label if label is not None else "scene"] = plan.reason
            continue
        chosen.append(_grasp(target, plan.pose, plan.width, plan.score, plan.kind, to_frame, spec))
        others += [_grasp(target, p, w, s, "alternative", to_frame, spec)
                   for p, w, s in _alternatives(plan, np.asarray(plan.pose)[None], top - 1, spec)]
    grasps = sorted(chosen, key=lambda g: -g.score) + sorted(others, key=lambda g: -g.score)
    timing = {"plan_s": time.perf_counter() - start}
    return FramePlan(grasps, plans, reasons, timing, frame)
