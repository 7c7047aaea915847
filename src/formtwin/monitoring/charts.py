"""EWMA and tabular CUSUM control charts in their textbook forms (Montgomery, *Introduction
to Statistical Quality Control*, ch. 9), on a standardised statistic ``z`` (in-control
mean 0, std 1, independent from product to product).

EWMA (Roberts 1959; Montgomery eq. 9.22, 9.25-9.26)::

    Z_i = lam z_i + (1 - lam) Z_{i-1},   Z_0 = 0
    limit_i = L sqrt(lam / (2 - lam) (1 - (1 - lam)^(2 i)))          (exact, time-varying)

Two-sided tabular CUSUM (Page 1954; Montgomery eq. 9.2-9.3), ``k`` and ``h`` in sigma units::

    C+_i = max(0, z_i - k + C+_{i-1}),   C-_i = max(0, -z_i - k + C-_{i-1}),   C_0 = 0
    signal when C+_i > h or C-_i > h

A chart restarts after it signals (``Z``, ``C`` to 0 and ``i`` to 0), the usual practice once
the cause has been looked for. Chart states are small immutable values (named tuples), so
a chart's state is a plain record that can be saved and restored; a
:class:`~formtwin.monitoring.Monitor` keeps its charts' states in arrays and steps them
with the same float operations (:mod:`~formtwin.monitoring.bank`).

Run lengths: :func:`cusum_arl_siegmund` (Siegmund's approximation), :func:`ewma_arl`
(Brook & Evans' Markov chain), and the inverses :func:`cusum_h` and :func:`ewma_L` that
design a chart for a wanted in-control average run length ``ARL0``.

>>> ewma_limit(1, 0.1, 3.0)          # 3 sqrt(0.1/1.9 * (1 - 0.81))
0.3
>>> round(cusum_arl_siegmund(0.5, 5.0), 1)   # one-sided; Montgomery's table: 930 (h = 5)
938.2
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np

#: the chart kinds of a monitor
CHARTS = ("ewma", "cusum")


def ewma_limit(i: int, lam: float, L: float) -> float:
    """Exact EWMA control limit after ``i`` >= 1 observations, in sigma units of ``z``."""
    return L * math.sqrt(lam / (2.0 - lam) * (1.0 - (1.0 - lam) ** (2 * i)))



@dataclass(frozen=True)
class Alarm:
    """One alarm.

    Attributes
    ----------
    variable : the quantity (a state variable, an angle, or a health statistic).
    chart : ``"ewma"``, ``"cusum"``, ``"glr"``, ``"shewhart"`` or ``"mismatch"``.
    index : the estimate's product index (0-based, the tracker's step).
    statistic : the chart statistic when it crossed (sigma units of the residual;
        ``shewhart``: the residual's score ``z`` itself; ``glr``: a log-likelihood ratio).
    limit : the limit it crossed (same units).
    side : ``"high"`` (above the in-control level) or ``"low"``.
    """

    variable: str
    chart: str
    index: int
    statistic: float
    limit: float
    side: str

    def to_dict(self) -> dict[str, Any]:
        return {"variable": self.variable, "chart": self.chart, "index": int(self.index),
                "statistic": float(self.statistic), "limit": float(self.limit),
                "side": self.side}


class EwmaState(NamedTuple):
    """EWMA statistic ``z`` after ``i`` observations since the (re)start."""

    z: float = 0.0
    i: int = 0


class CusumState(NamedTuple):
    """Upper and lower CUSUM sums, sigma units."""

    hi: float = 0.0
    lo: float = 0.0


class Signal(NamedTuple):
    """A chart's verdict on one observation: its statistic, the limit it was held against
    and the side it crossed (``"high"``, ``"low"`` or ``""`` for none)."""

    statistic: float
    limit: float
    side: str


@dataclass(frozen=True)
class Ewma:
    """EWMA chart with smoothing ``lam`` in (0, 1] and limit width ``L`` (sigma units)."""

    lam: float = 0.1
    L: float = 3.0

    def __post_init__(self) -> None:
        if not 0 < self.lam <= 1:
            raise ValueError(f"EWMA lam = {self.lam}, expected 0 < lam <= 1")
        if not self.L > 0:
            raise ValueError(f"EWMA L = {self.L}, expected > 0")

    def update(self, state: EwmaState, z: float) -> tuple[EwmaState, Signal]:
        """The next state and the signal for standardised observation ``z``; the returned
        state is the restarted one when the chart signals."""
        s = EwmaState(self.lam * z + (1.0 - self.lam) * state.z, state.i + 1)
        lim = ewma_limit(s.i, self.lam, self.L)
        side = "high" if s.z > lim else "low" if s.z < -lim else ""
        return (EwmaState() if side else s), Signal(s.z, lim, side)


@dataclass(frozen=True)
class Cusum:
    """Two-sided tabular CUSUM with reference ``k`` and decision interval ``h`` (sigma
    units of ``z``); ``sides`` "both", "high" or "low" (one-sided chart)."""

    k: float = 0.5
    h: float = 5.0
    sides: str = "both"

    def __post_init__(self) -> None:
        if self.k < 0 or not self.h > 0:
            raise ValueError(f"CUSUM k = {self.k}, h = {self.h}: expected k >= 0, h > 0")
        if self.sides not in ("both", "high", "low"):
            raise ValueError(f"CUSUM sides = {self.sides!r}, expected both, high or low")

    def update(self, state: CusumState, z: float) -> tuple[CusumState, Signal]:
        """The next state and the signal for standardised observation ``z``."""
        hi = max(0.0, z - self.k + state.hi) if self.sides != "low" else 0.0
        lo = max(0.0, -z - self.k + state.lo) if self.sides != "high" else 0.0
        if hi > self.h:
            return CusumState(), Signal(hi, self.h, "high")
        if lo > self.h:
            return CusumState(), Signal(lo, self.h, "low")
        return CusumState(hi, lo), Signal(max(hi, lo), self.h, "")


# ------------------------------------------------------------------- run-length design
def cusum_arl_siegmund(k: float, h: float, shift: float = 0.0) -> float:
    """Siegmund's approximation of the average run length of a *one-sided* CUSUM
    (Montgomery eq. 9.13): ``(exp(-2 D b) + 2 D b - 1) / (2 D^2)``, ``D = shift - k``,
    ``b = h + 1.166``; ``b^2`` when ``D = 0``. ``shift`` in sigma units."""
    d, b = shift - k, h + 1.166
    if abs(d) < 1e-12:
        return b * b
    return (math.exp(-2.0 * d * b) + 2.0 * d * b - 1.0) / (2.0 * d * d)


def cusum_arl_two_sided(k: float, h: float, shift: float = 0.0) -> float:
    """Two-sided ARL from the one-sided ones: ``1/ARL = 1/ARL+ + 1/ARL-``."""
    return 1.0 / (1.0 / cusum_arl_siegmund(k, h, shift)
                  + 1.0 / cusum_arl_siegmund(k, h, -shift))


def cusum_h(k: float, arl0: float, two_sided: bool = True) -> float:
    """Decision interval ``h`` giving in-control ARL ``arl0`` (Siegmund's approximation)."""
    from scipy.optimize import brentq  # on use: a service with stored charts needs none

    arl = cusum_arl_two_sided if two_sided else cusum_arl_siegmund
    top = min(200.0, 300.0 / max(k, 1e-9))  # exp(2 k (h + 1.166)) stays finite
    return float(brentq(lambda h: math.log(arl(k, h)) - math.log(arl0), 0.01, top))


def ewma_arl(lam: float, L: float, shift: float = 0.0, states: int = 201) -> float:
    """ARL of a two-sided EWMA with asymptotic limits ``+-L sqrt(lam/(2-lam))``, started at
    0, for a mean shift ``shift`` (sigma units): Brook & Evans' Markov chain over
    ``states`` cells of the in-control region (Lucas & Saccucci 1990 used the same)."""
    from scipy.stats import norm  # on use: ~1.3 s CPU to import

    c = L * math.sqrt(lam / (2.0 - lam))
    m = states
    w = 2.0 * c / m
    centres = -c + w * (np.arange(m) + 0.5)
    # P[i, j] = P(Z_next in cell j | Z = centre i), Z_next = (1-lam) Z + lam z
    lo = (centres[None, :] - w / 2 - (1.0 - lam) * centres[:, None]) / lam
    hi = (centres[None, :] + w / 2 - (1.0 - lam) * centres[:, None]) / lam
    p = norm.cdf(hi - shift) - norm.cdf(lo - shift)
    arl = np.linalg.solve(np.eye(m) - p, np.ones(m))
    return float(arl[m // 2])  # the start, Z_0 = 0, is the middle cell (m odd)


def ewma_L(lam: float, arl0: float, states: int = 201) -> float:
    """Limit width ``L`` giving in-control ARL ``arl0`` with asymptotic limits."""
    from scipy.optimize import brentq  # on use: a service with stored charts needs none

    return float(brentq(lambda L: math.log(ewma_arl(lam, L, 0.0, states)) - math.log(arl0),
                        0.5, 8.0))


__all__ = ["CHARTS", "Alarm", "Cusum", "CusumState", "Ewma", "EwmaState", "Signal",
           "cusum_arl_siegmund", "cusum_arl_two_sided", "cusum_h", "ewma_L", "ewma_arl",
           "ewma_limit"]
