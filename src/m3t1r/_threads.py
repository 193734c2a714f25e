"""BLAS threading for small-matrix workloads.

Every matrix here is tiny (16 x 16 to a few hundred rows); a multithreaded BLAS only adds thread
wake-ups, and with another process on the machine a 120 us FK solve was measured at 4 ms. Batch
entry points therefore run on one BLAS thread. Users calling the solver in their own loops can do
the same with `with single_blas_thread(): ...`.
"""

from __future__ import annotations

import functools
from typing import Callable, ParamSpec, TypeVar

from threadpoolctl import ThreadpoolController

P = ParamSpec("P")
R = TypeVar("R")
_controller: ThreadpoolController | None = None


def single_blas_thread():
    """Context manager limiting BLAS (OpenBLAS/MKL) to one thread inside the block.

    The controller (which scans the loaded libraries) is built once: a fresh
    `threadpool_limits` costs about 150 us per entry, the cached one about 4 us.
    """
    global _controller
    if _controller is None:
        _controller = ThreadpoolController()
    return _controller.limit(limits=1, user_api="blas")


def on_one_blas_thread(func: Callable[P, R]) -> Callable[P, R]:
    """Decorator: run `func` with BLAS limited to one thread."""

    @functools.wraps(func)
    def wrapper(*args: P.args, **kwargs: P.kwargs) -> R:
        with single_blas_thread():
            return func(*args, **kwargs)

    return wrapper
