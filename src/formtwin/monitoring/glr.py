"""GLR chart for an additive (level) change of an autoregressive quantity, in the residuals of
its in-control model (Basseville & Nikiforov, *Detection of Abrupt Changes*, 1993, ch. 7-8:
additive changes in AR models; Lai 1995; Lai & Shan 1999: window-limited GLR).

A quantity ``y`` with the in-control AR(p) model ``y_i - m = sum_l phi_l (y_{i-l} - m) + e_i``
whose *level* steps by ``delta`` at product ``tau`` (``y`` and its mean move together) shows
in the one-step residuals not a constant shift but a *signature*: at lag ``j`` after the
change the residual's mean moves by ``delta s_j`` with

    s_j = 1 - sum_{l <= min(j, p)} phi_l        (s_0 = 1: the jump; then the lasting shift),

a spike followed by a small lasting shift (``rho`` = 0.9: 4.6 and 0.46 innovation sigmas for a
2-sigma step of an AR(1) state). A CUSUM with a constant reference is matched to neither.
The generalised likelihood ratio of "a change of unknown size at an unknown product within
the last ``window``" against "no change", for standardised residuals ``z`` (N(0, 1)
independent in control), maximises over the change time ``tau`` the closed form over
``delta``::

    g_n = max_tau  (sum_{j=0}^{n-tau} s_j z_{tau+j})^2 / (2 sum_{j=0}^{n-tau} s_j^2)

and signals when ``g_n > h``. Both signs are covered (``delta`` is free). The numerators
for all candidate ``tau`` are kept as one array that each product shifts and updates in
``O(window)`` (:meth:`Glr.update`). After a signal the chart restarts.

Estimates that follow the state with a lag and only part of the way (a filter that expects
the state about its mean pulls a lasting offset back) leave another signature: it follows
from their response to a step of the true state (:func:`step_response`, fitted on simulated
in-control runs whose true states are known; :func:`response_signature`).

The threshold for an in-control average run length ``ARL0`` (:func:`glr_h`) is set by
simulating the statistic on independent N(0, 1) scores and extrapolating the rate of its
up-crossings of ``h`` with the large-``h`` form ``C h^a exp(-h)`` (for the GLR of a mean
change Siegmund & Venkatraman 1995 give ``a`` = 1/2 at one change time; fitted here):
fitted where the rate is measurable, solved where it is not. Scores may be clipped first
(``Glr.clip``: a bounded influence of any single product, as Huber's robust statistics).

>>> g = Glr(level_signature((0.9,)), h=10.0, window=50)
>>> tuple(round(v, 2) for v in g.signature)      # the jump, then 1 - rho
(1.0, 0.1)
>>> st, sig = g.update(GlrState(), 3.0)          # one residual of 3 sigma: 3^2 / 2
>>> round(sig.statistic, 2), sig.side
(4.5, '')
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np
from numba import njit
from numpy.typing import NDArray

from formtwin.monitoring.charts import Signal

FloatArray = NDArray[np.float64]


def level_signature(phi: Sequence[float]) -> tuple[float, ...]:
    """Residual signature ``(s_0, ..., s_p)`` (p + 1,) of a unit level step of an AR(p)
    quantity with coefficients ``phi``; ``s_j = s_p`` for ``j > p``."""
    return tuple(1.0 - float(np.sum(phi[:j])) for j in range(len(phi) + 1))


def step_response(estimates: Sequence[FloatArray], truths: Sequence[FloatArray], mean: float,
                  mu: float, length: int = 50) -> FloatArray:
    """Response ``g_j`` (length,) of the estimates of a state to a unit level step of the
    *true* state at lag 0 (estimates follow the state with a lag and, when the filter
    expects the state about ``mu``, only part of the way).

    Fitted on in-control runs whose true states are known (simulated): the ARX model
    ``y_i - m = b_1 (y_{i-1} - m) + b_2 (y_{i-2} - m) + c_0 (x_i - mu) + c_1 (x_{i-1} - mu)
    + c_2 (x_{i-2} - mu) + noise`` by least squares (each run (n_r,) of ``estimates`` with
    its true states ``truths`` (n_r,); ``m`` = ``mean``), run for ``x - mu`` = 1 from lag 0.
    """
    rows, target = [], []
    for y, x in zip(estimates, truths, strict=True):
        yc, xc = np.asarray(y, float) - mean, np.asarray(x, float) - mu
        rows.append(np.column_stack([yc[1:-1], yc[:-2], xc[2:], xc[1:-1], xc[:-2]]))
        target.append(yc[2:])
    a, t = np.vstack(rows), np.concatenate(target)
    ok = np.isfinite(t) & np.all(np.isfinite(a), axis=1)
    b = np.linalg.lstsq(a[ok], t[ok], rcond=None)[0]
    g = np.zeros(length + 2)  # g[j + 2] = response at lag j; zeros before the step
    for j in range(length):
        g[j + 2] = b[0] * g[j + 1] + b[1] * g[j] + b[2] + b[3] * (j >= 1) + b[4] * (j >= 2)
    return g[2:]


def response_signature(response: FloatArray, phi: Sequence[float]) -> tuple[float, ...]:
    """Residual signature of a step whose estimates respond by ``response`` (length,) (see
    :func:`step_response`), through the estimate's in-control AR model ``phi``: ``s_j = g_j
    - sum_l phi_l g_{j-l}``, scaled to a largest ``|s_j|`` of 1. (For estimates equal to
    the state, ``g_j`` = 1: :func:`level_signature`.)"""
    s = residual_response(response, phi)
    top = float(np.max(np.abs(s)))
    if not top > 0:
        raise ValueError("the estimates do not respond to the state: no GLR signature")
    return tuple(float(v) for v in s / top)


def residual_response(response: FloatArray, phi: Sequence[float]) -> FloatArray:
    """``s_j = g_j - sum_l phi_l g_{j-l}`` (len(response),), ``g`` = 0 before lag 0: the
    one-step residuals' mean after a step whose estimates respond by ``g``."""
    g = np.concatenate([np.zeros(len(phi)), np.asarray(response, dtype=np.float64)])
    p, n = len(phi), len(response)
    out: FloatArray = g[p:] - sum((c * g[p - lag: p - lag + n] for lag, c in enumerate(phi, 1)),
                                  np.zeros(n))
    return out


