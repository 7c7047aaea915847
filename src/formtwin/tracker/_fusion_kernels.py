"""Numba kernels of a sensor value's fusion (:meth:`~formtwin.tracker.SensorFusion.fuse`)
and of the final angle's issued interval (:meth:`~formtwin.tracker.SensorFusion.issue_final`).

:func:`normal_reweight` replaces the ~12 NumPy calls on the particles' (N,) arrays that
multiply a Normal likelihood into the log-weights (``norm.logpdf``'s operations, the
non-finite likelihoods set to zero, the sum and its maximum) with one pass of the same
float operations in their order; NumPy's ``exp`` and ``log`` stay NumPy's (the caller
normalises), so the weights are the same numbers bit for bit
(``tests/test_fusion.py``). :func:`weighted_moments` (the particles' weighted mean and
variance of their final angles), :func:`mixture_forecast` (the camera discrepancy's
prediction) and :func:`discrepancy_update` (its update by a camera value) are one pass
each instead of 7, 14 and ~30 NumPy calls: the same formula
summed in another order (a ratio of sums instead of normalised weights' dot products), so
their numbers agree with NumPy's to rounding (``tests/test_final_angles.py``,
``tests/test_angle_discrepancy.py``) and are
deterministic: a restored tracker issues the same intervals bit for bit. No fast-math.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def normal_reweight(logw, pred, value, sd, c, log_sd):  # type: ignore[no-untyped-def]
    """``new = logw + ll`` (N,) with ``ll = -((value - pred) / sd)^2 / 2 - c - log_sd``
    (``c = log sqrt(2 pi)``), a NaN or ``+inf`` ``ll`` taken as ``-inf`` (zero
    likelihood); returns ``new``, its maximum (NaN if it has a NaN, as ``np.max``) and
    whether any of it is finite."""
    n = pred.size
    new = np.empty(n)
    top = -np.inf
    nan = False
    finite = False
    for k in range(n):
        z = (value - pred[k]) / sd
        ll = -(z * z) / 2.0 - c - log_sd
        if ll != ll or ll == np.inf:
            ll = -np.inf
        v = logw[k] + ll
        new[k] = v
        if v != v:
            nan = True
        elif v > top:
            top = v
        if np.isfinite(v):
            finite = True
    return new, (np.nan if nan else top), finite


@njit(cache=True)
def weighted_moments(logw, a):  # type: ignore[no-untyped-def]
    """Mean and variance of ``a`` (N,) under the weights ``exp(logw)`` (N,) normalised:
    ``sum w a / sum w`` and ``sum w (a - mean)^2 / sum w`` with ``w = exp(logw - max)``
    (NaN, NaN if ``logw`` has a NaN; a NaN of ``a`` makes them NaN)."""
    n = logw.size
    top = -np.inf
    for k in range(n):
        if logw[k] != logw[k]:
            return np.nan, np.nan
        if logw[k] > top:
            top = logw[k]
    w = np.empty(n)
    total = 0.0
    mean = 0.0
    for k in range(n):
        w[k] = np.exp(logw[k] - top)
        total += w[k]
        mean += w[k] * a[k]
    mean /= total
    var = 0.0
    for k in range(n):
        d = a[k] - mean
        var += w[k] * d * d
    return mean, var / total


@njit(cache=True)
def mixture_forecast(a, C, S, n, logw, delta, ref, model_angle):  # type: ignore[no-untyped-def]
    """The camera discrepancy's predicted measured angle for the model's ``model_angle``
    (:meth:`~formtwin.tracker.angle_discrepancy.AngleDiscrepancy.predict`): per hypothesis
    ``h`` (``a`` (H, 2), ``C`` (H, 2, 2), ``S``, ``n``, ``logw``, ``delta`` (H,)) the
    forecast ``f = ref + a F`` and ``Q = F^T (C / delta) F + S`` with ``F = (1, model_angle
    - ref)``, the Student-t variance ``Q n / max(n - 2, 1)``; the mixture's mean and
    variance under the weights ``exp(logw)`` normalised, in one pass."""
    x = model_angle - ref
    top = -np.inf
    for h in range(logw.size):
        if logw[h] > top:
            top = logw[h]
    total = 0.0
    mean = 0.0
    w = np.empty(logw.size)
    f = np.empty(logw.size)
    v = np.empty(logw.size)
    for h in range(logw.size):
        w[h] = np.exp(logw[h] - top)
        total += w[h]
        f[h] = ref + (a[h, 0] + a[h, 1] * x)
        d = delta[h]
        q = (C[h, 0, 0] / d + C[h, 0, 1] / d * x + C[h, 1, 0] / d * x
             + C[h, 1, 1] / d * x * x + S[h])
        v[h] = q * n[h] / max(n[h] - 2.0, 1.0)
        mean += w[h] * f[h]
    mean /= total
    var = 0.0
    for h in range(logw.size):
        e = f[h] - mean
        var += w[h] * (v[h] + e * e)
    return mean, var / total


@njit(cache=True)
def discrepancy_update(a, C, S, n, n1, logw, delta, ref, model_angle, value, g):  # type: ignore[no-untyped-def]
    """One measured ``value`` of a product whose model angle was ``model_angle``
    (:meth:`~formtwin.tracker.angle_discrepancy.AngleDiscrepancy.update`): per hypothesis
    the forecast (:func:`mixture_forecast`'s ``f``, ``Q``), the Student-t log density of
    ``value`` (``g = gammaln((n + 1) / 2) - gammaln(n / 2)`` (H,) given), the conjugate
    update of ``a``, ``C``, ``S`` (``n1 = n + 1``), and the weights times the density,
    normalised. Returns the new ``a``, ``C``, ``S``, ``logw`` and the log evidence."""
    x = model_angle - ref
    h_n = S.size
    a1 = np.empty((h_n, 2))
    c1 = np.empty((h_n, 2, 2))
    s1 = np.empty(h_n)
    lw = np.empty(h_n)
    top = -np.inf
    nan = False
    for h in range(h_n):
        d = delta[h]
        r00, r01, r10, r11 = C[h, 0, 0] / d, C[h, 0, 1] / d, C[h, 1, 0] / d, C[h, 1, 1] / d
        f = ref + (a[h, 0] + a[h, 1] * x)
        q = r00 + r01 * x + r10 * x + r11 * x * x + S[h]
        e = value - f
        m = n[h]
        ll = (g[h] - 0.5 * np.log(m * np.pi * q)
              - (m + 1.0) / 2.0 * np.log1p(e * e / (m * q)))
        s1[h] = S[h] + S[h] / n1[h] * (e * e / q - 1.0)
        g0 = (r00 + r01 * x) / q  # the gain R F / Q
        g1 = (r10 + r11 * x) / q
        a1[h, 0] = a[h, 0] + g0 * e
        a1[h, 1] = a[h, 1] + g1 * e
        k = s1[h] / S[h]
        c1[h, 0, 0] = k * (r00 - g0 * g0 * q)
        c1[h, 0, 1] = k * (r01 - g0 * g1 * q)
        c1[h, 1, 0] = k * (r10 - g1 * g0 * q)
        c1[h, 1, 1] = k * (r11 - g1 * g1 * q)
        lw[h] = logw[h] + ll
        if lw[h] != lw[h]:
            nan = True
        elif lw[h] > top:
            top = lw[h]
    if nan:
        top = np.nan
    total = 0.0
    for h in range(h_n):
        total += np.exp(lw[h] - top)
    norm = top + np.log(total)
    for h in range(h_n):
        lw[h] = lw[h] - norm
    return a1, c1, s1, lw, norm


def load_kernels() -> None:
    """Load the kernels now (from Numba's cache, ~10 ms; compiled, seconds) for the
    argument types the tracker passes (contiguous and strided columns), not at the first
    camera value: a service calls it at its start, so that value's latency is like the
    others'."""
    w = np.zeros(2)
    column = np.zeros((2, 2))[:, 0]
    for pred in (w, column):
        normal_reweight(w, pred, 0.0, 1.0, 0.0, 0.0)
        weighted_moments(w, pred)
    h = np.ones(1)
    a, c = np.zeros((1, 2)), np.zeros((1, 2, 2))
    mixture_forecast(a, c, h, h, h, h, 0.0, 0.0)
    discrepancy_update(a, c, h, h, h, h, h, 0.0, 0.0, 0.0, h)


__all__ = ["discrepancy_update", "load_kernels", "mixture_forecast", "normal_reweight",
           "weighted_moments"]
