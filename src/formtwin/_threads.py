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

import ctypes
import threading
from contextlib import AbstractContextManager
from functools import lru_cache
from typing import Any

import scipy.linalg  # noqa: F401  (loads scipy's OpenBLAS before the inventory)
from threadpoolctl import ThreadpoolController


@lru_cache(maxsize=1)
def _controller() -> ThreadpoolController:
    return ThreadpoolController()


class _SingleThread(AbstractContextManager[Any]):
    """The limit of :func:`single_blas_thread`: set by the outermost one (counted over the
    process, as BLAS's thread count is), restored when that one exits."""

    depth = 0  # limits in force; one set without ``with`` stays forever
    _lock = threading.Lock()

    def __init__(self) -> None:
        with self._lock:
            cls = type(self)
            self.limit = None if cls.depth else _controller().limit(limits=1, user_api="blas")
            cls.depth += 1

    def __exit__(self, *exc: object) -> None:
        with self._lock:
            cls = type(self)
            cls.depth -= 1
            if self.limit is not None:
                self.limit.restore_original_limits()


def single_blas_thread() -> AbstractContextManager[Any]:
    """Limit every loaded BLAS (numpy's and scipy's) to one thread.

    Use as a context manager; the limit applies as soon as this is called, so calling it
    alone sets it for the rest of the process (a worker's initialiser). Inside another's
    limit it costs nothing (a counter; ~0.1 ms per entry and exit otherwise, twice per
    product in the metamodel's predictions).
    """
    return _SingleThread()


#: glibc ``mallopt`` parameters and the values :func:`retain_heap` sets: arrays below
#: 32 MiB come from the heap, and up to 128 MiB of freed heap stays with the process
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3
_TRIM_BYTES, _MMAP_BYTES = 128 << 20, 32 << 20


@lru_cache(maxsize=1)
def retain_heap() -> bool:
    """Keep freed memory in the process (glibc) instead of handing it back to the system
    after every product; returns whether the setting took (False off glibc).

    A filter step allocates and frees a few (N, n_centres) float32 blocks of ~1-2 MB
    (the metamodel's kernel matrix at N = 500). glibc returns the freed top of the heap
    to the system once more than its trim threshold is free, so every step paid the
    page faults of fresh memory again: the metamodel's curve evaluation took 2.2 ms
    instead of 1.1 ms. Fixed thresholds stop that (and glibc's dynamic adjustment of
    them). Numbers are unchanged; the process keeps up to 128 MiB it no longer uses.
    Once per process (later calls return the first result).
    """
    try:
        libc = ctypes.CDLL("libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):  # not glibc
        return False
    return bool(mallopt(_M_TRIM_THRESHOLD, _TRIM_BYTES)) and bool(
        mallopt(_M_MMAP_THRESHOLD, _MMAP_BYTES))
