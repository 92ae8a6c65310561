"""Grasp trials on MJX (MuJoCo in JAX): `jax.vmap` over trials, `jax.lax.scan` over steps, one `jit`.

Same schedule, same model and the same per-phase summary (`Rollout`) as the C backend. Differences:
  * MJX cannot evaluate contact sensors with body matching, so the scene is recompiled without its
    sensors (identical otherwise) and the counts "gripper touches X" are derived from MJX's contact
    list (active where dist < 0, the margin being 0) with the same grouping as the C sensors.
  * Every trial runs every phase (no early stop: on a GPU a stopped world saves nothing).
  * Batches are padded to a power of two so that a scene compiles once per size class; the compiled
    function is reused across scenes with the same model shapes (e.g. after `remove_object`).
On CPU, MJX is ~25x slower than the C engine and compiles for tens of seconds: use it on a GPU.
On CPU the rollout is also compiled with a plain-JAX Cholesky factorisation (`cpu_safe_cholesky`):
jaxlib 0.10's LAPACK kernel deadlocks XLA's CPU thread pool when MJX runs two of them at once.

Two MJX implementations: "jax" (pure JAX) and "warp" (MuJoCo Warp kernels, needs `warp-lang`; built
for NVIDIA GPUs, also runs, slowly, on CPU); "auto" takes warp on a GPU where it is installed. Warp
keeps one contact buffer for all worlds (`naconmax` in total, each contact tagged with its world), so
each trial counts its own contacts by world id, and a step that fills the buffer marks every trial of
the batch not ok (invalid), since contacts may be lost.
"""

from __future__ import annotations

import contextlib
import functools
import threading

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import mjx

from envs import gripper_model
from envs import scene as scene_lib
from envs.rollout import FALLEN_BELOW, Judge, Rollout, Schedule, initial_states


@functools.lru_cache(maxsize=4)
def _sensorless_model(assets: tuple, config: scene_lib.SceneConfig, gripper) -> mujoco.MjModel:
    return scene_lib.build_sensorless_spec(assets, config, gripper).compile()


IMPLS = ("jax", "warp")
WARP_CONTACTS_PER_WORLD = 512  # warp's contact buffer per trial (a 20-object pile touches ~100 pairs)


def warp_available() -> bool:
    """Whether MJX's warp implementation can run here (`warp-lang` importable)."""
    try:
        import warp  # noqa: F401
    except ImportError:
        return False
    return True


def resolve_impl(impl: str) -> str:
    """ "auto", "jax" or "warp" -> "jax" | "warp". auto: warp on a GPU with `warp-lang` installed, else
    jax (on CPU warp runs ~5x slower than jax: 0.3 against 1.3 trials/s in `bench_sim.py`)."""
    if impl == "auto":
        return "warp" if jax.default_backend() == "gpu" and warp_available() else "jax"
    if impl not in IMPLS:
        raise ValueError(f"MJX impl must be 'auto', 'jax' or 'warp', got {impl!r}")
    if impl == "warp" and not warp_available():
        raise ValueError("MJX impl 'warp' needs the warp-lang package (pip install warp-lang)")
    return impl


@functools.lru_cache(maxsize=4)
def _device_model(assets: tuple, config: scene_lib.SceneConfig, gripper, impl: str) -> mjx.Model:
    return mjx.put_model(_sensorless_model(assets, config, gripper), impl=impl)


def cholesky_columns(a: jax.Array) -> jax.Array:
    """Lower Cholesky factors of symmetric positive-definite matrices a [..., n, n] -> L [..., n, n]
    (zeros above the diagonal), in plain JAX ops: one column at a time, unrolled (n is MJX's nv, a few
    dozen). A matrix that is not positive definite comes back all NaN, as from JAX's LAPACK path."""
    n = a.shape[-1]
    rows = jnp.arange(n)
    low = jnp.zeros_like(a)
    for j in range(n):
        # Column j of L from the columns before it; written by adding a one-hot outer product rather
        # than by slice updates, which XLA's CPU loops copy (1.4x slower in a 100-step scan).
        v = a[..., :, j] - jnp.einsum("...ik,...k->...i", low, low[..., j, :])
        col = jnp.where(rows >= j, v * jax.lax.rsqrt(v[..., j : j + 1]), 0.0)
        low = low + col[..., :, None] * (rows == j).astype(a.dtype)
    ok = jnp.isfinite(low).all(axis=(-2, -1), keepdims=True)
    return jnp.where(ok, low, jnp.nan)


