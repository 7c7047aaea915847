"""Compile formtwin's Numba kernels into their on-disk cache, once, before the processes
that use them start.

The kernels are ``@njit(cache=True)``: the first process that calls one compiles it for the
argument types of the call and writes the machine code to the package's ``__pycache__``;
later processes load it in milliseconds. In a fresh clone, two pytest workers (and the
services and commands the tests start) that reach a kernel at about the same time each
compile it, the bending model's ~60 s of CPU among them. ``make test`` runs this script
beside the lint, so the tests load the kernels instead. The calls are those of the
package's own code paths: one bending run at the centre of the design, tracker steps on
the bundled metamodel with the deviation model, a GLR chart update.

Usage: ``python scripts/compile_kernels.py`` (prints what it compiled and the time it took).
"""

from __future__ import annotations

import time

import numpy as np


def main() -> None:
    """Call each kernel family once; print the time each took."""
    t0 = time.perf_counter()
    from formtwin.physics.bending import BendingModel

    model = BendingModel()
    run = model.run(model.centre())
    t1 = time.perf_counter()
    print(f"bending model kernels: {t1 - t0:.1f} s (centre run ok: {run.ok})")

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
    print(f"metamodel and deviation kernels: {t2 - t1:.1f} s")

    from formtwin.monitoring.glr import Glr, GlrState

    chart = Glr(signature=(1.0, 0.5), h=5.0, window=20)
    state = GlrState()
    for z in (0.1, -0.2, 0.3):
        state, _ = chart.update(state, z)
    print(f"GLR kernel: {time.perf_counter() - t2:.1f} s")


if __name__ == "__main__":
    main()
