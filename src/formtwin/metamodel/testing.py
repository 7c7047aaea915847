"""Small DOE datasets from the closed-form stand-in, for tests, doctests and benchmarks.

>>> data = analytic_dataset(50, seed=0)
>>> data.inputs.shape, data.curves.shape, int(data.ok.sum())
((50, 10), (50, 101), 50)
"""

from __future__ import annotations

import numpy as np
from scipy.stats import qmc

from formtwin.dataset import DoeDataset
from formtwin.physics.analytic import AnalyticBending
from formtwin.spec import ProcessSpec, load_spec


def analytic_dataset(n: int, seed: int = 0, spec: ProcessSpec | None = None,
                     failure_clearance: float | None = None) -> DoeDataset:
    """A seeded Latin hypercube of ``n`` points in the spec's box, run on the stand-in.

    ``failure_clearance`` (mm) makes some runs fail (see
    :class:`~formtwin.physics.analytic.AnalyticBending`); they are kept with ``ok=False``.
    """
    spec = spec or load_spec()
    sim = AnalyticBending(spec, failure_clearance=failure_clearance)
    U = qmc.LatinHypercube(d=spec.n_inputs, rng=np.random.default_rng(seed)).random(n)
    X = qmc.scale(U, spec.inputs.lo, spec.inputs.hi)
    curves, angles = sim.run_batch(X)
    ok = np.all(np.isfinite(curves), axis=1)
    reason = np.array(["" if good else sim.failure_reason(x)
                       for x, good in zip(X, ok, strict=True)])
    return DoeDataset(spec=spec, inputs=X, curves=curves, angles=angles, ok=ok,
                      reason=reason, model_version=sim.version)
