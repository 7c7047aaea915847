"""Can the model explain a curve at all? The best fit over the whole augmented box.

A run of curves that the filter's cloud does not explain (:mod:`formtwin.tracker.fit`) has
two causes that call for different actions: the *model* cannot produce such a curve for
any state and parameters (a metamodel of another press, a dead sensor, wrong units), or
the *filter* has not found the state yet (start-up, a large process change, a cloud stuck
in a wrong mode of theta_d). :func:`best_distance2` tells them apart: the smallest squared
Mahalanobis distance of the curve, under the likelihood's covariance, over every
``[x, theta, theta_d]`` in the spec's bounds, by bounded least squares
(``scipy.optimize.least_squares``, trust-region reflective) on the whitened residual
``L^-1 (obs - model)`` (``Sigma = L L^T``) from a few starting points. If it is within the
measurement model's 99.9 % quantile the model can explain the curve.

It is a local search: a curve that the model could explain from a point far from every
start may be reported as unexplained (the error is on the side of reporting a mismatch).
Cost: about ``max_nfev`` evaluations of ``d + 1`` model curves per start (tens of ms for
the bundled metamodel), and the service calls it only when its mismatch rule fires.

>>> import numpy as np
>>> from formtwin.defaults import analytic_model
>>> from formtwin.tracker import TrackerConfig, build_tracker
>>> model = analytic_model(); spec = model.spec
>>> tr = build_tracker(model, TrackerConfig(n_particles=50, estimate_deviation=False,
...                                         n_mc=500))
>>> x = spec.inputs.lo + 0.3 * (spec.inputs.hi - spec.inputs.lo)
>>> y = model.predict_curves(x[None])[0]
>>> starts = default_starts(tr.ssm, spec.augmented.lo + 0.5 * (spec.augmented.hi
...                                                            - spec.augmented.lo))
>>> best_distance2(tr.ssm, y, starts) < 1.0, best_distance2(tr.ssm, 3 * y, starts) > 1e3
(True, True)
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray
from scipy.linalg import cholesky, solve_triangular

from formtwin.tracker.ssm import BendingSSM

FloatArray = NDArray[np.float64]


def default_starts(ssm: BendingSSM, mean: FloatArray | None = None, n_box: int = 4,
                   seed: int = 0) -> FloatArray:
    """Starting points (S, 18): the posterior mean (if given), the box centre and ``n_box``
    scrambled Sobol points of the box (seeded, so the result is reproducible)."""
    lo, hi = ssm.spec.augmented.lo, ssm.spec.augmented.hi
    pts = [lo + 0.5 * (hi - lo)]
    if mean is not None and np.all(np.isfinite(mean)):
        pts.insert(0, np.clip(np.asarray(mean, dtype=np.float64), lo, hi))
    if n_box > 0:
        from scipy.stats import qmc  # on use: ~1.3 s CPU to import

        u = qmc.Sobol(lo.size, scramble=True, rng=np.random.default_rng(seed)).random(n_box)
        pts.extend(lo + u * (hi - lo))
    return np.array(pts)


def best_distance2(ssm: BendingSSM, y: FloatArray, starts: FloatArray,
                   target: float = 0.0, max_nfev: int = 40, scale: float = 1.0) -> float:
    """Smallest squared Mahalanobis distance of curve ``y`` (n_t,) N over the box.

    Parameters
    ----------
    ssm : the tracker's state-space model (model, deviation, likelihood, bounds).
    y : the measured curve.
    starts : (S, 18) starting points, tried in order.
    target : stop as soon as a start reaches a distance at or below it.
    max_nfev : function evaluations per start.
    scale : factor on the likelihood's covariance (the learned scale; else 1).
    """
    spec = ssm.spec
    lo, hi = spec.augmented.lo.copy(), spec.augmented.hi.copy()
    k = spec.n_inputs if not ssm.config.estimate_deviation else lo.size
    lo, hi = lo[:k], hi[:k]
    span = hi - lo
    chol = cholesky(scale * ssm.measurement.covariance(), lower=True)
    y = np.asarray(y, dtype=np.float64)

    def whitened(P: FloatArray) -> FloatArray:
        full = np.zeros((P.shape[0], ssm.n_aug))
        full[:, :k] = P
        r = ssm.residuals(full, y)
        out: FloatArray = solve_triangular(chol, r.T, lower=True).T
        return np.where(np.isfinite(out), out, 1e6)

    def jac(p: FloatArray) -> FloatArray:
        h = 1e-4 * span
        h = np.where(p + h > hi, -h, h)
        f = whitened(np.vstack([p, p + np.diag(h)]))
        out: FloatArray = ((f[1:] - f[0]) / h[:, None]).T
        return out

    from scipy.optimize import least_squares  # on use: ~0.2 s CPU to import

    best = math.inf
    eps = 1e-9 * span
    for x0 in np.atleast_2d(starts):
        p0 = np.clip(x0[:k], lo + eps, hi - eps)
        sol = least_squares(lambda p: whitened(p[None])[0], p0, jac=jac, bounds=(lo, hi),
                            x_scale=span, max_nfev=max_nfev, method="trf")
        best = min(best, 2.0 * float(sol.cost))
        if best <= target:
            break
    return best


__all__ = ["best_distance2", "default_starts"]
