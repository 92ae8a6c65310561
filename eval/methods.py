"""The registry of the decluttering benchmark's grasping methods: names -> factories.

`METHODS` maps each name to a `MethodInfo` (description, options it takes, whether it is available);
`make_method(name, **options)` builds one, raising `UnknownMethod` (listing the names),
`MethodUnavailable` (not installed / not available yet, with the reason) or `ValueError` (an option
the method does not take). The paper's baselines and ablations: `pointnetgpd`, `s1+pointnetgpd` and
`gpd+s2` (eval/baselines.py) and `contact-graspnet` (eval/contact_graspnet.py, out of process in its
own Python environment: unavailable until SGJAX_CGN_PYTHON names one).

Every method that plans with a gripper of its own takes the option `gripper` (a `GripperSpec`; None:
the default one), which the benchmark sets to its simulated gripper so that the two never differ
(`takes_gripper`; a `config` given with it that plans for another gripper is refused).

The registry sits above the methods: it imports each method module (lazily, in its factory), and the
methods import only the protocol they implement (`eval.protocol`: `Method`, `Decision`, errors).
"""

from __future__ import annotations

import dataclasses
import importlib.util
from collections.abc import Callable

from eval.protocol import Method, MethodUnavailable, check_gripper, split_preset

__all__ = ["METHODS", "MethodInfo", "MethodUnavailable", "UnknownMethod", "check_method", "make_method", "method_gripper",
           "method_names", "takes_gripper", "uses_database"]


class UnknownMethod(ValueError):
    """No method of that name is registered."""


@dataclasses.dataclass(frozen=True)
class MethodInfo:
    """A registry entry.

    factory: builds the method from its options; None for methods not available yet.
    options: option names `make_method` accepts for it.
    missing: () -> None when the method can run, else the reason it cannot.
    diagnostic: reads the simulator's ground truth (not a method of the paper).
    presets: takes a planner preset (`sgjax.presets`) as "name@preset".
    """

    name: str
    description: str
    factory: Callable[..., Method] | None
    options: tuple[str, ...] = ()
    missing: Callable[[], str | None] = lambda: None
    diagnostic: bool = False
    presets: bool = False

    def unavailable_reason(self) -> str | None:
        if self.factory is None:
            return "not available yet (registered as an extension point in eval/methods.py; no implementation yet)"
        return self.missing()


def _planner_missing() -> str | None:
    if importlib.util.find_spec("sgjax.planner") is None:
        return "not installed: the SuperGrasp planner (sgjax/planner.py) is missing"
    return None


def _for_gripper(name: str, config, gripper, default: Callable):
    """The method's config for `gripper`: `default(gripper)` when no config is given (gripper None: the
    default gripper's); a given config must plan for that gripper (its `spec`), else ValueError: the
    benchmark's simulated gripper and the method's are the same one (`eval.benchmark.run_benchmark`)."""
    if config is None:
        return default(gripper)
    check_gripper(name, config.spec, gripper)
    return config


def _gpd(config=None, gripper=None) -> Method:
    from eval.gpd import GPDMethod
    from sgjax.samplers.gpd import GPDConfig

    return GPDMethod(_for_gripper("gpd", config, gripper, lambda g: None if g is None else GPDConfig(spec=g)))


def _oracle(**options) -> Method:
    from eval.oracle import OracleTopDown

    return OracleTopDown(**options)


def _supergrasp(use_refinement: bool) -> Callable[..., Method]:
    def factory(model=None, small_db: bool = False, db=None, config=None, preset: str = "default",
                gripper=None) -> Method:
        from eval.supergrasp import PlannerMethod

        name = "supergrasp" if use_refinement else "supergrasp-norefine"
        return PlannerMethod(name, use_refinement, model=model, small_db=small_db, db=db, config=config, preset=preset,
                             gripper=gripper)

    return factory


_PLANNER_OPTIONS = ("model", "small_db", "db", "config", "gripper")


def _supergrasp_pointnetgpd(model=None, small_db: bool = False, db=None, config=None, gripper=None) -> Method:
    from eval.supergrasp import PlannerMethod
    from sgjax.stage2 import checkpoint, pointnetgpd

    spec = config.spec if config is not None else gripper  # the shipped PointNetGPD for it (None: the default)
    method = PlannerMethod("supergrasp-pointnetgpd", False, model=pointnetgpd.as_model(model, spec), small_db=small_db,
                           db=db, config=config, gripper=gripper)
    checkpoint.warn_gripper("PointNetGPD", model, checkpoint.POINTNETGPD_DEFAULT_DIR, method.config.spec)
    return method


def _supergrasp_stage1(small_db: bool = False, db=None, config=None, gripper=None) -> Method:
    from eval.supergrasp import PlannerMethod
    from sgjax.stage2.scorers import Stage1Order

    return PlannerMethod("supergrasp-stage1", False, model=Stage1Order(), small_db=small_db, db=db, config=config,
                         gripper=gripper)


def _baseline_config(gripper=None):
    """The baselines' settings with the workspace-cropped Stage-2 scene cloud that labelling, training and
    SuperGrasp use (the networks score the point density they were trained on), for `gripper` (None:
    the default one): the GPD-style generator's and Stage 1's spec."""
    from envs.scene import stage2_scene_cloud
    from eval.baselines import BaselineConfig

    config = BaselineConfig(scene_cloud=stage2_scene_cloud())
    return config if gripper is None else config.with_gripper(gripper)


