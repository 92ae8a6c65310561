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
    # A controller knows only the libraries loaded at its making, so both BLAS libraries are loaded first
    # (SciPy brings its own OpenBLAS; made before it, the controller left it on every core). A
    # controller's limit costs ~10 us, a fresh scan ~1 ms.
    import numpy.linalg  # noqa: F401
    import scipy.linalg  # noqa: F401

    return ThreadpoolController()


def one_blas_thread() -> contextlib.AbstractContextManager:
    """A context in which the loaded BLAS libraries run on one thread (restored on exit)."""
    return _controller().limit(limits=1, user_api="blas")
