"""The bending model gives bit-identical outputs whether its kernels are freshly compiled or
loaded from Numba's on-disk cache (0.1.0.dev12: with ``reassoc``/``contract`` fast-math flags
the two differed by up to 0.006 N, because the cached caller runs its own re-optimised copy
of a callee where the fresh process calls the callee's separately compiled code)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("numba")

#: runs the model at the centre and on 3 Latin-hypercube points; saves curves and angles
SCRIPT = """
import sys
import numpy as np
from formtwin.doe import latin_hypercube
from formtwin.physics.bending import BendingModel
m = BendingModel()
X = np.vstack([m.centre(), latin_hypercube(m.spec, 3, seed=1)])
runs = [m.run(x) for x in X]
np.savez(sys.argv[1], curves=np.array([r.curve for r in runs]),
         angles=np.array([r.angles for r in runs]), ok=np.array([r.ok for r in runs]))
"""


def _run(out: Path, cache: Path) -> dict[str, np.ndarray]:
    env = {**os.environ, "NUMBA_CACHE_DIR": str(cache), "OMP_NUM_THREADS": "1"}
    env.pop("NUMBA_DISABLE_JIT", None)
    proc = subprocess.run([sys.executable, "-c", SCRIPT, str(out)], env=env,
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    with np.load(out) as f:
        return {k: f[k] for k in f.files}


def test_fresh_compile_equals_cached_code(tmp_path: Path) -> None:
    cache = tmp_path / "numba_cache"
    cache.mkdir()
    fresh = _run(tmp_path / "fresh.npz", cache)  # empty cache: compiles and writes it
    assert any(cache.rglob("*.nbc")), "the first process wrote no Numba cache"
    cached = _run(tmp_path / "cached.npz", cache)  # loads the compiled code from the cache
    assert fresh["ok"].all()
    np.testing.assert_array_equal(cached["curves"], fresh["curves"])
    np.testing.assert_array_equal(cached["angles"], fresh["angles"])
