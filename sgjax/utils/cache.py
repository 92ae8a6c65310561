"""The cache directory for generated data (prepared meshes, primitive databases, datasets)."""

from __future__ import annotations

import os
from pathlib import Path


def cache_dir(*parts: str, create: bool = True) -> Path:
    """`$SGJAX_CACHE` (default `~/.cache/sgjax`) joined with `parts`; created unless `create=False`."""
    root = os.environ.get("SGJAX_CACHE") or os.path.join(os.path.expanduser("~"), ".cache", "sgjax")
    path = Path(root).joinpath(*parts)
    if create:
        path.mkdir(parents=True, exist_ok=True)
    return path


COMPILE_CACHE_ENV = "SGJAX_COMPILE_CACHE"
COMPILE_CACHE_DIR_ENV = "SGJAX_JAX_CACHE_DIR"  # where the compiled programs go (default $SGJAX_CACHE/jax)


def enable_compilation_cache() -> Path | None:
    """Turn on JAX's persistent compilation cache in `$SGJAX_CACHE/jax` (or `$SGJAX_JAX_CACHE_DIR`) -> its
    directory, or None when off.

    Every new process (a notebook kernel restart, each `sgjax plan` from a shell script) would otherwise
    compile EMS, Stage 1 and E-RNet again (seconds each); with the cache, a later process loads the
    compiled programs. On by default; `SGJAX_COMPILE_CACHE=0` turns it off. A cache directory the user
    already gave JAX (`jax_compilation_cache_dir`) is kept. Called by the planner, Stage 1, the trainer
    and the command line; calling it again does nothing more.
    """
    if os.environ.get(COMPILE_CACHE_ENV, "1").strip().lower() in ("0", "false", "off", "no"):
        return None
    import jax

    current = jax.config.jax_compilation_cache_dir
    if current:
        return Path(current)
    chosen = os.environ.get(COMPILE_CACHE_DIR_ENV, "").strip()
    path = Path(chosen).expanduser() if chosen else cache_dir("jax")
    path.mkdir(parents=True, exist_ok=True)
    jax.config.update("jax_compilation_cache_dir", str(path))
    # Our programs compile in 0.5-10 s on a laptop CPU; JAX's default keeps only those over 1 s.
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.2)
    return path
