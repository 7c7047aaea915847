"""BLAS thread control for hot paths.

numpy and scipy each ship their own OpenBLAS; on a 2-core machine the two thread pools
contend and made small matrix products 3-5x slower in our measurements. The particle filter
and metamodel evaluate many small products per product step, where one BLAS thread is
fastest, and parallelism comes from running independent filters in separate processes.
Hot paths therefore run inside :func:`single_blas_thread`; everything else leaves BLAS alone.
"""

from __future__ import annotations

from contextlib import AbstractContextManager
from typing import Any

from threadpoolctl import threadpool_limits


def single_blas_thread() -> AbstractContextManager[Any]:
    """Context manager limiting every loaded BLAS (numpy's and scipy's) to one thread."""
    return threadpool_limits(limits=1, user_api="blas")  # type: ignore[no-any-return]
