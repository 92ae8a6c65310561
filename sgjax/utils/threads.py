"""BLAS on one thread for thin array work.

NumPy's and SciPy's OpenBLAS split even an [N, 3] by [3, k] product over every core; on a 2-core machine
beside other busy processes its threads spin and wait for each other, and such products take 10x as
long as on one thread (docs/real-camera.md). Host code made of thin products (the depth front end)
runs inside `one_blas_thread()`.
"""

from __future__ import annotations

import contextlib
import functools

from threadpoolctl import ThreadpoolController


@functools.cache
def _controller() -> ThreadpoolController:
    # Made on first use, when NumPy's and SciPy's BLAS libraries are loaded (a controller knows the
    # libraries of its making); a controller's limit costs ~10 us, a fresh scan ~1 ms.
    return ThreadpoolController()


def one_blas_thread() -> contextlib.AbstractContextManager:
    """A context in which the loaded BLAS libraries run on one thread (restored on exit)."""
    return _controller().limit(limits=1, user_api="blas")