_LOWERING_LOCK = threading.Lock()


@contextlib.contextmanager
def cpu_safe_cholesky():
    """Within this block, `jax.lax.linalg.cholesky` (under `jax.scipy.linalg.cho_factor`, which MJX's
    solver and mass-matrix factorisation call) lowers on CPU to `cholesky_columns` instead of jaxlib's
    LAPACK kernel. Only what is traced and compiled inside the block is affected.

    Why: jaxlib 0.10's batched LAPACK kernels split their batch over XLA's intra-op thread pool and
    block until the pieces finish. When the pool's every thread runs such a kernel at once (MJX's step
    holds independent factorisations; on 2 cores two suffice), no thread is left to run the pieces:
    `sgjax label --backend mjx` hung with both pool threads waiting in `lapack_spotrf_ffi`. The plain
    version is ordinary XLA ops that never wait on the pool; it agrees with LAPACK to ~1e-6 and costs
    about as much at MJX's sizes (64 x 26x26: 0.7-1.2 ms against 0.7 ms; 256 x 32x32 in a scan: ~8x
    LAPACK), a small share of an MJX step on CPU, which mesh collisions dominate.
    JAX has no public switch for a primitive's lowering, so this swaps the registered CPU rule (a
    private table) for the duration, under a lock; GPUs lower through their own rules, untouched.
    """
    try:
        from jax._src.interpreters import mlir
        from jax._src.lax import linalg
    except ImportError:  # a JAX whose internals moved: keep LAPACK (newer jaxlibs no longer block)
        yield
        return
    rules = mlir._platform_specific_lowerings["cpu"]
    with _LOWERING_LOCK:
        saved = rules.get(linalg.cholesky_p)
        rules[linalg.cholesky_p] = mlir.LoweringRuleEntry(mlir.lower_fun(cholesky_columns, multiple_results=False), True)
        try:
            yield
        finally:
            if saved is None:
                rules.pop(linalg.cholesky_p, None)
            else:
                rules[linalg.cholesky_p] = saved


def _geom_masks(scene: scene_lib.Scene, model: mujoco.MjModel) -> tuple[np.ndarray, ...]:
    """Geom masks: table [ngeom], objects [ngeom, N], gripper / left finger / right finger [ngeom]."""
    geom_object = scene.geom_object()

    def body(name: str) -> np.ndarray:
        return model.geom_bodyid == mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, name)

    left, right = (body(name) for name in gripper_model.FINGER_BODIES)
    return (
        geom_object == scene_lib.TABLE,
        geom_object[:, None] == np.arange(scene.n_objects)[None],
        body(gripper_model.GRIPPER_BODY) | left | right,
        left,
        right,
    )


def _contacts(d: mjx.Data, world: jax.Array) -> tuple[jax.Array, jax.Array]:
    """This trial's contacts: (geom pairs [C, 2], active [C]: penetrating (dist < 0), in this world)."""
    impl = d._impl
    if hasattr(impl, "contact"):  # jax: one contact list per world
        return impl.contact.geom, impl.contact.dist < 0
    # warp: one buffer for all worlds, its first nacon entries filled
    filled = jnp.arange(impl.contact__dist.shape[0]) < jnp.reshape(impl.nacon, ())
    return impl.contact__geom, filled & (impl.contact__dist < 0) & (impl.contact__worldid == world)


