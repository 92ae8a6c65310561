"""Grasping methods of the decluttering benchmark: the `Method` protocol, `Decision`, and the registry.

A method sees one camera observation and nothing else of the simulator:

    method.plan(points [P, 3] world, labels [P] int (object ids; < 0 = table), viewpoint [3], seed,
                avoid=[F, 4, 4]) -> Decision(pose [4, 4] | None, width, score, reason, timing, info)

`avoid` is the harness's memory, given alike to every method: the poses of the grasps that already
failed in this scene. A method does not plan one of them again: it leaves out its candidates that
`near_grasps` calls the same grasp (closing-region centres within 1 cm, hands within 15 deg). A
method whose `plan` takes no `avoid` runs without the memory.

Diagnostic methods that read the simulator's ground truth (`oracle-topdown`) say so with
`uses_ground_truth = True`; the harness then hands them the scene with `set_scene(scene)` before each
plan. They validate the harness and never stand in for a method of the paper.

`METHODS` maps each name to a `MethodInfo` (description, options it takes, whether it is available);
`make_method(name, **options)` builds one, raising `UnknownMethod` (listing the names),
`MethodUnavailable` (not installed / not available yet, with the reason) or `ValueError` (an option
the method does not take). The paper's baselines and ablations: `pointnetgpd`, `s1+pointnetgpd` and
`gpd+s2` (eval/baselines.py) and `contact-graspnet` (eval/contact_graspnet.py, out of process in its
own Python environment: unavailable until SGJAX_CGN_PYTHON names one).
"""

from __future__ import annotations

import dataclasses
import importlib.util
from collections.abc import Callable
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


class UnknownMethod(ValueError):
    """No method of that name is registered."""


class MethodUnavailable(RuntimeError):
    """The method is registered but cannot run here (not installed, or not written yet)."""


@dataclasses.dataclass(frozen=True)
class MethodInfo:
    """A registry entry.

    factory: builds the method from its options; None for methods not available yet.
    options: option names `make_method` accepts for it.
    missing: () -> None when the method can run, else the reason it cannot.
    diagnostic: reads the simulator's ground truth (not a method of the paper).
    """

    name: str
    description: str
    factory: Callable[..., Method] | None
    options: tuple[str, ...] = ()
    missing: Callable[[], str | None] = lambda: None
    diagnostic: bool = False

    def unavailable_reason(self) -> str | None:
        if self.factory is None:
            return "not available yet (registered as an extension point in eval/methods.py; no implementation yet)"
        return self.missing()


def _planner_missing() -> str | None:
    if importlib.util.find_spec("sgjax.planner") is None:
        return "not installed: the SuperGrasp planner (sgjax/planner.py) is missing"
    return None


def _gpd(config=None) -> Method:
    from eval.gpd import GPDMethod

    return GPDMethod(config)


def _oracle(**options) -> Method:
    from eval.oracle import OracleTopDown

    return OracleTopDown(**options)


def _supergrasp(use_refinement: bool) -> Callable[..., Method]:
    def factory(model=None, small_db: bool = False, db=None, config=None) -> Method:
        from eval.supergrasp import PlannerMethod

        name = "supergrasp" if use_refinement else "supergrasp-norefine"
        return PlannerMethod(name, use_refinement, model=model, small_db=small_db, db=db, config=config)

    return factory


_PLANNER_OPTIONS = ("model", "small_db", "db", "config")


def _pointnetgpd(generator: str) -> Callable[..., Method]:
    def factory(model=None, small_db: bool = False, db=None, config=None) -> Method:
        from eval.baselines import PointNetGPDMethod

        return PointNetGPDMethod(generator, model=model, small_db=small_db, db=db, config=config)

    return factory


def _gpd_s2(model=None, config=None) -> Method:
    from eval.baselines import GPDStage2Method

    return GPDStage2Method(model=model, config=config)


def _contact_graspnet(config=None) -> Method:
    from eval.contact_graspnet import CGNConfig, ContactGraspNetMethod

    if config is None:  # the benchmark's workspace, cropped as for SuperGrasp's scene cloud
        from envs.scene import stage2_scene_cloud

        cloud = stage2_scene_cloud()
        config = CGNConfig(voxel=cloud.voxel, scene_bounds=cloud.bounds)
    return ContactGraspNetMethod(config)


def _cgn_missing() -> str | None:
    from eval.contact_graspnet import missing

    return missing()

METHODS: dict[str, MethodInfo] = {
    info.name: info
    for info in (
        MethodInfo(
            "supergrasp",
            "SuperGrasp: Stage-1 similarity matching + E-RNet evaluation and refinement",
            _supergrasp(True),
            _PLANNER_OPTIONS,
            _planner_missing,
        ),
        MethodInfo(
            "supergrasp-norefine",
            "SuperGrasp without the refinement branch (paper: Ours w/o RNet)",
            _supergrasp(False),
            _PLANNER_OPTIONS,
            _planner_missing,
        ),
        MethodInfo("gpd", "GPD-style geometric baseline: antipodal sampling, ranked by an antipodal score", _gpd, ("config",)),
        MethodInfo(
            "oracle-topdown",
            "diagnostic: top-down grasps from the simulator's ground-truth object poses",
            _oracle,
            ("depth", "order"),
            diagnostic=True,
        ),
        MethodInfo(
            "pointnetgpd",
            "PointNetGPD (paper baseline): GPD-style candidates scored by a PointNet over the closing region",
            _pointnetgpd("gpd"),
            ("model", "config"),
        ),
        MethodInfo(
            "s1+pointnetgpd",
            "Ours (S1) + PointNetGPD (paper ablation): Stage-1 candidates scored by PointNetGPD",
            _pointnetgpd("stage1"),
            ("model", "small_db", "db", "config"),
        ),
        MethodInfo(
            "gpd+s2",
            "GPD-style candidates + Ours (S2) (paper ablation: PointNetGPD + Ours (S2)): E-RNet and the decision policy",
            _gpd_s2,
            ("model", "config"),
            _planner_missing,
        ),
        MethodInfo(
            "contact-graspnet",
            "Contact-GraspNet (paper baseline), run out of process in its own environment ($SGJAX_CGN_PYTHON)",
            _contact_graspnet,
            ("config",),
            _cgn_missing,
        ),
    )
}


def method_names(available_only: bool = False) -> list[str]:
    """Registered names in registry order (only the ones that can run here if `available_only`)."""
    return [n for n, info in METHODS.items() if not available_only or info.unavailable_reason() is None]


def check_method(name: str, **options) -> MethodInfo:
    """The registry entry of `name` if it can run with `options` (None / False values are ignored).

    Raises UnknownMethod, MethodUnavailable or ValueError (an option the method does not take).
    """
    info = METHODS.get(name)
    if info is None:
        raise UnknownMethod(f"unknown method {name!r}: expected one of {', '.join(METHODS)}")
    reason = info.unavailable_reason()
    if reason is not None:
        raise MethodUnavailable(f"method {name!r} cannot run: {reason}")
    extra = sorted(k for k, v in options.items() if v is not None and v is not False and k not in info.options)
    if extra:
        takes = ", ".join(info.options) or "no options"
        raise ValueError(f"method {name!r} does not take option(s) {', '.join(extra)} (it takes: {takes})")
    return info


def make_method(name: str, **options) -> Method:
    """Build method `name` with `options` (see `METHODS[name].options`); options set to None or False
    are dropped. Raises as `check_method`."""
    info = check_method(name, **options)
    return info.factory(**{k: v for k, v in options.items() if v is not None and v is not False})
