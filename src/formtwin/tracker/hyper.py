"""Hyperparameters of the likelihood learned by Bayes' rule over a grid, shared by all
particles: the share ``kappa`` of the metamodel's error (adaptive and discrepancy
likelihoods, :mod:`formtwin.tracker.discrepancy`) and the factor ``c`` on the whole
covariance (``learn_scale``). A mixin of :class:`~formtwin.tracker.ssm.BendingSSM`, whose
``_last`` holds the last step's per-particle log-likelihoods on each grid; the
last curve's residuals for the goodness of fit and the angles' added variance,
which depend on those posteriors, are read here too."""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from formtwin.filters import logsumexp
from formtwin.tracker._kernels import row_sums, shifted_columns
from formtwin.tracker.config import SCALES

FloatArray = NDArray[np.float64]


class GridPosteriors:
    """Log-posteriors over the grids of ``kappa`` and ``c`` and their updates."""

    _scale: dict[str, FloatArray]
    _last: dict[str, FloatArray]
    discrepancy: Any
    measurement: Any
    angle_error_var: FloatArray

    @property
    def share_logpost(self) -> FloatArray:
        """Log-posterior (n_k,) of the independent share ``kappa`` of ``K_res`` over the
        discrepancy's grid (uniform prior), or ``[0]`` for one given value."""
        if "share" not in self._scale:
            n = 1 if self.discrepancy is None else self.discrepancy.shares.size
            self._scale["share"] = np.full(n, -np.log(n))
        return self._scale["share"]

    def set_share_logpost(self, value: FloatArray) -> None:
        """Replace the log-posterior of the share (restoring a saved state)."""
        self._scale["share"] = np.asarray(value, dtype=np.float64)

    def update_share(self, logw_prev: FloatArray) -> None:
        """Bayes' rule for ``kappa`` after a step whose predicted particles had normalised
        log-weights ``logw_prev`` (N,): ``p(kappa | Z_i) ~ p(kappa | Z_i-1) sum_k w_k
        p_kappa(z_i | particle k)``, the particle estimate of the evidence under each
        ``kappa``."""
        grid = self._last.pop("grid", None)
        if grid is None or grid.shape[1] < 2:
            return
        # logsumexp(logw_prev[:, None] + grid, axis=0), its steps but exp and log in
        # two Numba passes: the same numbers
        t, top = shifted_columns(np.ascontiguousarray(logw_prev, dtype=np.float64),
                                 np.ascontiguousarray(grid, dtype=np.float64))
        with np.errstate(divide="ignore"):  # a column of zero weight: -inf, as logsumexp
            ev = np.log(row_sums(np.exp(t, out=t))) + top
        if not np.all(np.isfinite(ev)):
            return  # a collapsed step says nothing about the share
        logp = self.share_logpost + ev
        self.set_share_logpost(logp - logsumexp(logp))

    def mix_share(self, ll: FloatArray) -> FloatArray:
        """Log-likelihoods (N,) from those on the share's grid ``ll`` (N, n_k): their
        mixture over the share's posterior."""
        logp = self.share_logpost
        out: FloatArray = logsumexp(ll + logp, axis=1) if logp.size > 1 else ll[:, 0]
        return out

    def mix_scale(self, ll: FloatArray) -> FloatArray:
        """Log-likelihoods (N,) from those on the scale's grid ``ll`` (N, n_scales): their
        mixture over the scale's posterior."""
        out: FloatArray = logsumexp(ll + self.scale_logpost, axis=1)
        return out

    @property
    def scale_logpost(self) -> FloatArray:
        """Log-posterior (n_scales,) of the factor on the likelihood covariance over
        :data:`~formtwin.tracker.config.SCALES` (``learn_scale``; uniform prior)."""
        if "logp" not in self._scale:
            self._scale["logp"] = np.full(len(SCALES), -np.log(len(SCALES)))
        return self._scale["logp"]

    def set_scale_logpost(self, value: FloatArray) -> None:
        """Replace the log-posterior of the scale (restoring a saved state)."""
        self._scale["logp"] = np.asarray(value, dtype=np.float64)

    def update_scale(self, logw_prev: FloatArray) -> None:
        """Bayes' rule for the scale after a step whose predicted particles had normalised
        log-weights ``logw_prev`` (N,): ``p(c | Z_i) ~ p(c | Z_i-1) p(z_i | Z_i-1, c)``.

        The predictive ``p(z_i | Z_i-1, c)`` is taken Gaussian, moment-matched to the
        predicted cloud (the innovation likelihood of adaptive Kalman filtering): residual
        mean ``e`` and covariance ``P`` of ``obs - model`` over the particles, and
        ``z_i - model ~ N(e, c Sigma + P)``. (The particle mixture ``sum_k w_k N(r_k; 0, c
        Sigma)`` instead rewards small ``c`` whenever one particle lands near the data.)
        """
        if "scaled" not in self._last or "r" not in self._last:
            return
        ll = self._last.pop("scaled")
        good = np.all(np.isfinite(ll), axis=1) & np.all(np.isfinite(self._last["r"]), axis=1)
        w = np.exp(logw_prev - logsumexp(logw_prev)) * good
        if w.sum() <= 0:
            return  # a collapsed step says nothing about the scale
        w = w / w.sum()
        r = np.where(good[:, None], self._last["r"], 0.0)
        e = w @ r
        d = (r - e) * np.sqrt(w)[:, None]
        if "white" not in self._scale:  # Sigma = L L^T; whiten by L^-1
            L = np.linalg.cholesky(self.measurement.covariance())
            self._scale["white"] = np.linalg.inv(L)
        Wt = self._scale["white"]
        dw = d @ Wt.T
        gam, V = np.linalg.eigh(dw.T @ dw)  # whitened P = V diag(gam) V^T
        ev2 = (V.T @ (Wt @ e)) ** 2
        c = np.array(SCALES)[:, None]
        g = np.maximum(gam, 0.0)[None, :]
        ev = -0.5 * (np.sum(np.log(c + g), axis=1) + np.sum(ev2 / (c + g), axis=1))
        logp = self.scale_logpost + ev
        self.set_scale_logpost(logp - logsumexp(logp))

    def angle_error(self) -> FloatArray:
        """Variance (2,) deg^2 the predicted angles' variance adds for the metamodel's own
        angle error: its held-out variance (calibrated, discrepancy); for the adaptive
        likelihood that times the posterior probability that the metamodel's error is in
        the data at all (``kappa > 0``: in the curves a part of the error is taken up by
        the parameters, in the angles nothing takes it up); 0 for the paper's."""
        d = self.discrepancy
        if d is None or d.shared:
            return self.angle_error_var
        present = float(np.exp(self.share_logpost) @ (d.shares > 0))
        out: FloatArray = self.angle_error_var * present
        return out

    def fit_residuals(self) -> tuple[FloatArray, FloatArray | None]:
        """The last curve's residuals and their predictive covariance, as the goodness of
        fit (:func:`~formtwin.tracker.fit.assess`) takes them: with the adaptive and
        discrepancy likelihoods in the coordinates where that covariance is diagonal (the
        likelihood's :meth:`~formtwin.tracker.discrepancy.Discrepancy.whiten`, (N, n_t),
        computed by the step) and its variances there (n_t,); else ``last_residuals()``
        (N, n_t) and ``None`` (the measurement model's). The distances are the same."""
        if "var" not in self._last:
            return self._last["r"], None
        return self._last["c"], self._last["var"]