def _contact_counts(d: mjx.Data, world, table, objects, grip, left, right) -> jax.Array:
    """[1 + 3N] contact counts in the C sensors' order: gripper-table, then per object
    (gripper, left finger, right finger)."""
    geom, active = _contacts(d, world)
    active = active[:, None]
    g1, g2 = geom[:, 0], geom[:, 1]

    def pair(a, b):  # [C, K] contacts between a geom of mask a and a geom of mask(s) b
        a1, a2 = a[g1][:, None], a[g2][:, None]
        b1, b2 = b[g1].reshape(len(g1), -1), b[g2].reshape(len(g2), -1)
        return (a1 & b2) | (a2 & b1)

    table_count = jnp.sum(pair(grip, table) & active, axis=0)  # [1]
    per_object = [jnp.sum(pair(mask, objects) & active, axis=0) for mask in (grip, left, right)]  # 3 x [N]
    return jnp.concatenate([table_count, jnp.stack(per_object, axis=1).reshape(-1)]).astype(jnp.float32)


def _buffer_full(d: mjx.Data) -> jax.Array:
    """Whether warp's shared contact buffer is full (contacts may have been dropped); False on jax."""
    impl = d._impl
    return jnp.reshape(impl.nacon, ()) >= impl.naconmax if hasattr(impl, "nacon") else jnp.bool_(False)


@functools.partial(jax.jit, static_argnames=("phase_steps", "mocap"))
def _run(mx, d0, init, controls, force_mask, phase_force, masks, speed_dofs, height_adr, phase_steps, mocap):
    """vmap over trials of one scan over all steps (one traced mjx.step keeps compiling short).

    Returns per trial and phase: (contact_max [P, S], end counts [P, S], end qpos [P, nq], speed [P]),
    and per trial whether warp's contact buffer ever filled up.
    """
    table, objects, grip, left, right = masks
    nphase, nsensor = len(phase_steps), 1 + 3 * objects.shape[1]
    phase_of_step = jnp.asarray(np.repeat(np.arange(nphase), phase_steps))
    last_step = jnp.asarray(np.cumsum(phase_steps) - 1)

    def trial(world, init, controls, force_mask):
        def step(carry, inputs):
            d, cmax, last, qpos, vmax, full = carry
            t, u = inputs
            phase = phase_of_step[t]
            d = d.replace(
                ctrl=u[:2],
                mocap_pos=d.mocap_pos.at[mocap].set(u[2:5]),
                mocap_quat=d.mocap_quat.at[mocap].set(u[5:9]),
                xfrc_applied=jnp.zeros_like(d.xfrc_applied).at[:, 2].set(-phase_force[phase] * force_mask),
            )
            d = mjx.step(mx, d)
            counts = _contact_counts(d, world, table, objects, grip, left, right)
            full = full | _buffer_full(d)
            on_table = d.qpos[height_adr] > FALLEN_BELOW  # objects that fell off may fall fast
            speed = jnp.max(jnp.where(on_table, jnp.linalg.norm(d.qvel[speed_dofs], axis=-1), 0.0), initial=0.0)
            end = t == last_step[phase]
            cmax = cmax.at[phase].max(counts)
            vmax = vmax.at[phase].max(speed)
            last = last.at[phase].set(jnp.where(end, counts, last[phase]))
            qpos = qpos.at[phase].set(jnp.where(end, d.qpos, qpos[phase]))
            return (d, cmax, last, qpos, vmax, full), None

        d = d0.replace(**init)
        zeros = jnp.zeros((nphase, nsensor), jnp.float32)
        qpos = jnp.zeros((nphase, d.qpos.shape[0]), d.qpos.dtype)
        carry = (d, zeros, zeros, qpos, jnp.zeros(nphase, d.qvel.dtype), jnp.bool_(False))
        (_, cmax, last, qpos, vmax, full), _ = jax.lax.scan(step, carry, (jnp.arange(len(controls)), controls))
        return cmax, last, qpos, vmax, full

    # vmap lane i is warp's world i (the batch axis becomes warp's worlds).
    return jax.vmap(trial)(jnp.arange(len(controls)), init, controls, force_mask)


