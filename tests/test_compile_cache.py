"""JAX's persistent compilation cache: on by default under $SGJAX_CACHE/jax, off with SGJAX_COMPILE_CACHE=0.

Run in fresh interpreters: the setting is process-wide and JAX reads it once per process.
"""

from __future__ import annotations

import os
import subprocess
import sys

CHILD = (
    "import jax, jax.numpy as jnp\n"
    "from sgjax.utils.cache import enable_compilation_cache\n"
    "print(enable_compilation_cache())\n"
    "print(jax.config.jax_compilation_cache_dir)\n"
    "jax.config.update('jax_persistent_cache_min_compile_time_secs', 0)  # keep even a fast compile\n"
    "jax.jit(lambda x: jnp.sin(x) @ x.T)(jnp.ones((64, 64))).block_until_ready()\n"
)


def _run(env: dict) -> list[str]:
    done = subprocess.run([sys.executable, "-c", CHILD], env=env, capture_output=True, text=True, check=True)
    return done.stdout.strip().splitlines()


def test_cache_is_on_by_default_in_the_data_cache(tmp_path):
    env = {**os.environ, "SGJAX_CACHE": str(tmp_path)}
    env.pop("SGJAX_COMPILE_CACHE", None)
    env.pop("SGJAX_JAX_CACHE_DIR", None)
    returned, configured = _run(env)
    assert returned == configured == str(tmp_path / "jax")
    assert any(p.name.startswith("jit__lambda") for p in (tmp_path / "jax").iterdir())  # the program was written there


def test_cache_off_and_elsewhere(tmp_path):
    env = {**os.environ, "SGJAX_CACHE": str(tmp_path / "data"), "SGJAX_COMPILE_CACHE": "0"}
    assert _run(env) == ["None", "None"]
    env = {**os.environ, "SGJAX_CACHE": str(tmp_path / "data"), "SGJAX_JAX_CACHE_DIR": str(tmp_path / "compiled")}
    env.pop("SGJAX_COMPILE_CACHE", None)
    assert _run(env)[0] == str(tmp_path / "compiled")
