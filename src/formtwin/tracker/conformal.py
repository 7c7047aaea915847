"""Prediction intervals calibrated online by the measured values: adaptive conformal
inference (ACI, Gibbs & Candes 2021) with delayed feedback.

The twin predicts a product's final angle (mean ``m`` and std ``s``) before the camera
measures it; the measured value arrives ``d`` products later. The interval issued for
product ``i`` is

    m_i +- q_i s_i,    q_i = the ceil((n + 1)(1 - alpha_i))-th smallest of the n stored
                       scores |y_j - m_j| / s_j of the products measured so far

(the largest score when that rank exceeds ``n``; before ``warmup`` scores the Normal
quantile ``z_{1 - alpha_i / 2}``; ``alpha_i <= 0`` gives an infinite interval, ``alpha_i >=
1`` an empty one: the guarantee below needs only these two), and when the value ``y_j`` of
product ``j`` arrives, ``alpha`` takes the ACI step with the interval issued for ``j``::

    alpha  <-  alpha + gamma (alpha_target - 1{y_j outside its interval})

Intervals issued before ``y_j`` arrived did not use it: the delay is respected as it comes.
Whatever the data, ``alpha`` stays in ``[-d gamma, 1 + d gamma]`` and the miss rate over
the ``n`` products measured so far is within ``(1 + 2 d gamma) / (gamma n)`` of the
target (the sum of the steps telescopes), where ``d`` bounds how many intervals are
pending when one is scored; the stored scores (the last ``window``) make the interval
track a calibration that drifts.

>>> aci = AdaptiveConformal(alpha=0.1, gamma=0.01)
>>> lo, hi = aci.interval(0, 10.0, 1.0); round(hi - 10.0, 3)   # Normal before warm-up
1.645
>>> aci.update(0, 14.0)     # missed: the next intervals widen
True
>>> aci.alpha < 0.1
True
"""

from __future__ import annotations

import bisect
import math
from dataclasses import dataclass, field


@dataclass
class AdaptiveConformal:
    """Online interval calibration of a scalar prediction (see the module doc).

    Parameters
    ----------
    alpha : target miss rate (0.1: a 90 % interval).
    gamma : ACI step size (larger: faster to adapt, more jitter in the coverage).
    window : scores kept (the most recent).
    warmup : scores needed before the empirical quantile replaces the Normal one.
    """

    alpha_target: float = 0.1
    gamma: float = 0.005
    window: int = 500
    warmup: int = 20
    alpha: float = math.nan
    #: the last ``window`` scores, oldest first (given: restored from a state)
    scores: list[float] = field(default_factory=list)
    #: product -> (mean, scale, issued half-width multiplier q)
    pending: dict[int, tuple[float, float, float]] = field(default_factory=dict)
    #: :attr:`scores` in ascending order, kept beside them by :meth:`update`
    _sorted: list[float] = field(default_factory=list, init=False, repr=False,
                                 compare=False)

    def __post_init__(self) -> None:
        if not 0.0 < self.alpha_target < 1.0:
            raise ValueError(f"alpha = {self.alpha_target}, expected in (0, 1)")
        if not self.gamma > 0.0:
            raise ValueError(f"gamma = {self.gamma}, expected > 0")
        if self.window < 1 or self.warmup < 1:
            raise ValueError(f"window = {self.window}, warmup = {self.warmup}: expected >= 1")
        if math.isnan(self.alpha):
            self.alpha = self.alpha_target
        if any(math.isnan(v) for v in self.scores):
            raise ValueError("scores: NaN, expected scores |y - m| / s >= 0")
        self._sorted = sorted(self.scores)

    def multiplier(self) -> float:
        """The current half-width ``q`` in units of the prediction's scale."""
        a = self.alpha
        if a <= 0.0:
            return math.inf
        if a >= 1.0:
            return 0.0
        n = len(self.scores)
        if n < self.warmup:
            from scipy.stats import norm  # on use: ~1.3 s CPU to import

            return float(norm.ppf(1.0 - a / 2.0))
        k = min(math.ceil((n + 1) * (1.0 - a)), n)  # beyond the scores: the largest
        return self._sorted[k - 1]

    def interval(self, product: int, mean: float, scale: float) -> tuple[float, float]:
        """The interval ``(lo, hi)`` issued for ``product``'s value, predicted ``mean`` with
        std ``scale`` (> 0); remembered until its value arrives (:meth:`update`)."""
        if not (math.isfinite(mean) and math.isfinite(scale) and scale > 0):
            return math.nan, math.nan
        q = self.multiplier()
        self.pending[int(product)] = (float(mean), float(scale), q)
        return mean - q * scale, mean + q * scale

    def update(self, product: int, value: float) -> bool | None:
        """Score ``product``'s measured ``value`` against its issued interval and take the
        ACI step; return whether it missed (None: no interval was issued for it)."""
        issued = self.pending.pop(int(product), None)
        if issued is None or not math.isfinite(value):
            return None
        mean, scale, q = issued
        score = abs(value - mean) / scale
        miss = bool(score > q)
        self.alpha += self.gamma * (self.alpha_target - float(miss))
        self.scores.append(score)  # not NaN: value, mean and scale are finite, scale > 0
        bisect.insort(self._sorted, score)
        for old in self.scores[:-self.window]:
            del self._sorted[bisect.bisect_left(self._sorted, old)]
        del self.scores[:-self.window]
        return miss


__all__ = ["AdaptiveConformal"]