def rollout_mjx(scene: scene_lib.Scene, judge: Judge, schedule: Schedule, nthread: int = 0, impl: str = "auto") -> Rollout:
    """Roll out the M trials of `schedule` on MJX from the scene's settled state (nthread is unused).
    impl: "auto" (`resolve_impl`: warp on a GPU where warp-lang is installed, else jax), "jax" or "warp"."""
    del nthread
    impl = resolve_impl(impl)
    model = _sensorless_model(scene.assets, scene.config, scene.gripper)
    if (model.nq, model.nv, model.nbody, model.ngeom) != (
        scene.model.nq, scene.model.nv, scene.model.nbody, scene.model.ngeom
    ):
        raise AssertionError("the sensorless model must match the scene model")
    mx = _device_model(scene.assets, scene.config, scene.gripper, impl)
    m = len(judge.targets)
    size = 1 << max(0, (m - 1).bit_length())  # pad to a power of two: few compiled sizes
    pad = np.concatenate([np.arange(m), np.zeros(size - m, np.int64)])

    states = initial_states(scene, schedule, judge.lay)[pad]
    data = mujoco.MjData(model)
    mujoco.mj_setState(model, data, scene.state, scene_lib.STATE_SPEC)
    mujoco.mj_forward(model, data)
    if impl == "warp":
        d0 = mjx.put_data(model, data, impl=impl, naconmax=size * WARP_CONTACTS_PER_WORLD, njmax=6 * WARP_CONTACTS_PER_WORLD)
    else:
        d0 = mjx.put_data(model, data, impl=impl)

    def part(bit: mujoco.mjtState, shape: tuple) -> jax.Array:
        return jnp.asarray(states[:, scene_lib.state_slice(model, bit)].reshape(size, *shape))

    init = {
        "qpos": part(mujoco.mjtState.mjSTATE_QPOS, (model.nq,)),
        "qvel": part(mujoco.mjtState.mjSTATE_QVEL, (model.nv,)),
        "ctrl": part(mujoco.mjtState.mjSTATE_CTRL, (model.nu,)),
        "mocap_pos": part(mujoco.mjtState.mjSTATE_MOCAP_POS, (model.nmocap, 3)),
        "mocap_quat": part(mujoco.mjtState.mjSTATE_MOCAP_QUAT, (model.nmocap, 4)),
        "eq_active": part(mujoco.mjtState.mjSTATE_EQ_ACTIVE, (model.neq,)).astype(d0.eq_active.dtype),
    }
    force_mask = np.zeros((size, model.nbody))
    force_mask[np.arange(size), scene.body_ids[judge.targets[pad]]] = 1.0
    # Every object (fixed shapes): parked ones sit far below FALLEN_BELOW and never count.
    speed_dofs = judge.lay.object_qvel[:, None] + np.arange(3)
    height_adr = judge.lay.object_qpos + 2
    # Every call, not only the first: a call that traces anew (new shapes) must trace inside too.
    safe = cpu_safe_cholesky() if jax.default_backend() == "cpu" else contextlib.nullcontext()
    with safe:
        cmax, last, qpos, vmax, full = _run(
            mx,
            d0,
            init,
            jnp.asarray(schedule.controls()[pad], d0.qpos.dtype),
            jnp.asarray(force_mask, d0.qpos.dtype),
            jnp.asarray(schedule.phase_force, d0.qpos.dtype),
            tuple(jnp.asarray(x) for x in _geom_masks(scene, model)),
            jnp.asarray(speed_dofs),
            jnp.asarray(height_adr),
            phase_steps=tuple(schedule.phase_steps),
            mocap=judge.lay.mocap,
        )
        # Wait here, inside: JAX dispatches asynchronously, and the result is what must be computed.
        cmax, last, qpos, vmax, full = jax.block_until_ready((cmax, last, qpos, vmax, full))
    cmax, last, qpos, vmax = (np.asarray(x, np.float64)[:m] for x in (cmax, last, qpos, vmax))
    ok = ~np.asarray(full)[:m]  # NaNs are judged per phase by `classify`
    return Rollout(contact_max=cmax, end_contacts=last, end_qpos=qpos, max_speed=vmax, ok=ok)
