"""BLAS thread control for hot paths.

numpy and scipy each ship their own OpenBLAS; on a 2-core machine the two thread pools
contend and made small matrix products 3-5x slower in our measurements. The particle filter
and metamodel evaluate many small products per product step, where one BLAS thread is
fastest, and parallelism comes from running independent filters in separate processes.
Hot paths therefore run inside :func:`single_blas_thread`; everything else leaves BLAS alone.

The thread-pool inventory is taken once (about 0.6 ms a call otherwise, measured on the
metamodel's predict), after scipy's BLAS is loaded so that both copies are in it.
"""

from __future__ import annotations

from contextlib import AbstractContextManager
from functools import lru_cache
from typing import Any

import scipy.linalg  # noqa: F401  (loads scipy's OpenBLAS before the inventory)
from threadpoolctl import ThreadpoolController


@lru_cache(maxsize=1)
def _controller() -> ThreadpoolController:
    return ThreadpoolController()


def single_blas_thread() -> AbstractContextManager[Any]:
    """Limit every loaded BLAS (numpy's and scipy's) to one thread.

    Use as a context manager; the limit applies as soon as this is called, so calling it
    alone sets it for the rest of the process (a worker's initialiser).
    """
    return _controller().limit(limits=1, user_api="blas")  # type: ignore[no-any-return]