def _pointnetgpd(generator: str) -> Callable[..., Method]:
    def factory(model=None, small_db: bool = False, db=None, config=None, gripper=None) -> Method:
        from eval.baselines import PointNetGPDMethod

        name = "pointnetgpd" if generator == "gpd" else "s1+pointnetgpd"
        config = _for_gripper(name, config, gripper, _baseline_config)
        return PointNetGPDMethod(generator, model=model, small_db=small_db, db=db, config=config)

    return factory


def _gpd_s2(model=None, config=None, gripper=None) -> Method:
    from eval.baselines import GPDStage2Method

    return GPDStage2Method(model=model, config=_for_gripper("gpd+s2", config, gripper, _baseline_config))


def _cgn_config(gripper=None):
    """Contact-GraspNet's settings: the workspace crop on a 3 mm grid, as SuperGrasp's cloud (measured
    best, docs/benchmark.md); its grasps are placed for `gripper` (None: the default one)."""
    import dataclasses

    from envs.scene import stage2_scene_cloud
    from eval.contact_graspnet import CGNConfig

    cloud = stage2_scene_cloud()
    config = CGNConfig(voxel=cloud.voxel, scene_bounds=cloud.bounds)
    return config if gripper is None else dataclasses.replace(config, spec=gripper)


def _contact_graspnet(config=None, gripper=None) -> Method:
    from eval.contact_graspnet import ContactGraspNetMethod

    return ContactGraspNetMethod(_for_gripper("contact-graspnet", config, gripper, _cgn_config))


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
            presets=True,
        ),
        MethodInfo(
            "supergrasp-norefine",
            "SuperGrasp without the refinement branch (paper: Ours w/o RNet)",
            _supergrasp(False),
            _PLANNER_OPTIONS,
            _planner_missing,
            presets=True,
        ),
        MethodInfo(
            "supergrasp-pointnetgpd",
            "SuperGrasp's planner (Stage 1, every addition) with PointNetGPD in place of E-RNet (network ablation)",
            _supergrasp_pointnetgpd,
            _PLANNER_OPTIONS,
            _planner_missing,
        ),
        MethodInfo(
            "supergrasp-stage1",
            "SuperGrasp without Stage 2 (w/o E-RNet): the planner executes Stage 1's order, the best-matched first",
            _supergrasp_stage1,
            ("small_db", "db", "config", "gripper"),
            _planner_missing,
        ),
        MethodInfo("gpd", "GPD-style geometric baseline: antipodal sampling, ranked by an antipodal score", _gpd,
                   ("config", "gripper")),
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
            ("model", "config", "gripper"),
        ),
        MethodInfo(
            "s1+pointnetgpd",
            "Ours (S1) + PointNetGPD (paper ablation): Stage-1 candidates scored by PointNetGPD",
            _pointnetgpd("stage1"),
            ("model", "small_db", "db", "config", "gripper"),
        ),
        MethodInfo(
            "gpd+s2",
            "GPD-style candidates + Ours (S2) (paper ablation: PointNetGPD + Ours (S2)): E-RNet and the decision policy",
            _gpd_s2,
            ("model", "config", "gripper"),
            _planner_missing,
        ),
        MethodInfo(
            "contact-graspnet",
            "Contact-GraspNet (paper baseline), run out of process in its own environment ($SGJAX_CGN_PYTHON)",
            _contact_graspnet,
            ("config", "gripper"),
            _cgn_missing,
        ),
    )
}


def takes_gripper(name: str) -> bool:
    """Whether method `name` ("method" or "method@preset") plans with a gripper of its own: it takes the
    `gripper` option, which `eval.benchmark.run_benchmark` sets to the simulated gripper
    (`DeclutterConfig.gripper`). The others (oracle-topdown) read the scene's gripper."""
    info = METHODS.get(split_preset(name)[0])
    return info is not None and "gripper" in info.options


def uses_database(name: str) -> bool:
    """Whether method `name` runs Stage 1 on a primitive database (it takes `small_db`), whose gripper is
    the method's: a gripper other than the default one builds its own on first use."""
    info = METHODS.get(split_preset(name)[0])
    return info is not None and "small_db" in info.options


def method_gripper(method: Method):
    """The gripper a built method plans with (its config's `spec`), None when it has none of its own
    (e.g. oracle-topdown, which reads the scene's)."""
    from sgjax.geometry.gripper import GripperSpec

    spec = getattr(getattr(method, "config", None), "spec", None)
    return spec if isinstance(spec, GripperSpec) else None


def method_names(available_only: bool = False) -> list[str]:
    """Registered names in registry order (only the ones that can run here if `available_only`)."""
    return [n for n, info in METHODS.items() if not available_only or info.unavailable_reason() is None]


def check_method(name: str, **options) -> MethodInfo:
    """The registry entry of `name` ("method" or "method@preset" for the planner's methods) if it can run
    with `options` (None / False values are ignored).

    Raises UnknownMethod, MethodUnavailable or ValueError (an option the method does not take, a preset
    of a method without presets, an unknown preset).
    """
    name, preset = split_preset(name)
    info = METHODS.get(name)
    if info is None:
        raise UnknownMethod(f"unknown method {name!r}: expected one of {', '.join(METHODS)}")
    if preset != "default":
        if not info.presets:
            takers = ", ".join(n for n, i in METHODS.items() if i.presets)
            raise ValueError(f"method {name!r} takes no planner preset (only {takers} do)")
        from sgjax import presets

        presets.get(preset)  # an unknown name raises, listing the known ones
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
    given = {k: v for k, v in options.items() if v is not None and v is not False}
    _, preset = split_preset(name)
    return info.factory(**given, preset=preset) if preset != "default" else info.factory(**given)