@dataclass(frozen=True)
class GlrState:
    """Numerators ``sum_j s_j z_{tau+j}`` by the change's age ``n - tau`` (0 .. window-1;
    empty: none yet) and the products since the (re)start ``i``."""

    sums: FloatArray = field(default_factory=lambda: np.zeros(0))
    i: int = 0


@dataclass(frozen=True)
class Glr:
    """Window-limited GLR chart for a change with residual signature ``signature``
    (``s_0, s_1, ...``; the last value holds for all later lags), threshold ``h`` on the
    log-likelihood ratio, change times within the last ``window`` products; ``clip``: each
    score is clipped to ``+-clip`` first (bounded influence of a single product; the
    threshold must be designed for the clipped scores, :func:`glr_h`)."""

    signature: tuple[float, ...]
    h: float
    window: int = 200
    clip: float | None = None

    def __post_init__(self) -> None:
        s = tuple(float(v) for v in self.signature)
        if not all(math.isfinite(v) for v in s) or not any(s):
            raise ValueError(f"GLR signature {s}: expected finite values, not all 0")
        if self.clip is not None and not self.clip > 0:
            raise ValueError(f"GLR clip = {self.clip}, expected > 0 or None")
        if not self.h > 0 or self.window < 1:
            raise ValueError(f"GLR h = {self.h}, window = {self.window}: expected > 0, >= 1")
        object.__setattr__(self, "signature", s)
        full = np.full(self.window, s[-1])
        full[: min(len(s), self.window)] = s[: self.window]
        object.__setattr__(self, "_s", full)
        # 2 sum_{j<=a} s_j^2 by age a; a lasting shift of 0 would give 0 beyond s: guard
        object.__setattr__(self, "_d2", 2.0 * np.maximum(np.cumsum(full * full), 1e-300))

    def update(self, state: GlrState, z: float) -> tuple[GlrState, Signal]:
        """The next state and the signal for standardised residual ``z``; the statistic is
        ``g_n``, signed by the estimated change's direction; restarted after a signal."""
        s: FloatArray = self._s  # type: ignore[attr-defined]
        if self.clip is not None:
            z = min(max(z, -self.clip), self.clip)
        m = min(state.i + 1, self.window)
        sums, k, g = _glr_step(state.sums, s, self._d2, float(z), m)  # type: ignore[attr-defined]
        side = "" if g <= self.h else ("high" if sums[k] > 0 else "low")
        if side:
            return GlrState(), Signal(g, self.h, side)
        return GlrState(sums, state.i + 1), Signal(g, self.h, "")


@njit(cache=True)
def _add_and_max(sums, s, d2, z, m):  # type: ignore[no-untyped-def]
    """In place: ``sums[:m] += s[:m] z`` (the NumPy steps' operations in their order); the
    age ``k`` of the largest ``sums^2 / d2`` with its value (the first largest; the first
    NaN if any, as argmax)."""
    k, g = 0, -np.inf
    for j in range(m):
        sums[j] = sums[j] + s[j] * z
        v = sums[j] * sums[j] / d2[j]
        if v != v:  # NaN: argmax stops at the first
            return j, v
        if v > g:
            k, g = j, v
    return k, g


