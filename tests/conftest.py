"""Shared fixtures: a small primitive database built once per test session in a temporary cache."""

from __future__ import annotations

import os

# The suite is dominated by XLA compiling (each test compiles its own small shapes once) rather than by
# running the compiled code, so on CPU the tests ask LLVM for cheaper code generation: ~40 % less
# compile time, the same computation (no fast-math: results do not change). Set before JAX is imported;
# subprocesses started by tests (the CLI, the notebook kernel) inherit it. A user's own XLA_FLAGS wins.
os.environ.setdefault("XLA_FLAGS", "--xla_llvm_disable_expensive_passes=true --xla_backend_optimization_level=0")

import pytest  # noqa: E402

from sgjax.stage1.database import DBConfig, build_database  # noqa: E402


@pytest.fixture(scope="session")
def small_db():
    """DBConfig.small(): a few dozen primitives of every family (~10 s to build, mostly EMS compile)."""
    return build_database(DBConfig.small(), workers=2, progress=False)
