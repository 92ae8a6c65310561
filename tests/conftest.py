"""Shared fixtures: a small primitive database built once per test session in a temporary cache."""

from __future__ import annotations

import os

# The suite is dominated by XLA compiling (each test compiles its own small shapes once) rather than by
# running the compiled code, so on CPU the tests ask for cheaper code generation: LLVM's cheap passes
# (~40 % less compile time) and XLA:CPU's older loop emitters instead of its MLIR fusion emitters (about
# half the compile time again: a fresh process's first plan 97 -> 62 s, one test 90 -> 52 s, the plans
# as fast after; docs/experiments.md, 2026-12-06). Neither is fast-math: the same operations, perhaps
# rounded in another order. Set before JAX is imported; subprocesses started by tests (the CLI, the
# notebook kernel) inherit it. A user's own XLA_FLAGS wins.
os.environ.setdefault("XLA_FLAGS", "--xla_llvm_disable_expensive_passes=true --xla_backend_optimization_level=0 "
                                   "--xla_cpu_use_fusion_emitters=false")

import gc  # noqa: E402

import jax  # noqa: E402
import pytest  # noqa: E402

from sgjax.stage1.database import DBConfig, build_database  # noqa: E402
from sgjax.utils.cache import enable_compilation_cache  # noqa: E402

# Every test module drops its compiled programs when it ends (below), and the next module that uses the
# same program compiles it again unless JAX's persistent cache holds it. The library keeps only programs
# that took over 0.2 s to compile (`enable_compilation_cache`); the suite also compiles hundreds of small
# ones (array helpers, geometry, the decision policy), the same in every module, so it keeps them all.
if enable_compilation_cache() is not None:
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)


@pytest.fixture(scope="session")
def small_db():
    """DBConfig.small(): a few dozen primitives of every family (~10 s to build, mostly EMS compile)."""
    return build_database(DBConfig.small(), workers=2, progress=False)


@pytest.fixture(autouse=True, scope="module")
def release_compiled_programs():
    """After each test module, drop JAX's compiled executables (`jax.clear_caches`).

    Each XLA:CPU executable keeps ~10 memory mappings while it lives, and a process may hold at most
    `vm.max_map_count` (65530 by default) of them. One process running the whole suite compiles
    thousands of programs: by the last test files it neared that limit, a large compilation then
    failed, and the C++ exception jaxlib raised for the failure crashed in the unwinder (CI: a
    segfault in `test_cpu_and_mjx_backends_agree`, 2026-12-02). Programs are only ever shared within
    a module (module-scoped fixtures); later modules recompile what they use (or load it from the
    persistent cache)."""
    yield
    jax.clear_caches()
    gc.collect()
