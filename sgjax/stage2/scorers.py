"""Which Stage-2 network scores the planner's candidates: E-RNet, or PointNetGPD in its place (ablation).

The planner is written against one contract, `score(graphdef, state, scene [N, 3], poses [M, 4, 4],
widths [M], scene_mask [N], *, spec, key) -> ernet.ERNetScores`. E-RNet fills it as it is; PointNetGPD,
which has no refinement head, gives its stable-grasp probability as the evaluation and refinement
probabilities of 0, so a planner with `use_refinement=False` runs every step of its policy (robust
choice, fallbacks, memory) on PointNetGPD's judgement: the network compared with the network, not with
the planner around it (`eval`'s `supergrasp-pointnetgpd`).
"""

from __future__ import annotations

import functools
from collections.abc import Callable

import jax
import jax.numpy as jnp
from flax import nnx

from sgjax.geometry.gripper import GripperSpec
from sgjax.stage2 import ernet, pointnetgpd

Scorer = Callable[..., ernet.ERNetScores]


@functools.partial(jax.jit, static_argnames=("graphdef", "spec"))
def pointnetgpd_score(graphdef: nnx.GraphDef, state: nnx.State, scene: jax.Array, poses: jax.Array, widths: jax.Array,
                      scene_mask: jax.Array | None = None, *, spec: GripperSpec = ernet.DEFAULT_SPEC,
                      key: jax.Array | None = None) -> ernet.ERNetScores:
    """PointNetGPD in E-RNet's contract: eval_prob [M] = its probability, refine_prob [M, K] = 0."""
    s = pointnetgpd.score(graphdef, state, scene, poses, widths, scene_mask, spec=spec, key=key)
    return ernet.ERNetScores(s.prob, jnp.zeros((s.prob.shape[0], spec.num_refinements), s.prob.dtype), s.valid, s.count)


def scorer_for(model: nnx.Module) -> Scorer:
    """The scoring function of a Stage-2 network (an ERNet or a PointNetGPD); TypeError otherwise."""
    if isinstance(model, ernet.ERNet):
        return ernet.score
    if isinstance(model, pointnetgpd.PointNetGPD):
        return pointnetgpd_score
    raise TypeError(f"the planner scores with an ERNet or a PointNetGPD, got {type(model).__name__}")


def has_refinement(model: nnx.Module) -> bool:
    """Whether the network proposes refinements (E-RNet does, PointNetGPD does not)."""
    return isinstance(model, ernet.ERNet)
