"""Shared fixtures: a small primitive database built once per test session in a temporary cache."""

from __future__ import annotations

import pytest

from sgjax.stage1.database import DBConfig, build_database


@pytest.fixture(scope="session")
def small_db():
    """DBConfig.small(): a few dozen primitives of every family (~10 s to build, mostly EMS compile)."""
    return build_database(DBConfig.small(), workers=2, progress=False)
