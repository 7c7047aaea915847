"""The in-control model of a monitored quantity, and the standardised residual the charts see.

The estimates of a product stream are autocorrelated: the state drifts by eq. 4 (rho 0.7 to
0.95) and the posterior mean follows it, so its lag-1 autocorrelation is 0.8-0.98. Charts
designed for independent observations would then signal far too often. As Montgomery
(ch. 10.4, "SPC with autocorrelated process data") recommends, each quantity ``y`` gets an
autoregressive model AR(p) about its in-control mean ``m``::

    y_i - m = sum_j phi_j (y_{i-j} - m) + e_i,       e_i ~ N(0, sigma^2) independent,

fitted by least squares to an in-control run, and the charts watch the standardised
one-step residual ``z_i = e_i / sigma``, which is independent N(0, 1) in control. (A
posterior mean is a filtered AR(1): an AR(2) whitens it; on the bundled metamodel the lag-1
autocorrelation of the residuals is below 0.03 with p = 2, 0.1-0.35 with p = 1.)

A change of the mean by ``delta`` shows in the residuals as a jump of ``delta`` at the
change, followed by a lasting shift ``(1 - sum phi) delta``: the charts see the abrupt change
well and the lasting shift less well (the price of the autocorrelation).

Health statistics (the log-evidence increment, the ESS) are not Gaussian; they are first
mapped through the empirical distribution function of a simulated in-control run to normal
scores (:class:`Reference`), oriented so that large means "worse fit".

>>> import numpy as np
>>> rng = np.random.default_rng(0)
>>> e = rng.standard_normal(20_000)
>>> y = np.empty_like(e); y[0] = 0.0
>>> for i in range(1, e.size): y[i] = 0.8 * y[i - 1] + e[i]
>>> ic = fit_in_control([5.0 + y], order=1, mean=5.0)
>>> round(ic.phi[0], 2), round(ic.sigma, 2)
(0.8, 1.0)
"""

from __future__ import annotations

import math
from bisect import bisect_left, bisect_right
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.special import ndtri  # Phi^-1 (what norm.ppf calls, without its overhead)

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class InControl:
    """In-control AR(p) model of one quantity.

    Attributes
    ----------
    mean : in-control mean ``m`` (the quantity's unit); ``None``: estimated in Phase I
        (the mean of the first products the monitor sees, see :class:`MonitorConfig`).
    sigma : std of the one-step residual ``e`` (the quantity's unit), > 0.
    phi : (p,) autoregressive coefficients; ``()`` for independent observations, when
        ``sigma`` is the std of ``y`` itself.
    quantiles : sorted quantiles of the in-control standardised residual ``e / sigma``
        (from :func:`fit_in_control` with ``tails=True``); when given, :meth:`score` maps
        the residual through their distribution to a normal score (heavy-tailed residuals
        would otherwise make Gaussian limits far too tight). ``()``: ``e / sigma`` as is.
    """

    mean: float | None
    sigma: float
    phi: tuple[float, ...] = ()
    quantiles: tuple[float, ...] = ()

    def __post_init__(self) -> None:
        if not (math.isfinite(self.sigma) and self.sigma > 0):
            raise ValueError(f"in-control sigma = {self.sigma}, expected a number > 0")
        if self.mean is not None and not math.isfinite(self.mean):
            raise ValueError(f"in-control mean = {self.mean}, expected a finite number")
        object.__setattr__(self, "phi", tuple(float(p) for p in self.phi))
        q = tuple(float(v) for v in self.quantiles)
        if q and (len(q) < 20 or any(b < a for a, b in zip(q, q[1:], strict=False))):
            raise ValueError("in-control quantiles: expected >= 20 sorted values")
        object.__setattr__(self, "quantiles", q)
        # the outermost score once (score runs for every product and chart)
        object.__setattr__(self, "_zmax", float(ndtri(1.0 - 0.5 / len(q))) if q else 0.0)

    @property
    def order(self) -> int:
        """p: how many earlier values a residual needs."""
        return len(self.phi)

    def score(self, y: float, history: Sequence[float], mean: float) -> float:
        """Standardised residual ``z`` of ``y`` given the ``p`` previous values
        (``history``, oldest first) and the mean in force."""
        pred = mean + sum(p * (h - mean) for p, h in zip(self.phi, reversed(history),
                                                          strict=True))
        e = (y - pred) / self.sigma
        if not self.quantiles:
            return e
        return _score(e, self.quantiles, self._zmax)  # type: ignore[attr-defined]

    def to_dict(self) -> dict[str, Any]:
        return {"mean": self.mean, "sigma": self.sigma, "phi": list(self.phi),
                "quantiles": list(self.quantiles)}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> InControl:
        return cls(mean=None if d["mean"] is None else float(d["mean"]),
                   sigma=float(d["sigma"]), phi=tuple(d["phi"]),
                   quantiles=tuple(d.get("quantiles", ())))


def normal_score(e: float, q: Sequence[float]) -> float:
    """``Phi^-1`` of the in-control probability below ``e`` given its sorted quantiles ``q``
    (at probabilities ``(i + 0.5) / m``); beyond the outermost quantile the score grows
    linearly with ``e`` from there (unit slope), so a large change stays large.

    >>> q = [float(k) for k in range(-10, 11)]      # 21 quantiles
    >>> normal_score(0.0, q), round(normal_score(12.0, q), 3)   # 1.981 + 2 beyond the last
    (0.0, 3.981)
    """
    a = tuple(float(v) for v in q)
    return _score(e, a, float(ndtri(1.0 - 0.5 / len(a))))


