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
