"""Which Stage-2 network scores the planner's candidates: E-RNet, PointNetGPD in its place, or none
(ablations).

The planner is written against one contract, `score(graphdef, state, scene [N, 3], poses [M, 4, 4],
widths [M], scene_mask [N], *, spec, key) -> ernet.ERNetScores`. E-RNet fills it as it is; PointNetGPD,
which has no refinement head, gives its stable-grasp probability as the evaluation and refinement
probabilities of 0, so a planner with `use_refinement=False` runs every step of its policy (robust
choice, fallbacks, memory) on PointNetGPD's judgement: the network compared with the network, not with
the planner around it (`eval`'s `supergrasp-pointnetgpd`). `Stage1Order` is no network at all: every
candidate with scene points between its fingers passes with 1, so the planner executes Stage 1's own
order, the first object's best-matched candidate first (`supergrasp-stage1`, the ablation "w/o E-RNet").
"""

from __future__ import annotations

import functools
from collections.abc import Callable

import jax
import jax.numpy as jnp
from flax import nnx

from sgjax.geometry.gripper import GripperSpec
from sgjax.stage2 import ernet, pointnetgpd
from sgjax.stage2.crops import crop_closing_regions

Scorer = Callable[..., ernet.ERNetScores]


@functools.partial(jax.jit, static_argnames=("graphdef", "spec"))
def pointnetgpd_score(graphdef: nnx.GraphDef, state: nnx.State, scene: jax.Array, poses: jax.Array, widths: jax.Array,
                      scene_mask: jax.Array | None = None, *, spec: GripperSpec = ernet.DEFAULT_SPEC,
                      key: jax.Array | None = None) -> ernet.ERNetScores:
    """PointNetGPD in E-RNet's contract: eval_prob [M] = its probability, refine_prob [M, K] = 0."""
    s = pointnetgpd.score(graphdef, state, scene, poses, widths, scene_mask, spec=spec, key=key)
    return ernet.ERNetScores(s.prob, jnp.zeros((s.prob.shape[0], spec.num_refinements), s.prob.dtype), s.valid, s.count)


STAGE1_ORDER = "none (Stage 1's order)"  # what the planner names as its checkpoint with `Stage1Order`


class Stage1Order(nnx.Module):
    """No Stage-2 network: a stand-in without parameters that the planner holds in the network's place."""

    config = "stage1-order"  # the planner's compiled Stage 2 is keyed by the network's class and config


@functools.partial(jax.jit, static_argnames=("graphdef", "spec"))
def stage1_order_score(graphdef: nnx.GraphDef, state: nnx.State, scene: jax.Array, poses: jax.Array, widths: jax.Array,
                       scene_mask: jax.Array | None = None, *, spec: GripperSpec = ernet.DEFAULT_SPEC,
                       key: jax.Array | None = None) -> ernet.ERNetScores:
    """1 for every valid candidate with a scene point between its fingers, else 0; no refinements."""
    c = ernet.scene_candidates(scene, poses, widths, scene_mask, spec, key)
    region = crop_closing_regions(c.scene, c.poses, c.widths, spec, 1, c.scene_mask)
    valid = c.ok & (region.count > 0)
    prob = valid.astype(jnp.float32)
    return ernet.ERNetScores(prob, jnp.zeros((prob.shape[0], spec.num_refinements), jnp.float32), valid, region.count)


def scorer_for(model: nnx.Module) -> Scorer:
    """The scoring function of a Stage-2 network (an ERNet, a PointNetGPD or `Stage1Order`); TypeError otherwise."""
    if isinstance(model, ernet.ERNet):
        return ernet.score
    if isinstance(model, pointnetgpd.PointNetGPD):
        return pointnetgpd_score
    if isinstance(model, Stage1Order):
        return stage1_order_score
    raise TypeError(f"the planner scores with an ERNet, a PointNetGPD or Stage1Order, got {type(model).__name__}")


def has_refinement(model: nnx.Module) -> bool:
    """Whether the network proposes refinements (E-RNet does, PointNetGPD does not)."""
    return isinstance(model, ernet.ERNet)
