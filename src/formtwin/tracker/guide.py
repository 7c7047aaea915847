"""The guided proposal of the augmented model (``filter="guided"``,
:class:`~formtwin.filters.GuidedSIR`): the state ``x`` drawn near its posterior given the
parent and the curve, from a Gaussian built by linearising the model once per product. A
mixin of :class:`~formtwin.tracker.ssm.BendingSSM`.

For particle ``k`` the transition (eq. 4-5) gives ``x ~ N(a_k, Q)``, ``a_k = (1 - rho) mu +
rho x_(k, i-1)``, ``Q = diag((1 - rho^2) sigma^2)``; the constant parameters are jittered as
in SIR. The curve is linearised in ``x`` about the cloud's mean ``c`` (finite differences,
``n_x + 1`` model evaluations): ``h(x) ~ h(a_k) + H (x - a_k)``, and with the likelihood's
covariance ``R`` (``Sigma + E[kappa] K_res`` for the adaptive likelihood) the proposal is
the Kalman step

    q(x | x_(k, i-1), z_i) = N(a_k + S H^T R^-1 (z_i - h(a_k)),  S),
    S = (Q^-1 + H^T R^-1 H)^-1,

which costs one more model evaluation per particle (at ``a_k``; ``filter="guided"``). With
``filter="guided_lin"`` each particle carries the model curve of its last product (``n_t``
more columns, resampled and saved with it) and ``h(a_k)`` is that curve moved by the
Jacobian at the cloud's mean in every column that varies (x, theta, theta_d: ``n + 1``
evaluations, ``n <= 18``, instead of N): a step costs about one evaluation per particle as
SIR's (the first product, with no parent curves, evaluates the pilots). The draw is reflected into
the design box like the transition; the ratio ``log N(x; a_k, Q) - log q(x)`` is that of the
Gaussians (the reflection's images are left out: the box is many ``sqrt(S)`` wide). The
linearisation only makes ``q`` better or worse; the weights keep the filter's target exact.
Not with a learned mu (the transition is then the predictive of the path's statistics) nor
with the shared discrepancy (its residuals depend on each particle's statistics).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from formtwin.evolution import reflect
from formtwin.tracker.hyper import GridPosteriors

FloatArray = NDArray[np.float64]


class GuidedProposal(GridPosteriors):
    """``sample_guided(x, y, rng) -> (x_new, log_ratio)`` of the augmented model."""

    _lo: FloatArray
    _hi: FloatArray
    _mu: FloatArray
    _sigma: FloatArray
    _rho: FloatArray
    _sizes: tuple[int, int, int]
    _curve: int
    config: Any
    sample_transition: Any
    residuals: Any
    model: Any
    deviation: Any
    #: step of the finite differences of the linearisation, in units of sigma
    fd_step: float = 0.1
    #: factor on the proposal's covariance ``S``: above 1 its tails are heavier than the
    #: posterior's, which bounds the importance ratios where the linearisation is off
    widen: float = 2.0

    def _lik_cov(self) -> FloatArray:
        """The likelihood's covariance (n_t, n_t) for the proposal: ``Sigma``, plus the
        posterior mean of ``kappa`` times ``K_res`` for the adaptive likelihood."""
        d = self.discrepancy
        if d is None:
            return np.asarray(self.measurement.covariance())
        return np.asarray(d.predictive_cov(None, np.exp(self.share_logpost)))

    def _lik_whitening(self) -> tuple[FloatArray, FloatArray] | None:
        """``(T, v)`` with :meth:`_lik_cov` ``= T^-1 diag(v) T^-T`` (``T`` (n_t, n_t) the
        adaptive likelihood's :meth:`~formtwin.tracker.discrepancy.Discrepancy.whiten`,
        ``v`` (n_t,)): its inverse is ``T^T diag(1/v) T`` without a factorisation; None
        without a discrepancy."""
        d = self.discrepancy
        if d is None:
            return None
        return d.transform, d.predictive_var(None, np.exp(self.share_logpost))

    def sample_guided(self, x: FloatArray, y: FloatArray, rng: np.random.Generator,
                      pilot: bool = True) -> tuple[FloatArray, FloatArray]:
        """Particles (N, d) of the next product drawn from the guided proposal given this
        one's ``x`` (N, d) and its curve ``y`` (n_t,) N, and their log importance ratios
        (N,) ``log p(x_new | x) - log q(x_new | x, y)`` (see the module doc). ``pilot``:
        the residual at each particle's prediction from a model evaluation (N more); else
        from the parent's curve, carried in the particle's columns, and the Jacobian at the
        cloud's mean (:meth:`_linear_residuals`; the pilot evaluation where a parent has
        no curve: the first product, the model-space comparison)."""
        if self.config.learn_mu or (self.discrepancy is not None and self.discrepancy.shared):
            raise ValueError("the guided proposal needs a fixed mu and no shared discrepancy")
        nx = self._sizes[0]
        out = self.sample_transition(x, rng)  # constant parameters jittered as in SIR
        a = (1.0 - self._rho) * self._mu + self._rho * x[:, :nx]
        q = (1.0 - self._rho**2) * self._sigma**2
        at = out.copy()
        at[:, :nx] = a
        parents = x[:, self._curve:self._curve + len(y)] if self._curve else None
        if pilot or parents is None or not np.all(np.isfinite(parents)):
            r = self.residuals(at, y)  # z - h(a_k), (N, n_t)
            H = self._jacobian(at.mean(axis=0), self.fd_step * self._sigma, y)
        else:
            r, H = self._linear_residuals(at, y, x, parents)
        RiH = np.linalg.solve(self._lik_cov(), H)
        S = np.linalg.inv(np.diag(1.0 / q) + H.T @ RiH)
        S = 0.5 * (S + S.T)
        L = np.linalg.cholesky(S * self.widen)
        good = np.all(np.isfinite(r), axis=1)
        mean = a + np.where(good[:, None], np.nan_to_num(r) @ (S @ RiH.T).T, 0.0)  # gain
        eps = rng.standard_normal((x.shape[0], nx))
        new = mean + eps @ L.T
        log_p = -0.5 * np.sum((new - a) ** 2 / q + np.log(2.0 * math.pi * q), axis=1)
        log_q = (-0.5 * np.sum(eps**2, axis=1) - float(np.sum(np.log(np.diag(L))))
                 - 0.5 * nx * math.log(2.0 * math.pi))
        out[:, :nx] = reflect(new, self._lo[:nx], self._hi[:nx])
        return out, log_p - log_q

    def _linear_residuals(self, at: FloatArray, y: FloatArray, x: FloatArray,
                          curves: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Residuals ``z - h`` (N, n_t) at the particles ``at`` (N, d) from their parents
        ``x`` (N, d) with model curves ``curves`` (N, n_t) and the model's Jacobian ``J`` at
        the mean of ``at`` in every column that varies (the state, theta and, when
        estimated, theta_d; finite differences, at most 19 evaluations instead of N):
        ``r ~ z - curves - J (at - x)``; and the state's block ``H`` (n_t, n_x) of ``J``."""
        nx, n_cols = self._sizes[0], self.n_varying
        J, _ = self._cloud_jacobian(at.mean(axis=0), at[:, nx:n_cols].std(axis=0), y)
        r = (y - curves) - (at[:, :n_cols] - x[:, :n_cols]) @ J.T
        return r, J[:, :nx]

    @property
    def n_varying(self) -> int:
        """The particle columns that vary: the state, theta and, when estimated, theta_d."""
        _, n_in, na = self._sizes
        return na if self.config.estimate_deviation else n_in

    def _cloud_jacobian(self, c: FloatArray, spread: FloatArray, y: FloatArray,
                        exact: bool = False) -> tuple[FloatArray, FloatArray]:
        """``dh/dcolumn`` (n_t, m) at the particle ``c`` (d,) in the ``m`` columns that vary
        (:attr:`n_varying`), and its steps (m,): ``fd_step`` times the state's sigma and the
        cloud's ``spread`` (m - n_x,) of the other columns (at least 1e-3 of their range).
        ``exact``: the model's own derivative in ``[x, theta]`` where it has one
        (``model.differentiable``, :meth:`_exact_jacobian`), else forward differences of
        these steps."""
        nx, m = self._sizes[0], self.n_varying
        width = self._hi[nx:m] - self._lo[nx:m]
        step = self.fd_step * np.r_[self._sigma, np.maximum(spread, 1e-3 * width)]
        if exact and getattr(self.model, "differentiable", False):
            return self._exact_jacobian(c, step[self._sizes[1]:], y), step
        return self._jacobian(c, step, y), step

    def _exact_jacobian(self, c: FloatArray, td_step: FloatArray, y: FloatArray
                        ) -> FloatArray:
        """``dh/dcolumn`` (n_t, m) at the particle ``c`` (d,): in ``[x, theta]`` from the
        model's curve Jacobian (``model.curve_jacobian``), through ``g`` with the
        particle's ``theta_d`` (``g`` is linear in the curve: ``dg(z, t)/dx = g(dz/dx,
        t)``; with ``compare="model"`` the model side is the curve itself); in the
        ``theta_d`` columns by forward differences of ``td_step`` (m - n_in,) of ``g``
        of the particle's curve (``g^-1`` of ``y`` with ``compare="model"``), which the
        model's inputs do not change: no model evaluation."""
        n_in, m, n_td = self._sizes[1], self.n_varying, td_step.size
        curve, dz = self.model.curve_jacobian(c[None, :n_in])
        J = np.empty((dz.shape[1], m))
        if n_td == 0:
            J[:] = dz[0]
            return J
        td = np.repeat(c[None, n_in:m], n_td + 1, axis=0)
        td[1:] += np.diag(td_step)
        if self.config.compare == "model":  # r = g^-1(y, theta_d) - z~: h = z~ - g^-1
            J[:, :n_in] = dz[0]
            obs = self.deviation.invert(y, td)
            J[:, n_in:] = (obs[0] - obs[1:]).T / td_step
            return J
        rows = np.concatenate([np.repeat(curve, n_td + 1, axis=0), dz[0].T])
        g = self.deviation.apply(rows, np.concatenate([td, np.repeat(td[:1], n_in, axis=0)]))
        J[:, :n_in] = g[n_td + 1:].T
        J[:, n_in:] = (g[1:n_td + 1] - g[0]).T / td_step
        return J

    def _jacobian(self, c: FloatArray, step: FloatArray, y: FloatArray) -> FloatArray:
        """``dh/dcolumn`` (n_t, m) of the model curve at the particle ``c`` (d,) in its first
        ``m = len(step)`` columns, by forward differences of ``step`` (m,) (``m + 1`` model
        evaluations; the residuals are ``z - h``)."""
        base = np.repeat(c[None, :], step.size + 1, axis=0)
        base[1:, :step.size] += np.diag(step)
        r_fd = self.residuals(base, y)
        J: FloatArray = (r_fd[0] - r_fd[1:]).T / step
        return J
