"""Compile formtwin's Numba kernels into their on-disk cache, once, before the processes
that use them start.

The kernels are ``@njit(cache=True)``: the first process that calls one compiles it for the
argument types of the call and writes the machine code to the package's ``__pycache__``;
later processes load it in milliseconds. In a fresh clone, two pytest workers (and the
services and commands the tests start) that reach a kernel at about the same time each
compile it, the bending model's ~60 s of CPU among them. ``make test`` runs this script
beside the lint, so the tests load the kernels instead. The calls are those of the
package's own code paths: one bending run at the centre of the design, tracker steps on
the bundled metamodel with the deviation model (the metamodel's and the deviation's
kernels, and the tracker's own: ``formtwin.tracker._kernels``), a GLR chart update, a
monitor's charted product (``formtwin.monitoring.bank``) and the sensor fusion's kernels
(``formtwin.tracker._fusion_kernels``).

Usage: ``python scripts/compile_kernels.py`` (prints what it compiled and the time it took).
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np


def kernel_cache_counts() -> tuple[int, int]:
    """Numba's on-disk cache hits and misses of this process's bending kernels so far."""
    import importlib

    from numba.core.registry import CPUDispatcher

    hits = misses = 0
    for name in ("contact", "faces", "kernels", "solver"):
        module = importlib.import_module(f"formtwin.physics.bending.{name}")
        for kernel in vars(module).values():
            if isinstance(kernel, CPUDispatcher):
                hits += sum(kernel.stats.cache_hits.values())
                misses += sum(kernel.stats.cache_misses.values())
    return hits, misses


def record_fresh_runs(model: Any) -> None:
    """When this process compiled the bending kernels afresh into the package's cache
    (no cache hit, no ``NUMBA_CACHE_DIR``), write the runs that
    ``tests/test_physics_determinism.py`` compares with a process loading that cache (the
    centre and 3 Latin-hypercube points of seed 1) to ``__pycache__/fresh_compile_runs.npz``
    beside the kernels, keyed by their sources and the library versions; the test then
    runs only the loading process instead of compiling again (~50 s)."""
    import os
    import sys

    import numba

    from formtwin.doe import latin_hypercube
    from formtwin.physics.bending import _cache

    hits, misses = kernel_cache_counts()
    record = _cache.PACKAGE / "__pycache__" / "fresh_compile_runs.npz"
    record.unlink(missing_ok=True)
    if hits or not misses or os.environ.get("NUMBA_CACHE_DIR"):
        return
    spec = model.spec
    X = np.vstack([model.centre(), latin_hypercube(spec, 3, seed=1)])
    runs = [model.run(x) for x in X]
    key = f"{_cache.sources_digest()} numba {numba.__version__} numpy {np.__version__} " \
        f"python {sys.version}"
    np.savez(record, key=np.array(key), curves=np.array([r.curve for r in runs]),
             angles=np.array([r.angles for r in runs]), ok=np.array([r.ok for r in runs]))
    print(f"bending model: compiled afresh ({misses} kernels), runs recorded")


def main() -> None:
    """Call each kernel family once; print the time each took."""
    t0 = time.perf_counter()
    from formtwin.physics.bending import BendingModel

    model = BendingModel()
    run = model.run(model.centre())
    t1 = time.perf_counter()
    print(f"bending model kernels: {t1 - t0:.1f} s (centre run ok: {run.ok})")
    record_fresh_runs(model)

    from formtwin.defaults import bundled_metamodel
    from formtwin.metamodel import Metamodel
    from formtwin.tracker import TrackerConfig, build_tracker

    mm = Metamodel.load(bundled_metamodel("bending"))
    curves = mm.predict_curves(np.tile(mm.spec.inputs.lo + 0.5 * (mm.spec.inputs.hi
                                                                  - mm.spec.inputs.lo), (2, 1)))
    for deviation in (False, True):
        tracker = build_tracker(mm, TrackerConfig(n_particles=50, n_mc=100,
                                                  estimate_deviation=deviation))
        for curve in curves:
            tracker.step(curve)
    t2 = time.perf_counter()
    print(f"metamodel, deviation and tracker kernels: {t2 - t1:.1f} s")

    from formtwin.monitoring.episodes import run_lengths
    from formtwin.monitoring.glr import Glr, GlrState, glr_statistics

    chart = Glr(signature=(1.0, 0.5), h=5.0, window=20)
    state = GlrState()
    for z in (0.1, -0.2, 0.3):
        state, _ = chart.update(state, z)
    run_lengths(chart, 1.0, runs=4, horizon=3)  # the clear-after's kernel
    glr_statistics((1.0, 0.5), 20, np.zeros((2, 3)))  # the threshold's simulation
    print(f"GLR kernels: {time.perf_counter() - t2:.1f} s")

    t3 = time.perf_counter()
    from formtwin.monitoring.bank import load_kernels as chart_kernels
    from formtwin.monitoring.charts import Cusum
    from formtwin.monitoring.incontrol import InControl, Reference
    from formtwin.monitoring.monitor import Monitor, MonitorConfig
    from formtwin.tracker._fusion_kernels import load_kernels as fusion_kernels

    ref = Reference(tuple(np.linspace(-2.0, 2.0, 21)))
    chart_kernels(Monitor(MonitorConfig(
        {"x": InControl(0.0, 1.0, (0.5,), tuple(np.linspace(-2.0, 2.0, 21)))},
        {"ess": ref}, {"ess": InControl(0.0, 1.0)}, mismatch=Cusum(1.0, 5.0, "high"),
        glr={"x": chart})))
    fusion_kernels()
    print(f"chart and sensor fusion kernels: {time.perf_counter() - t3:.1f} s")


if __name__ == "__main__":
    main()
