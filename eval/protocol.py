"""The protocol every benchmark method implements: `Method`, the `Decision` it returns, its errors.

A method sees one camera observation and nothing else of the simulator:

    method.plan(points [P, 3] world, labels [P] int (object ids; < 0 = table), viewpoint [3], seed,
                avoid=[F, 4, 4]) -> Decision(pose [4, 4] | None, width, score, reason, timing, info)

`avoid` is the harness's memory, given alike to every method: the poses of the grasps that already
failed in this scene. A method does not plan one of them again: it leaves out its candidates that
`near_grasps` calls the same grasp (closing-region centres within 1 cm, hands within 15 deg). A
method whose `plan` takes no `avoid` runs without the memory.

A method that keeps state over the plans of one scene (the SuperGrasp planner keeps each unchanged
object's Stage-1 result) defines `begin_scene()`; the harness calls it before a scene's first plan, so
that a scene's outcomes never depend on the scenes run before it in the same process.

Diagnostic methods that read the simulator's ground truth (`oracle-topdown`) say so with
`uses_ground_truth = True`; the harness then hands them the scene with `set_scene(scene)` before each
plan. They validate the harness and never stand in for a method of the paper.

Method modules import this module only, never one another nor the registry (`eval.methods`).
"""

from __future__ import annotations

import dataclasses
from typing import Protocol, runtime_checkable

import numpy as np


@dataclasses.dataclass(frozen=True)
class Decision:
    """What a method chose for one observation.

    pose: [4, 4] gripper pose in the world (sgjax gripper frame), or None for "no grasp".
    width: gripper opening (m); the harness clips it to [0, max_opening].
    score: the method's own confidence (its scale is the method's).
    reason: why there is no grasp ("" when there is one).
    timing: {"stage1_s", "stage2_s", "total_s"} wall seconds of this plan call.
    info: free-form extras for the logs (counts, the method's idea of the target...); JSON-able.
    """

    pose: np.ndarray | None
    width: float
    score: float
    reason: str
    timing: dict
    info: dict = dataclasses.field(default_factory=dict)


@runtime_checkable
class Method(Protocol):
    name: str

    def plan(self, points: np.ndarray, labels: np.ndarray, viewpoint: np.ndarray, seed: int = 0,
             avoid: np.ndarray | None = None) -> Decision: ...


def near_grasps(poses, avoid, spec) -> np.ndarray:
    """Which of poses [K, 4, 4] are the same grasp as one in avoid [F, 4, 4] (or None) -> bool[K];
    host-side `sgjax.geometry.gripper.near_grasps` with its default tolerances."""
    from sgjax.geometry import gripper

    poses = np.asarray(poses, np.float64).reshape(-1, 4, 4)
    avoid = np.zeros((0, 4, 4)) if avoid is None else np.asarray(avoid, np.float64).reshape(-1, 4, 4)
    return gripper.near_grasps(poses, avoid, spec, xp=np)


def with_preset(method: str, preset: str) -> str:
    """A method's name under a planner preset (`sgjax.presets`): "supergrasp", "paper" -> "supergrasp@paper";
    the "default" preset keeps the plain name."""
    return method if preset == "default" else f"{method}@{preset}"


def split_preset(name: str) -> tuple[str, str]:
    """`with_preset` undone: "supergrasp@paper" -> ("supergrasp", "paper"); without one the preset is
    "default"."""
    base, at, preset = name.partition("@")
    return base, (preset if at else "default")


def check_gripper(name: str, planned, gripper) -> None:
    """ValueError when method `name`'s config plans for gripper `planned` while it is asked to plan for
    `gripper` (None: no gripper asked for): a method and the benchmark's simulated gripper are the same one."""
    if gripper is not None and planned != gripper:
        from sgjax.stage2.checkpoint import describe_gripper

        raise ValueError(f"method {name!r}: its config plans for gripper {describe_gripper(planned, gripper)} but the "
                         f"benchmark simulates gripper {describe_gripper(gripper, planned)} (DeclutterConfig.gripper): "
                         "give a config with that spec, or none")


class MethodUnavailable(RuntimeError):
    """The method is registered but cannot run here (not installed, or not written yet)."""
