"""Named planner configurations: one name, one `PlannerConfig` (a registry in the style of MuJoCo
Playground's configs).

    config = sgjax.presets.get("paper")          # the paper's plain SuperGrasp
    planner = sgjax.Planner(config=config)
    sgjax.presets.names()                        # ("default", "paper")

`sgjax declutter --method supergrasp --preset NAME` runs one on the benchmark (which adds its workspace
crop to the Stage-2 scene cloud); `--method supergrasp-norefine` is the same preset without the
refinement branch (the paper's "w/o RNet" ablation). Each README row names the preset that made it.
`get(name, gripper=spec)` (or `with_gripper(config, spec)`) is the preset for another gripper
(`sgjax.geometry.gripper_files.load_gripper`; `--gripper` on the command line).
"""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING, Callable

if TYPE_CHECKING:
    from sgjax.geometry.gripper import GripperSpec
    from sgjax.planner import PlannerConfig

# The planner (and JAX with it) is imported when a preset is built, not when its name is looked up:
# the command line lists the names without that cost.


def default() -> PlannerConfig:
    """Today's SuperGrasp: the paper's pipeline plus this project's additions (the extra Stage-1 filters,
    grasps on the fitted superquadric, the neighbours' fits as obstacles, the robust choice, refinements
    re-scored at their pose, a second plan with looser filters). Equal to `PlannerConfig()`."""
    from sgjax.planner import PlannerConfig

    return PlannerConfig()


def paper() -> PlannerConfig:
    """The paper's plain SuperGrasp (Sec. IV): filters (i)-(v) as the paper reads them (no camera-ray
    shadows, no obstacle margin, hidden contacts not judged), the transferred template grasps only, the
    highest evaluation executed, else the best refinement by the refine head alone, one plan."""
    from sgjax.planner import PlannerConfig
    from sgjax.stage1.filters import FilterConfig
    from sgjax.stage1.pipeline import Stage1Config

    paper_filter = FilterConfig(shadow_depth=0.0, obstacle_margin=0.0, hidden_contacts="accept")
    return PlannerConfig(
        stage1=Stage1Config(filter=paper_filter),
        refine_rescore=0,
        fallback_filter=None,
        fit_grasps=None,
        neighbour_fits=None,
        robust=None,
    )


PRESETS: dict[str, Callable[[], PlannerConfig]] = {"default": default, "paper": paper}


def names() -> tuple[str, ...]:
    """The registered preset names, "default" first."""
    return tuple(PRESETS)


def get(name: str, gripper: GripperSpec | None = None, **changes) -> PlannerConfig:
    """The `PlannerConfig` of preset `name`, with any top-level fields replaced by `changes` (e.g.
    `use_refinement=False`) and planning for `gripper` (None: the preset's, the default gripper; see
    `with_gripper`). Unknown names raise ValueError listing the known ones."""
    if name not in PRESETS:
        raise ValueError(f"unknown planner preset {name!r}; known: {', '.join(PRESETS)}")
    config = dataclasses.replace(PRESETS[name](), **changes)
    return config if gripper is None else with_gripper(config, gripper)


def with_gripper(config: PlannerConfig, gripper: GripperSpec) -> PlannerConfig:
    """`config` planning for `gripper`: the planner's gripper is its Stage-1 config's spec
    (`PlannerConfig.spec`, also Stage 2's crops and the refinements); nothing else holds one. The same
    config when `gripper` is already its spec."""
    if config.spec == gripper:
        return config
    return dataclasses.replace(config, stage1=dataclasses.replace(config.stage1, spec=gripper))
