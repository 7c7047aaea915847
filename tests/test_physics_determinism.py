"""The bending model gives bit-identical outputs whether its kernels are freshly compiled or
loaded from Numba's on-disk cache (0.1.0.dev12: with ``reassoc``/``contract`` fast-math flags
the two differed by up to 0.006 N, because the cached caller runs its own re-optimised copy
of a callee where the fresh process calls the callee's separately compiled code).

The fresh compile is ~50 s of CPU. ``make test`` makes it once before the tests
(``scripts/compile_kernels.py`` compiles the kernels into the package's cache and, when it
compiled them afresh, records the runs below from that process); with that record, of the
sources and libraries as they are, this test runs only a process that loads the cache.
Without it, it compiles afresh itself, into a cache folder of its own."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("numba")

#: runs the model at the centre and on 3 Latin-hypercube points (the points
#: scripts/compile_kernels.py records); saves curves and angles, prints the kernels'
#: Numba cache hits and misses
SCRIPT = """
import json, sys
import numpy as np
from numba.core.registry import CPUDispatcher
from formtwin.doe import latin_hypercube
from formtwin.physics.bending import BendingModel, contact, faces, kernels, solver
m = BendingModel()
X = np.vstack([m.centre(), latin_hypercube(m.spec, 3, seed=1)])
runs = [m.run(x) for x in X]
np.savez(sys.argv[1], curves=np.array([r.curve for r in runs]),
         angles=np.array([r.angles for r in runs]), ok=np.array([r.ok for r in runs]))
ds = [k for mod in (contact, faces, kernels, solver) for k in vars(mod).values()
      if isinstance(k, CPUDispatcher)]
print(json.dumps({"hits": sum(sum(d.stats.cache_hits.values()) for d in ds),
                  "misses": sum(sum(d.stats.cache_misses.values()) for d in ds)}))
"""


def _run(out: Path, cache: Path | None) -> tuple[dict[str, np.ndarray], dict[str, int]]:
    """The runs of SCRIPT in a new process (its Numba cache ``cache``, None: the package's)
    and its kernels' cache hits and misses."""
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    env.pop("NUMBA_DISABLE_JIT", None)
    if cache is not None:
        env["NUMBA_CACHE_DIR"] = str(cache)
    proc = subprocess.run([sys.executable, "-c", SCRIPT, str(out)], env=env,
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    with np.load(out) as f:
        return {k: f[k] for k in f.files}, json.loads(proc.stdout.strip().splitlines()[-1])


def _recorded_fresh_runs() -> dict[str, np.ndarray] | None:
    """The runs scripts/compile_kernels.py recorded from a fresh compile into the
    package's cache, if that record is of the sources and libraries as they are now."""
    import numba

    from formtwin.physics.bending import _cache

    record = _cache.PACKAGE / "__pycache__" / "fresh_compile_runs.npz"
    if os.environ.get("NUMBA_CACHE_DIR") or not record.exists():
        return None
    key = f"{_cache.sources_digest()} numba {numba.__version__} numpy {np.__version__} " \
        f"python {sys.version}"
    with np.load(record) as f:
        return {k: f[k] for k in f.files if k != "key"} if str(f["key"]) == key else None


def test_fresh_compile_equals_cached_code(tmp_path: Path) -> None:
    fresh = _recorded_fresh_runs()
    if fresh is None:  # compile afresh here, into an empty cache of this test's own
        cache: Path | None = tmp_path / "numba_cache"
        assert cache is not None
        cache.mkdir()
        fresh, counts = _run(tmp_path / "fresh.npz", cache)
        assert counts["hits"] == 0 and counts["misses"] > 0, counts
        assert any(cache.rglob("*.nbc")), "the first process wrote no Numba cache"
    else:  # compiled afresh into the package's cache by scripts/compile_kernels.py
        cache = None
    cached, counts = _run(tmp_path / "cached.npz", cache)  # loads the compiled code
    assert counts["hits"] > 0 and counts["misses"] == 0, counts  # nothing compiled again
    assert fresh["ok"].all()
    np.testing.assert_array_equal(cached["curves"], fresh["curves"])
    np.testing.assert_array_equal(cached["angles"], fresh["angles"])
