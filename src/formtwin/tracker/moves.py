"""The hooks of the resample-move filter (:class:`~formtwin.filters.ResampleMoveSIR`) on
the augmented model: which columns move, their bounds, the transition density given the
parent, and a likelihood without side effects. A mixin of
:class:`~formtwin.tracker.ssm.BendingSSM`."""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from formtwin.filters import logsumexp
from formtwin.tracker.hyper import GridPosteriors

FloatArray = NDArray[np.float64]


class MoveHooks(GridPosteriors):
    """``move_mask``, ``in_bounds``, ``log_transition``, ``loglik_fixed``."""

    _lo: FloatArray
    _hi: FloatArray
    _mu: FloatArray
    _sigma: FloatArray
    _rho: FloatArray
    config: Any
    _sizes: tuple[int, int, int]
    _loglik: Any
    #: particles per block in :meth:`loglik_fixed` (the model's own block size)
    chunk: int = 512

    @property
    def move_mask(self) -> NDArray[np.bool_]:
        """Columns (d,) a Metropolis-Hastings move may change: ``x`` (not when learning mu:
        its statistics follow from the path), ``theta`` and, when estimated, ``theta_d``."""
        nx, n_in, na = self._sizes
        out = np.zeros(self._lo.size, dtype=bool)
        out[: na if self.config.estimate_deviation else n_in] = True
        out[:nx] = not self.config.learn_mu
        return out

    def in_bounds(self, x: FloatArray) -> NDArray[np.bool_]:
        """Rows (N,) of ``x`` whose movable columns lie inside their bounds."""
        m = self.move_mask
        v = x[:, m]
        out: NDArray[np.bool_] = np.all((v >= self._lo[m]) & (v <= self._hi[m]), axis=1)
        return out

    def log_transition(self, parents: FloatArray, x: FloatArray) -> FloatArray:
        """``log p(x | parents)`` (N,) of the transition of the movable columns, up to a
        constant that depends on neither: the AR(1) of ``x`` (eq. 4-5) and the jitter of
        ``theta`` and ``theta_d`` (eq. 10), each a Gaussian reflected into the bounds."""
        (nx, n_in, na), lo, hi = self._sizes, self._lo, self._hi
        out = np.zeros(x.shape[0])
        if not self.config.learn_mu:  # (learning mu, x does not move)
            mean = (1.0 - self._rho) * self._mu + self._rho * parents[:, :nx]
            std = np.sqrt(1.0 - self._rho**2) * self._sigma
            out = _reflected_logpdf(x[:, :nx], mean, std, lo[:nx], hi[:nx])
        stop = na if self.config.estimate_deviation else n_in
        if stop > nx and self.config.alpha > 0:
            s = self.config.alpha * (hi[nx:stop] - lo[nx:stop])
            out = out + _reflected_logpdf(x[:, nx:stop], parents[:, nx:stop], s,
                                          lo[nx:stop], hi[nx:stop])
        return out

    def loglik_fixed(self, x: FloatArray, y: FloatArray) -> FloatArray:
        """:meth:`loglik` (N,) of ``y`` without side effects (no residuals kept, no
        statistics updated): the mixture over the current posterior of the share or
        scale. Not for the discrepancy likelihood with a shared part."""
        d = self.discrepancy
        if d is not None and d.shared:
            raise ValueError("loglik_fixed: the discrepancy likelihood updates its "
                             "statistics with every evaluation")
        ll = np.concatenate([self._loglik(x[i: i + self.chunk], y)[0]
                             for i in range(0, x.shape[0], self.chunk)])
        if d is not None:
            ll = self.mix_share(ll)
        out: FloatArray = self.mix_scale(ll) if self.config.learn_scale else ll
        return out


def _reflected_logpdf(v: FloatArray, mean: FloatArray, std: FloatArray, lo: FloatArray,
                      hi: FloatArray) -> FloatArray:
    """Sum over columns (N,) of the log-density, up to ``-log(std sqrt(2 pi))``, of
    ``N(mean, std^2)`` reflected into ``[lo, hi]`` at ``v`` (N, d): the direct term and
    the mirror images at both bounds (further images matter only for ``std`` near the
    width of the box)."""
    terms = np.stack([v - mean, 2.0 * lo - v - mean, 2.0 * hi - v - mean])
    out: FloatArray = np.sum(logsumexp(-0.5 * (terms / std) ** 2, axis=0), axis=1)
    return out
