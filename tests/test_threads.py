"""retain_heap: freed temporaries of the filter step stay in the process (no page faults
per product); the numbers do not depend on it."""

from __future__ import annotations

import ctypes
import platform

import numpy as np
import pytest

from formtwin._threads import retain_heap


class _MallInfo2(ctypes.Structure):
    _fields_ = [(name, ctypes.c_size_t) for name in (
        "arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks", "fsmblks", "uordblks",
        "fordblks", "keepcost")]


def _glibc() -> ctypes.CDLL | None:
    if platform.system() != "Linux":
        return None
    try:
        libc = ctypes.CDLL("libc.so.6")
        libc.mallinfo2.restype = _MallInfo2
    except (OSError, AttributeError):
        return None
    return libc


def test_retain_heap_keeps_freed_blocks() -> None:
    libc = _glibc()
    if libc is None:
        pytest.skip("needs glibc >= 2.33 (mallinfo2)")
    assert retain_heap() is True
    assert retain_heap() is True  # once per process
    before = libc.mallinfo2()
    block = np.ones(1 << 20)  # 8 MB: from the heap (below the 32 MiB mmap threshold)
    grown = libc.mallinfo2()
    assert grown.hblkhd == before.hblkhd  # not a mapping of its own
    assert grown.arena >= before.arena
    del block
    after = libc.mallinfo2()
    assert after.arena == grown.arena  # freed, but not handed back to the system


def test_single_blas_thread_nests_and_restores() -> None:
    """The outermost limit sets one BLAS thread and restores the count on exit; the
    nested ones change nothing (and cost nothing)."""
    from threadpoolctl import threadpool_info

    from formtwin._threads import _SingleThread, single_blas_thread

    def blas_threads() -> list[int]:
        return [p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas"]

    if not blas_threads():
        pytest.skip("no BLAS thread pool found")
    before, depth = blas_threads(), _SingleThread.depth
    with single_blas_thread() as outer:
        assert blas_threads() == [1] * len(before)
        with single_blas_thread() as inner:
            assert inner.limit is None and _SingleThread.depth == depth + 2
            assert blas_threads() == [1] * len(before)
        assert blas_threads() == [1] * len(before)  # the inner exit restored nothing
        assert (outer.limit is None) == (depth > 0)
    assert _SingleThread.depth == depth
    assert blas_threads() == before


def test_a_tracker_is_built_alike_whatever_threads_blas_has(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """The measurement model (``K_MC``: a product of 10 000 Monte-Carlo curves) is made with
    one BLAS thread inside :func:`~formtwin.tracker.build_measurement`: the same numbers,
    bit for bit, whether the caller's BLAS has one thread or two (a multi-threaded product
    sums in another order)."""
    from threadpoolctl import threadpool_limits

    from formtwin._threads import _SingleThread
    from formtwin.defaults import bundled_metamodel
    from formtwin.metamodel import Metamodel
    from formtwin.tracker import TrackerConfig, build_measurement

    model = Metamodel.load(bundled_metamodel("bending"))
    monkeypatch.setattr(_SingleThread, "depth", 0)  # no outer limit (the session holds one)
    made = []
    for threads in (1, 2):
        with threadpool_limits(limits=threads, user_api="blas"):
            made.append(build_measurement(model, TrackerConfig()).covariance())
    assert np.array_equal(made[0], made[1])