@njit(cache=True)
def _glr_step(prev, s, d2, z, m):  # type: ignore[no-untyped-def]
    """One :meth:`Glr.update` in one pass (Numba): the new sums ``[0, prev[:m-1]] + s[:m]
    z`` (m,) and :func:`_add_and_max`'s age and value."""
    sums = np.empty(m)
    sums[0] = 0.0
    for j in range(1, m):
        sums[j] = prev[j - 1]
    k, g = _add_and_max(sums, s, d2, z, m)
    return sums, k, g


@njit(cache=True)
def glr_advance(sums, s, d2, z, m):  # type: ignore[no-untyped-def]
    """One step of many streams' GLR sums (Numba): each row of ``sums`` (streams, window)
    shifted by one age in place and :func:`_add_and_max` with its ``z`` (streams,) over
    the first ``m`` ages; returns each stream's largest ``sums^2 / d2`` (streams,)."""
    n, w = sums.shape
    g = np.empty(n)
    for r in range(n):
        row = sums[r]
        for j in range(w - 1, 0, -1):
            row[j] = row[j - 1]
        row[0] = 0.0
        g[r] = _add_and_max(row, s, d2, z[r], m)[1]
    return g


def load_kernel() -> None:
    """Load :meth:`Glr.update`'s kernel now (from Numba's cache, ~10 ms; compiled, ~1 s),
    not at the first charted product: a service calls it at its start, so that product's
    latency is like the others'."""
    _glr_step(np.zeros(0), np.ones(1), np.ones(1), 0.0, 1)


def glr_statistics(signature: Sequence[float], window: int, z: FloatArray,
                   clip: float | None = None) -> FloatArray:
    """The statistic ``g_n`` without restarts for the scores ``z`` (streams, steps) (clipped
    to ``+-clip`` if given), each stream charted from its start: (streams, steps)."""
    g = Glr(tuple(signature), 1.0, window)
    if clip is not None:
        z = np.clip(z, -clip, clip)
    s: FloatArray = g._s  # type: ignore[attr-defined]
    d2: FloatArray = g._d2  # type: ignore[attr-defined]
    streams, steps = z.shape
    zt = np.ascontiguousarray(np.transpose(z), dtype=np.float64)  # (steps, streams)
    sums = np.zeros((streams, window))
    out = np.empty((streams, steps))
    for t in range(steps):
        out[:, t] = glr_advance(sums, s, d2, zt[t], min(t + 1, window))
    return out


def glr_h(signature: Sequence[float], window: int, arl0: float, clip: float | None = None
          ) -> float:
    """Threshold ``h`` giving in-control ARL ``arl0`` for independent N(0, 1) scores, clipped
    to ``+-clip`` if given (:func:`glr_rate`)."""
    if not arl0 > 1:
        raise ValueError(f"ARL0 = {arl0}, expected > 1")
    c, a = glr_rate(tuple(round(float(v), 4) for v in signature), int(window), clip)
    from scipy.optimize import brentq  # on use: a service with stored charts needs none

    return float(brentq(lambda h: c + a * math.log(h) - h + math.log(arl0), 1.0, 200.0))


@lru_cache(maxsize=64)
def glr_rate(signature: tuple[float, ...], window: int, clip: float | None = None,
             streams: int = 300,
             steps: int = 2500, seed: int = 0) -> tuple[float, float]:
    """``(c, a)`` of the up-crossing rate of ``h`` per product, ``log rate = c + a log(h) -
    h``, for independent N(0, 1) scores (clipped to ``+-clip`` if given): the statistic
    simulated on ``streams`` x ``steps`` scores (after a burn-in of one window), the form
    fitted by least squares over the grid ``h`` >= 5 where at least 50 up-crossings are
    seen (the maximum over change times makes ``a`` about 1-2.5, not a single time's 1/2).
    Checked against direct simulation in the tests; at ARL0 1e4-1e5 the real ARL is 1-1.5
    times the design's."""
    z = np.random.default_rng(seed).standard_normal((streams, steps + window))
    g = glr_statistics(signature, window, z, clip)[:, window:]
    grid = np.arange(5.0, 30.01, 0.5)
    up = np.array([np.sum((g[:, 1:] > h) & (g[:, :-1] <= h)) for h in grid])
    ok = up >= 50
    if ok.sum() < 3:
        raise ValueError("GLR threshold: too few simulated up-crossings to fit their rate "
                         f"(largest statistic {float(g.max()):.2f}: bounded?)")
    y = np.log(up[ok] / g[:, 1:].size) + grid[ok]
    a, c = np.polyfit(np.log(grid[ok]), y, 1)
    return float(c), float(a)


__all__ = ["Glr", "GlrState", "glr_h", "glr_rate", "glr_statistics", "level_signature",
           "load_kernel", "residual_response", "response_signature", "step_response"]
