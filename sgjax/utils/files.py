"""Atomic file output: a reader (or a resumed job) never sees half a file."""

from __future__ import annotations

import os
import secrets
import socket
from collections.abc import Callable


def atomic_write(path: str | os.PathLike, write: Callable[[str], None]) -> None:
    """Call `write(tmp_path)` on a temporary file beside `path`, then rename it onto `path`.

    The temporary name keeps the extension, so writers that choose a format by it (numpy, trimesh)
    behave as for `path`; on failure the temporary file is removed and `path` is left untouched.
    """
    path = os.fspath(path)
    stem, ext = os.path.splitext(path)
    # Unique across machines, not only processes: workers on several hosts (or in containers, where pids
    # repeat) may write the same file of a shared directory at once, and each needs its own temporary.
    tmp = f"{stem}.tmp-{socket.gethostname()}-{os.getpid()}-{secrets.token_hex(4)}{ext}"
    try:
        write(tmp)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)


def atomic_write_text(path: str | os.PathLike, text: str) -> None:
    """Write `text` to `path` atomically (UTF-8)."""

    def write(tmp: str) -> None:
        with open(tmp, "w", encoding="utf-8") as fh:
            fh.write(text)

    atomic_write(path, write)


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> None:
    """Write `data` to `path` atomically."""

    def write(tmp: str) -> None:
        with open(tmp, "wb") as fh:
            fh.write(data)

    atomic_write(path, write)
