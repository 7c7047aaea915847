"""The service's robust option: skip the tracker's update for a single outlier curve."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np


@dataclass
class OutlierGate:
    """Robust option: skip the update for a single outlier curve.

    After the tracker has stepped, the step's log-likelihood ``loglik`` is compared with the
    last ``window`` accepted ones: if it lies more than ``k`` robust standard deviations
    (1.4826 x median absolute deviation) below their median, the step is undone (the tracker
    is restored from the checkpoint of the previous product), the product is stored with
    status ``gated`` and an ``outlier_gated`` error is published. Only *single* outliers
    are gated: the product after a gated one is always accepted, so a genuine process
    change is followed after one product. Nothing is gated before ``warmup`` accepted
    products.

    >>> g = OutlierGate(k=5.0, warmup=5)
    >>> g.history = [-100.0, -101.0, -99.0, -100.5, -100.2, -99.5]
    >>> g.is_outlier(-100.3), g.is_outlier(-400.0)
    (False, True)
    """

    k: float = 8.0
    window: int = 100
    warmup: int = 20
    history: list[float] = field(default_factory=list)
    last_gated: bool = False

    def threshold(self) -> float:
        """Lowest loglik accepted now (``-inf`` during warm-up)."""
        h = np.asarray(self.history[-self.window:], dtype=np.float64)
        h = h[np.isfinite(h)]
        if h.size < self.warmup:
            return -math.inf
        med = float(np.median(h))
        mad = 1.4826 * float(np.median(np.abs(h - med)))
        return med - self.k * max(mad, 1e-9)

    def is_outlier(self, loglik: float) -> bool:
        """True if ``loglik`` should be gated now (never twice in a row)."""
        if self.last_gated:
            return False
        return not loglik >= self.threshold()

    def record(self, loglik: float, gated: bool) -> None:
        """Note the outcome of a product."""
        self.last_gated = gated
        if not gated and math.isfinite(loglik):  # as rebuilt from the store on restart
            self.history.append(float(loglik))
            del self.history[:-self.window]
