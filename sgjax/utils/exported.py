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
import json
import os
import pickle
from collections.abc import Callable, Hashable
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import Any

import jax
import numpy as np

from sgjax.utils.cache import COMPILE_CACHE_ENV, cache_dir, enable_compilation_cache
from sgjax.utils.files import atomic_write_bytes

SUFFIX = ".jaxexport"
_loaded: dict[str, tuple[Callable, Any]] = {}  # key -> (jitted call of the exported program, output treedef)
_jitted: dict[tuple, Callable] = {}  # (name, static) -> jax.jit of the function, when export is off
stats = {"exported": 0, "loaded": 0, "jitted": 0, "unreadable": 0}  # programs made, loaded or not loadable here
_pending: dict[str, Future] = {}  # key -> prefetch's future (its (run, out_tree), or None when it failed)
_used: dict[str, None] = {}  # keys the prefetched group called, in the order of their first call
_manifest: dict = {}  # "path" and "keys" of the prefetched group's list (see `prefetch`)


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
        future = _pending.pop(key, None)
        # A prefetched program has been tried already: a file that failed there is not read again.
        loaded = _load_exported(key) if future is None else future.result()
        _loaded[key] = loaded if loaded is not None else _export(key, fn, leaves, treedef)
    if "path" in _manifest and key not in _used:  # a prefetched group lists its calls
        _remember(key)
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


def prefetch(group: str) -> None:
    """Start loading, on a background thread, the programs that the last process of `group` called (a
    list kept beside them, `<group>.keys`), so that their deserialisation and compilation (a persistent
    cache hit, ~1 s for Stage 1 and 2 on 2 cores) overlaps what the process does before it first calls
    them (reading a frame, restoring a checkpoint). `call` then waits for a program still loading. The
    list is written again when this process calls programs in another order or others (a new code or
    configuration); group names what decides the programs (a command and its settings). Off with
    SGJAX_COMPILE_CACHE=0."""
    if not enabled():
        return
    # Per code version: another sgjax (or jax) calls other programs, and two checkouts sharing a cache
    # would otherwise rewrite each other's list.
    digest = hashlib.sha256("\0".join((group, jax.__version__, source_digest())).encode()).hexdigest()
    path = cache_dir("exported") / (digest[:24] + ".keys")
    try:
        keys = json.loads(path.read_text())["keys"]
    except (OSError, ValueError, KeyError, TypeError):
        keys = []
    _manifest.update(path=path, keys=keys)
    _used.clear()  # a process may prefetch for one group after another (a notebook, the tests)
    todo = [k for k in keys if k not in _loaded and k not in _pending and (path.parent / (k + SUFFIX)).exists()]
    if todo:
        pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="sgjax-prefetch")
        for key in todo:
            _pending[key] = pool.submit(_load_exported, key)
        pool.shutdown(wait=False)


def end_group() -> None:
    """Stop listing calls for the prefetched group: its command is done, and what the process calls next
    (a caller's own code, the next command of a session) is not the group's to load next time."""
    _manifest.clear()
    _used.clear()


def settle() -> None:
    """Wait for the programs `prefetch` is still loading (a process that ends without calling them)."""
    for future in list(_pending.values()):
        future.result()


def _load_exported(key: str) -> tuple[Callable, Any] | None:
    """An exported program (`call`'s (run, output treedef)), compiled for the inputs it was exported with:
    a hit in the persistent compilation cache. None when there is no such file or it cannot be read."""
    path = cache_dir("exported") / (key + SUFFIX)
    if not path.exists():
        return None
    try:
        enable_compilation_cache()
        blob = pickle.loads(path.read_bytes())
        exported = jax.export.deserialize(blob["program"])
        run = jax.jit(exported.call)
        # The call's compilation depends on its inputs' weak types and on which are committed to a device
        # (a restored checkpoint's arrays are), which the program does not keep: they are kept beside it.
        device = jax.devices()[0]
        specs = [jax.ShapeDtypeStruct(a.shape, a.dtype, weak_type=weak,
                                      sharding=jax.sharding.SingleDeviceSharding(device) if committed else None)
                 for a, weak, committed in zip(exported.in_avals, blob["weak"], blob["committed"])]
        run.lower(*specs).compile()
        stats["loaded"] += 1
        return run, jax.tree.structure(blob["skeleton"])
    except Exception:  # a foreign, damaged or older file: the caller exports the program again
        stats["unreadable"] += 1
        return None


def _remember(key: str) -> None:
    """Note that the prefetched group called `key`; rewrite its list when it no longer starts with the
    group's calls."""
    _used[key] = None
    used = list(_used)
    if _manifest["keys"][:len(used)] != used:
        _manifest["keys"] = used
        atomic_write_bytes(_manifest["path"], json.dumps({"keys": used}).encode())


def _export(key: str, fn: Callable, leaves: list, treedef) -> tuple[Callable, Any]:
    """fn traced for `leaves` and exported to the cache under `key` (replacing an unreadable or foreign
    file) -> `call`'s (run, output treedef)."""
    box = {}  # the output's treedef, recorded while tracing

    def flat(*xs):
        out = fn(*jax.tree.unflatten(treedef, list(xs)))
        box["tree"] = jax.tree.structure(out)  # recorded while jax.export traces it (once)
        return jax.tree.leaves(out)

    specs = [jax.ShapeDtypeStruct(np.shape(x), jax.numpy.result_type(x), weak_type=_weak(x)) for x in leaves]
    exported = jax.export.export(jax.jit(flat))(*specs)
    skeleton = jax.tree.unflatten(box["tree"], [0] * box["tree"].num_leaves)  # picklable: leaves are 0
    atomic_write_bytes(cache_dir("exported") / (key + SUFFIX),
                       pickle.dumps({"program": exported.serialize(), "skeleton": skeleton, "weak": [_weak(x) for x in leaves],
                                     "committed": [bool(getattr(x, "committed", False)) for x in leaves]}))
    stats["exported"] += 1
    return jax.jit(exported.call), jax.tree.structure(skeleton)


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
