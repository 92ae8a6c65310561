"""Which code produced a result: the git commit of this package's own checkout."""

from __future__ import annotations

import subprocess
from pathlib import Path
from typing import Any


def code_commit() -> dict[str, Any]:
    """The git commit of this code -> {"sha": "<HEAD>" | "unknown", "dirty": bool | None}.

    Only the repository whose top level holds this package counts (an installed copy inside some other
    checkout is "unknown"). dirty: tracked files differ from HEAD; untracked files are left out, or
    every run directory and cache kept in the checkout (runs/ by default) would mark the code dirty.
    """
    root = Path(__file__).resolve().parents[2]

    def git(*args: str) -> str:
        done = subprocess.run(["git", "-C", str(root), *args], capture_output=True, text=True, timeout=30, check=True)
        return done.stdout.strip()

    try:
        if Path(git("rev-parse", "--show-toplevel")).resolve() != root:
            return {"sha": "unknown", "dirty": None}
        return {"sha": git("rev-parse", "HEAD"), "dirty": bool(git("status", "--porcelain", "--untracked-files=no"))}
    except (OSError, subprocess.SubprocessError):
        return {"sha": "unknown", "dirty": None}
