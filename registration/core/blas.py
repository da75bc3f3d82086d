"""BLAS on one thread while the engine works (:func:`one_blas_thread`).

The engine's parallel DRR kernels run on numba's OpenMP threads, which spin for a while after
each render waiting for the next. A multi-threaded BLAS call made meanwhile (a phase correlation's
matrix products, small matrix products from several Python threads at once) then shares the
cores with spinning threads and waits for its own, for milliseconds. The engine's matrices are
small, so it keeps BLAS to one thread while it works; the process's own setting comes back
afterwards (docs/decisions/2026-12-07-blas-one-thread.md).
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import ParamSpec, TypeVar

import threadpoolctl
from threadpoolctl import threadpool_limits

_P = ParamSpec("_P")
_R = TypeVar("_R")

#: threadpoolctl lets only the first thread that set a limit change OpenBLAS's process-wide pool
#: (its "controlling thread"); the engine's limit is process-wide by design, so it takes control.
_OPENBLAS = getattr(threadpoolctl, "OpenBLASController", None)

_lock = threading.Lock()
_users = 0
_limits: threadpool_limits | None = None


@contextmanager
def one_blas_thread() -> Iterator[None]:
    """Within the block, BLAS libraries loaded in the process use one thread; nested or
    concurrent blocks (several registrations in threads) share the limit, and the last one to
    leave restores what the process had."""
    global _users, _limits
    with _lock:
        if _users == 0:
            _release_control()
            _limits = threadpool_limits(limits=1, user_api="blas")
        _users += 1
    try:
        yield
    finally:
        with _lock:
            _users -= 1
            if _users == 0 and _limits is not None:
                _release_control()
                _limits.restore_original_limits()
                _limits = None
                _release_control()  # whichever thread sets a limit next may


def _release_control() -> None:
    if _OPENBLAS is not None and hasattr(_OPENBLAS, "clear_controlling_thread"):
        _OPENBLAS.clear_controlling_thread(force=True)


def with_one_blas_thread(fn: Callable[_P, _R]) -> Callable[_P, _R]:
    """``fn`` run within :func:`one_blas_thread` (a fresh block per call)."""
    return one_blas_thread()(fn)