def _score(e: float, q: Sequence[float], zmax: float) -> float:
    """:func:`normal_score` with the quantiles (a sequence of floats, sorted) and
    ``zmax = Phi^-1(1 - 1/(2m))``; a tuple is searched fastest (:func:`bisect.bisect_right`,
    the index NumPy's ``searchsorted(..., "right")`` gives)."""
    m = len(q)
    lo, hi = float(q[0]), float(q[-1])
    if not math.isfinite(e):
        return math.copysign(math.inf, e) if not math.isnan(e) else math.nan
    if e <= lo:
        return -zmax - (lo - e)
    if e >= hi:
        return zmax + (e - hi)
    k = bisect_right(q, e) - 1  # q[k] <= e < q[k + 1]
    span = float(q[k + 1] - q[k])
    f = (k + 0.5 + ((e - float(q[k])) / span if span > 0 else 0.5)) / m
    return float(ndtri(f))


def fit_in_control(runs: Sequence[FloatArray], order: int = 2, mean: float | None = None,
                   keep_mean: bool = True, tails: bool = False, n_quantiles: int = 1000
                   ) -> InControl:
    """Least-squares AR(``order``) fit pooled over in-control runs (each (n_r,)).

    ``mean`` is the in-control mean (e.g. the spec's mu); ``None``: each run is centred on
    its own mean (a run's level is then set in Phase I), and the result has ``mean=None``
    unless ``keep_mean`` (then the pooled mean). Non-finite values are dropped with the
    rows they touch. ``tails``: keep ``n_quantiles`` quantiles of the standardised
    residuals (:attr:`InControl.quantiles`).
    """
    if order < 0:
        raise ValueError(f"AR order = {order}, expected >= 0")
    rows, targets = [], []
    for run in runs:
        y = np.asarray(run, dtype=np.float64)
        c = y - (np.nanmean(y) if mean is None else mean)
        if c.size <= order:
            continue
        lagged = np.column_stack([c[order - j - 1: c.size - j - 1] for j in range(order)]) \
            if order else np.empty((c.size, 0))
        rows.append(lagged)
        targets.append(c[order:])
    if not rows:
        raise ValueError(f"no in-control run longer than the AR order {order}")
    a, b = np.vstack(rows), np.concatenate(targets)
    ok = np.isfinite(b) & np.all(np.isfinite(a), axis=1)
    a, b = a[ok], b[ok]
    if b.size < 10 * (order + 1):
        raise ValueError(f"{b.size} in-control values: too few to fit an AR({order}) model")
    phi = np.linalg.lstsq(a, b, rcond=None)[0] if order else np.empty(0)
    resid = b - a @ phi
    sigma = float(np.sqrt(resid @ resid / max(b.size - order, 1)))
    if mean is None and keep_mean:
        mean = float(np.nanmean(np.concatenate([np.asarray(r, float) for r in runs])))
    quantiles: tuple[float, ...] = ()
    if tails:
        m = min(n_quantiles, resid.size)
        quantiles = tuple(np.quantile(resid / sigma, (np.arange(m) + 0.5) / m))
    return InControl(mean=mean, sigma=sigma, phi=tuple(phi), quantiles=quantiles)


@dataclass(frozen=True)
class Reference:
    """Empirical in-control distribution of a health statistic and its orientation.

    Attributes
    ----------
    sample : sorted in-control values (from a simulated in-control run).
    bad : ``"low"`` if low values mean a worse fit (log-evidence, ESS), ``"high"`` if high
        ones do (a misfit distance).
    """

    sample: tuple[float, ...]
    bad: str = "low"

    def __post_init__(self) -> None:
        if self.bad not in ("low", "high"):
            raise ValueError(f"bad = {self.bad!r}, expected low or high")
        s = np.sort(np.asarray(self.sample, dtype=np.float64))
        s = s[np.isfinite(s)]
        if s.size < 20:
            raise ValueError(f"reference has {s.size} finite values, expected >= 20")
        object.__setattr__(self, "sample", tuple(float(v) for v in s))
        object.__setattr__(self, "_array", s)

    def normal_score(self, v: float) -> float:
        """``Phi^-1`` of the in-control probability of a value at least as good as ``v``:
        N(0, 1) in control, large when the fit is worse; ``-inf``/NaN count as worst.
        Clipped to the resolution of the sample (``+-Phi^-1(1 - 1/(2n))``)."""
        s: FloatArray = self._array  # type: ignore[attr-defined]
        n = s.size
        if not math.isfinite(v):  # NaN is worst; an infinity is worst on its bad side
            u = 0.0 if (v > 0) == (self.bad == "low") and not math.isnan(v) else 1.0
        else:  # mid-rank: ties (ESS = 1) get the middle of their probability mass
            below = bisect_left(self.sample, v) + bisect_right(self.sample, v)
            f = float(below) / (2.0 * n)
            u = 1.0 - f if self.bad == "low" else f
        return float(ndtri(min(max(u, 0.5 / n), 1.0 - 0.5 / n)))

    def of_line(self, values: Sequence[float] | FloatArray) -> Reference:
        """A line's own reference: its (Phase-I) ``values`` with this reference's
        orientation, or this reference where they have fewer than 20 finite values."""
        v = np.asarray(values, dtype=np.float64)
        return Reference(tuple(v), self.bad) if np.isfinite(v).sum() >= 20 else self


__all__ = ["InControl", "Reference", "fit_in_control", "normal_score"]
