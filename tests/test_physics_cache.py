"""The bending kernels' Numba cache follows their sources (formtwin.physics.bending._cache)."""

from __future__ import annotations

from pathlib import Path

from formtwin.physics.bending import _cache


def test_cache_files_go_when_any_source_changes(tmp_path: Path) -> None:
    (tmp_path / "kernels.py").write_text("x = 1\n")
    (tmp_path / "solver.py").write_text("y = 2\n")
    cache = tmp_path / "__pycache__"
    cache.mkdir()
    for name in ("solver.run-1.py311.nbi", "solver.run-1.py311.1.nbc", "solver.cpython-311.pyc"):
        (cache / name).write_bytes(b"old")
    assert _cache.sync_cache(tmp_path) == 2  # no stamp: Numba's files go, Python's stay
    assert sorted(p.name for p in cache.iterdir()) == [_cache.STAMP, "solver.cpython-311.pyc"]
    (cache / "solver.run-1.py311.nbi").write_bytes(b"new")  # compiled from these sources
    assert _cache.sync_cache(tmp_path) == 0 and (cache / "solver.run-1.py311.nbi").exists()
    # a callee's file changes, the caller's does not: the caller's cache goes too
    (tmp_path / "kernels.py").write_text("x = 3\n")
    assert _cache.sync_cache(tmp_path) == 1 and not (cache / "solver.run-1.py311.nbi").exists()
    assert (cache / _cache.STAMP).read_text() == _cache.sources_digest(tmp_path)


def test_the_package_cache_is_stamped_with_its_sources() -> None:
    import formtwin.physics.bending  # noqa: F401  (the import syncs)

    stamp = _cache.PACKAGE / "__pycache__" / _cache.STAMP
    assert stamp.read_text() == _cache.sources_digest()
