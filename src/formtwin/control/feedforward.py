"""Feedforward control of the final angle from the posterior over the process state.

After product ``i``'s stage-1 force curve the tracker holds particles ``x_k`` with weights
``w_k`` (the posterior of the state, machine parameters and deviation). The stage-2 setting
``u`` of the same product is chosen to minimise the posterior expected squared error of its
final angle ``a(x, u)`` against the target ``T``::

    J(u) = sum_k w_k (a(x_k, u) - T)^2  =  (E[a(u)] - T)^2 + Var[a(u)],

over the feasible interval ``[max(lo, u_prev - step), min(hi, u_prev + step)]`` (actuator
limits and the largest change from one product to the next). Minimising ``J`` rather than
``(a(E[x], u) - T)^2`` accounts for the curvature of ``a`` over the cloud.

Search: ``J`` on a grid of ``grid`` settings over the interval (one batched call of the
angle model for all particles and settings), then up to ``refine`` steps of successive
parabolic interpolation: the vertex of the parabola through the best point so far and its
neighbours (one call each). The best point evaluated is taken. For an angle linear in
``u`` (``J`` quadratic) the first vertex is the exact minimiser.

>>> import numpy as np
>>> c = np.array([88.0, 88.5, 89.5])                 # three particles' angle at u = 0
>>> final_angle = lambda u: c[:, None] - 0.05 * np.asarray(u)[None, :]   # deg, u in um
>>> s = Feedforward(target=90.0, actuator=Actuator(-100.0, 100.0)).choose(final_angle)
>>> round(s.u, 6), round(s.angle_mean, 6)           # E[a] = 88.667 -> u = -26.67 um
(-26.666667, 90.0)
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]

#: the process as the controller sees it: settings (n_u,) -> final angles (N, n_u)
AngleFunction = Callable[[FloatArray], FloatArray]


@dataclass(frozen=True)
class Actuator:
    """Limits of the press setting ``u`` (internal units).

    Attributes
    ----------
    lo, hi : actuator limits.
    max_step : largest change of ``u`` from one product to the next (``inf``: none).
    """

    lo: float
    hi: float
    max_step: float = math.inf

    def __post_init__(self) -> None:
        if not (math.isfinite(self.lo) and math.isfinite(self.hi) and self.lo < self.hi):
            raise ValueError(f"actuator limits [{self.lo}, {self.hi}]: expected finite lo < hi")
        if not self.max_step > 0:
            raise ValueError(f"actuator max_step = {self.max_step}, expected > 0")

    def feasible(self, u_prev: float | None) -> tuple[float, float]:
        """The interval of settings allowed after ``u_prev`` (None: the whole range)."""
        if u_prev is None:
            return self.lo, self.hi
        a = max(self.lo, min(self.hi, u_prev) - self.max_step)
        b = min(self.hi, max(self.lo, u_prev) + self.max_step)
        return a, b

    def clip(self, u: float, u_prev: float | None = None) -> float:
        """``u`` moved into the feasible interval after ``u_prev``."""
        a, b = self.feasible(u_prev)
        return float(min(max(u, a), b))


@dataclass(frozen=True)
class Suggestion:
    """The setting chosen for one product and what it is expected to give.

    Attributes
    ----------
    u : the chosen setting.
    angle_mean, angle_std : posterior mean and std of the final angle at ``u``, degrees.
    interval : (lo, hi) central ``coverage`` interval of the final angle at ``u``, degrees.
    expected_sq_error : ``J(u)``, deg^2.
    limited : the unconstrained optimum lay outside the feasible interval (``u`` is on
        its edge).
    """

    u: float
    angle_mean: float
    angle_std: float
    interval: tuple[float, float]
    expected_sq_error: float
    limited: bool

    def to_dict(self) -> dict[str, object]:
        """JSON-ready values (non-finite -> None)."""
        def num(v: float) -> float | None:
            return float(v) if math.isfinite(v) else None
        return {"u": num(self.u), "angle_mean": num(self.angle_mean),
                "angle_std": num(self.angle_std),
                "interval": [num(self.interval[0]), num(self.interval[1])],
                "expected_sq_error": num(self.expected_sq_error), "limited": self.limited}


def reference_angle(final_angle: AngleFunction, u_ref: float,
                    weights: FloatArray | None = None) -> float:
    """``c_i``: the posterior mean of the final angle at setting ``u_ref``, degrees, over
    the particles with a finite angle (``weights`` (N,), None: equal); NaN if none."""
    a = np.asarray(final_angle(np.array([u_ref])), dtype=np.float64)[:, 0]
    w = np.ones(a.size) if weights is None else np.asarray(weights, dtype=np.float64)
    ok = np.isfinite(a)
    return float(w[ok] @ a[ok] / w[ok].sum()) if ok.any() and w[ok].sum() > 0 else math.nan


def weighted_quantile(values: FloatArray, weights: FloatArray, q: FloatArray) -> FloatArray:
    """Quantiles ``q`` of the discrete distribution of ``values`` (N,) with ``weights`` (N,)
    (the inverse of its CDF, mid-point convention).

    >>> weighted_quantile(np.array([1.0, 2.0, 3.0, 4.0]), np.ones(4), np.array([0.5]))
    array([2.5])
    """
    order = np.argsort(values)
    v, w = values[order], weights[order] / weights.sum()
    cdf = np.cumsum(w) - 0.5 * w
    return np.interp(q, cdf, v)


@dataclass(frozen=True)
class Feedforward:
    """Per-product choice of ``u`` from the posterior (see the module doc).

    Attributes
    ----------
    target : wanted final angle, degrees.
    actuator : limits and maximum step of ``u``.
    grid : settings tried on the first pass (>= 3).
    refine : most successive parabolic steps after the grid (one angle-model call each).
    coverage : probability of the reported interval of the final angle.
    """

    target: float
    actuator: Actuator
    grid: int = 9
    coverage: float = 0.9
    refine: int = 4

    def __post_init__(self) -> None:
        if self.grid < 3:
            raise ValueError(f"grid = {self.grid}, expected >= 3")
        if not 0 < self.coverage < 1:
            raise ValueError(f"coverage = {self.coverage}, expected in (0, 1)")

    def cost(self, angles: FloatArray, w: FloatArray) -> FloatArray:
        """``J`` (n_u,) of final angles (N, n_u) with normalised weights (N,); a particle
        whose angle is not finite counts with the worst finite error."""
        err = (angles - self.target) ** 2
        bad = ~np.isfinite(err)
        if bad.any():
            worst = np.nanmax(np.where(bad, np.nan, err)) if (~bad).any() else 0.0
            err = np.where(bad, worst, err)
        out: FloatArray = w @ err
        return out

    def choose(self, final_angle: AngleFunction, weights: FloatArray | None = None,
               u_prev: float | None = None) -> Suggestion:
        """The setting minimising ``J`` after ``u_prev`` (None: anywhere in the limits).

        ``final_angle(u)`` gives the final angle (N, n_u) of every particle at settings
        ``u`` (n_u,); ``weights`` (N,) are the particles' (None: equal, as after
        resampling).
        """
        a, b = self.actuator.feasible(u_prev)
        grid = np.linspace(a, b, self.grid) if b > a else np.array([a])
        angles = np.asarray(final_angle(grid), dtype=np.float64)
        if angles.ndim != 2 or angles.shape[1] != grid.size:
            raise ValueError(f"final_angle returned shape {angles.shape}, expected "
                             f"(N, {grid.size})")
        n = angles.shape[0]
        w = np.full(n, 1.0 / n) if weights is None else np.asarray(weights, np.float64)
        if w.shape != (n,) or not np.all(w >= 0) or not w.sum() > 0:
            raise ValueError(f"weights: expected {n} non-negative numbers with a positive sum")
        w = w / w.sum()
        j = self.cost(angles, w)
        us, js, cols = list(grid), list(j), list(angles.T)
        tol = 1e-9 * (self.actuator.hi - self.actuator.lo)
        for _ in range(self.refine if grid.size >= 3 else 0):
            order = np.argsort(us)
            su, sj = np.asarray(us)[order], np.asarray(js)[order]
            c = min(max(int(np.argmin(sj)), 1), su.size - 2)
            v = _vertex(su[c - 1: c + 2], sj[c - 1: c + 2])
            if v is None or not su[c - 1] <= v <= su[c + 1] or \
                    np.min(np.abs(su - v)) <= tol:
                break
            av = np.asarray(final_angle(np.array([v])), dtype=np.float64)[:, 0]
            us.append(v)
            js.append(float(self.cost(av[:, None], w)[0]))
            cols.append(av)
        best = int(np.argmin(js))
        u, col, jbest = float(us[best]), cols[best], float(js[best])
        # the unconstrained optimum lies beyond an edge when J still falls towards it
        limited = grid.size == 1 or bool((u == grid[0] and j[0] < j[1]) or
                                         (u == grid[-1] and j[-1] < j[-2]))
        ok = np.isfinite(col)
        wo = w[ok] / w[ok].sum() if ok.any() else w
        co = col[ok] if ok.any() else col
        mean = float(wo @ co)
        std = float(np.sqrt(max(float(wo @ (co - mean) ** 2), 0.0)))
        lo_q, hi_q = weighted_quantile(co, wo, np.array([(1 - self.coverage) / 2,
                                                         (1 + self.coverage) / 2]))
        return Suggestion(u, mean, std, (float(lo_q), float(hi_q)), jbest, limited)


def _vertex(u: FloatArray, j: FloatArray) -> float | None:
    """Abscissa of the vertex of the parabola through three points, if it is a minimum."""
    (u0, u1, u2), (j0, j1, j2) = u, j
    d = (u1 - u0) * (j1 - j2) - (u1 - u2) * (j1 - j0)
    num = (u1 - u0) ** 2 * (j1 - j2) - (u1 - u2) ** 2 * (j1 - j0)
    curvature = (j0 - j1) / (u0 - u1) - (j1 - j2) / (u1 - u2)
    if d == 0 or not curvature < 0:  # divided differences: a minimum needs a rising slope
        return None
    return float(u1 - 0.5 * num / d)


__all__ = ["Actuator", "AngleFunction", "Feedforward", "Suggestion", "reference_angle",
           "weighted_quantile"]
