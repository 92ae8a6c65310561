"""Traced programs kept on disk (`jax.export`), so a new process skips tracing as well as compiling.

JAX's persistent compilation cache (`sgjax.utils.cache.enable_compilation_cache`) saves the compiled
executables, but a new process still traces and lowers each program before it can look one up: for
Stage 1 (EMS under vmap) that alone takes 10-40 s on a laptop CPU. `call` instead keeps each program's
exported StableHLO in `$SGJAX_CACHE/exported/`, keyed by

    the program's name and static settings, its input structure, shapes and dtypes, the jax and
    jaxlib versions, the platform, and a digest of sgjax's own source files,

so a changed function, setting or input shape never reuses a stale program. A new process
deserialises it and compiles it (a hit in the persistent compilation cache). Off with
`SGJAX_COMPILE_CACHE=0` (plain `jax.jit` then, as for a program that cannot be exported).

Inputs may be any pytree; outputs are returned with the structure the function gave when it was
exported (its skeleton is pickled beside the program, so the output's classes must be importable).
"""

from __future__ import annotations

import functools
import hashlib
import os
import pickle
from collections.abc import Callable, Hashable
from pathlib import Path
from typing import Any

import jax
import numpy as np

from sgjax.utils.cache import COMPILE_CACHE_ENV, cache_dir, enable_compilation_cache
from sgjax.utils.files import atomic_write_bytes

SUFFIX = ".jaxexport"
_loaded: dict[str, tuple[Callable, Any]] = {}  # key -> (jitted call of the exported program, output treedef)
_jitted: dict[tuple, Callable] = {}  # (name, static) -> jax.jit of the function, when export is off
stats = {"exported": 0, "loaded": 0, "jitted": 0}  # programs made or loaded in this process


def enabled() -> bool:
    """Whether programs are exported to and loaded from the cache (SGJAX_COMPILE_CACHE is not 0)."""
    return os.environ.get(COMPILE_CACHE_ENV, "1").strip().lower() not in ("0", "false", "off", "no")


@functools.lru_cache(maxsize=1)
def source_digest() -> str:
    """sha256 over the sgjax package's .py files (paths and contents): any code change gives a new key."""
    root = Path(__file__).resolve().parents[1]
    h = hashlib.sha256()
    for path in sorted(root.rglob("*.py")):
        h.update(str(path.relative_to(root)).encode())
        h.update(path.read_bytes())
    return h.hexdigest()


def program_key(name: str, static: Hashable, leaves: list, treedef) -> str:
    """The cache key of `name` with these static settings on inputs of this structure, shapes and dtypes."""
    import jaxlib

    h = hashlib.sha256()
    avals = [(tuple(np.shape(x)), str(jax.numpy.result_type(x)), _weak(x)) for x in leaves]
    for part in (name, repr(static), str(treedef), repr(avals), jax.__version__, jaxlib.__version__,
                 jax.default_backend(), source_digest()):
        h.update(part.encode())
        h.update(b"\0")
    return f"{name}-{h.hexdigest()[:24]}"


def _weak(x) -> bool:
    return bool(getattr(x, "weak_type", False))


def call(name: str, fn: Callable, args: tuple, static: Hashable = ()) -> Any:
    """fn(*args), jit-compiled: from an exported program in the cache when there is one, else exported
    there first. `static` must describe everything fn closes over that changes its program (configs,
    flags); fn's arguments are arrays (any pytree). Returns fn's output pytree."""
    if not enabled():
        jitted = _jitted.get((name, static))
        if jitted is None:
            jitted = _jitted[(name, static)] = jax.jit(fn)
            stats["jitted"] += 1
        return jitted(*args)
    leaves, treedef = jax.tree.flatten(args)
    key = program_key(name, static, leaves, treedef)
    if key not in _loaded:
        _loaded[key] = _load_or_export(key, fn, leaves, treedef)
    run, out_tree = _loaded[key]
    return jax.tree.unflatten(out_tree, run(*leaves))


def ready(name: str, args: tuple, static: Hashable = ()) -> bool:
    """Whether `call(name, fn, args, static)` would find its program without tracing it: loaded in this
    process, or exported on disk (then a load, not a compile). False when exporting is off."""
    if not enabled():
        return False
    leaves, treedef = jax.tree.flatten(args)
    key = program_key(name, static, leaves, treedef)
    return key in _loaded or (cache_dir("exported") / (key + SUFFIX)).exists()


def _load_or_export(key: str, fn: Callable, leaves: list, treedef) -> tuple[Callable, Any]:
    enable_compilation_cache()  # the exported program's compilation is then a cache hit too
    path = cache_dir("exported") / (key + SUFFIX)
    exported = skeleton = None
    if path.exists():
        try:
            blob = pickle.loads(path.read_bytes())
            exported = jax.export.deserialize(blob["program"])
            skeleton = blob["skeleton"]
            stats["loaded"] += 1
        except Exception:  # an unreadable or foreign file: export again (and replace it)
            exported = None
    if exported is None:
        box = {}

        def flat(*xs):
            out = fn(*jax.tree.unflatten(treedef, list(xs)))
            box["tree"] = jax.tree.structure(out)  # recorded while jax.export traces it (once)
            return jax.tree.leaves(out)

        specs = [jax.ShapeDtypeStruct(np.shape(x), jax.numpy.result_type(x), weak_type=_weak(x)) for x in leaves]
        exported = jax.export.export(jax.jit(flat))(*specs)
        skeleton = jax.tree.unflatten(box["tree"], [0] * box["tree"].num_leaves)  # picklable: leaves are 0
        atomic_write_bytes(path, pickle.dumps({"program": exported.serialize(), "skeleton": skeleton}))
        stats["exported"] += 1
    out_tree = jax.tree.structure(skeleton)
    return jax.jit(exported.call), out_tree


def compiled_programs() -> int:
    """How many compiled programs the calls of this process hold (grows by one with each compilation)."""
    runs = [run for run, _ in _loaded.values()] + list(_jitted.values())
    return sum(run._cache_size() for run in runs)


def traced_programs() -> int:
    """How many programs this process has traced: exported to the cache, jitted with exporting off, or
    compiled again for a new input signature. Loading a program another process exported is not
    counted (a load, not a trace), so this stays put when later calls load sizes the cache already holds."""
    retraced = sum(max(run._cache_size() - 1, 0) for run, _ in _loaded.values())
    return stats["exported"] + retraced + sum(run._cache_size() for run in _jitted.values())
