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
