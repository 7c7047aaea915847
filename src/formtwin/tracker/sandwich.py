"""The linearised filter's error terms of the reported intervals, which the particle cloud
does not show: a persistent metamodel error's (``TrackerConfig(intervals="sandwich")``)
and an assumed mu's (``mu_known=False``, every ``intervals`` but ``"cloud"``).

A metamodel error ``delta ~ N(0, K_res)`` (``K_res`` the k-fold held-out residual
covariance) that stays the same from product to product is not averaged away: on the
filter linearised about the cloud's mean (the curve's Jacobian ``J`` (n_t, m) in the m
columns that vary, the likelihood's covariance ``S``, the transition factors ``F`` (rho
for the state, 1 for the constant parameters) and the process noise ``Q`` (the AR(1)'s
``(1 - rho^2) sigma^2``, the jitter's ``(alpha range)^2``)), one Kalman step is

    P_pred = F P_prev F + Q,   P_lin = (P_pred^-1 + J^T S^-1 J)^-1,
    K = P_lin J^T S^-1,        A = P_lin P_pred^-1 F,

and the estimate's error from ``delta`` follows ``e_i = A e_(i-1) + K delta``: it is
``G_i delta`` with the sensitivity ``G_i = A G_(i-1) + K`` (m, n_t), ``G_0 = 0``. Its
covariance ``B = G K_res G^T`` is added to the cloud's covariance ``P`` in the reported
std (:func:`sandwich_step`); the angles add ``a' B a'^T`` with ``a'`` the angle
metamodel's gradient in ``[x, theta]`` at the cloud's mean. ``P_prev`` is the previous
product's cloud covariance; one step with ``F = 0`` is the one-product sandwich
``P J^T S^-1 K_res S^-1 J P``. For a linear-Gaussian model the recursion is exact: the
Kalman estimate's mean error under a fixed offset ``delta`` is ``G delta`` and its mean
squared error ``P + G delta delta^T G^T`` (tests/test_tracker_intervals.py).

An assumed mu: the line's state means are ``mu + d``, not the filter's ``mu``. The state's
prediction error then gains ``(1 - rho) d`` each product (the constant parameters' random
walk has no mean: nothing), and the update keeps ``(I - K J) = P_lin P_pred^-1`` of the
prediction error, so the estimate's error from ``d`` is ``G_mu d`` with

    G_mu,i = P_lin P_pred^-1 (F G_mu,(i-1) + [diag(1 - rho); 0]),   G_mu,0 = [I; 0]

(:func:`mu_step`; the initial law is centred on ``mu``). With ``d``'s second moment
``E[d d^T]`` from the paper's law of the line's statistics, ``mu ~ U(mu_min, mu_max)``
(``diag(range^2 / 12) + (mid - mu)(mid - mu)^T``), the reported covariance adds
``G_mu E[d d^T] G_mu^T`` (the law of total variance over mu, to first order; the data's
information on mu is not used: ``learn_mu`` learns it, and then there is no term). Exact
for a linear-Gaussian model (tests/test_tracker_intervals.py). Without data (``J = 0``)
``G_mu`` stays ``[I; 0]``: the estimate keeps the whole offset.

``"gated"`` multiplies ``B`` by the posterior probability that the metamodel's error is in
the data (the adaptive likelihood's ``P(kappa > 0)``; 1 for the other likelihoods).
``J`` and the angle gradient are refreshed every :data:`EVERY` products: in ``[x, theta]``
the metamodel's closed-form derivatives (:mod:`formtwin.metamodel.gradient`; forward
differences of its float32 evaluation carry that rounding over the step, 10-40 % of the
state's columns on the bundled metamodel), in ``theta_d`` forward differences of ``g`` of
the mean's curve; for a model without derivatives ``m + 1`` curve and ``n_in + 1`` angle
evaluations by forward differences. The particles, weights, means, ESS, evidence and
health do not change (the intervals are computed after the step and draw no random
numbers). What this does and does not explain on the physics data: docs/explanation/likelihood.md.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.linalg.lapack import dgesv as _gesv

from formtwin.tracker._kernels import cloud_moments, information, mu_gain_step, term_variances
from formtwin.tracker.discrepancy import residual_covariance

FloatArray = NDArray[np.float64]

#: the curve's Jacobian and the angles' gradient are refreshed every this many products
#: (the cloud's mean drifts slowly; each refresh costs m + 1 + n_in + 1 model rows)
EVERY = 4

#: keys of the sandwich's state in :attr:`formtwin.tracker.TrackerState.model`
STATE_KEYS = ("sandwich_G", "sandwich_P", "sandwich_J", "sandwich_Ja", "sandwich_Gmu")


def _gains(P_prev: FloatArray, info: FloatArray, S_inv_J: FloatArray | None, F: FloatArray,
           Q: FloatArray) -> tuple[FloatArray, FloatArray | None]:
    """``(I - K J) = P_lin P_pred^-1`` (m, m) and the gain ``K = P_lin J^T S^-1`` (m, n_t)
    of the linearised step (module doc) from the information ``J^T S^-1 J`` (m, m) and
    ``S^-1 J`` (n_t, m) (None: ``K`` is not wanted, None).

    With ``P_lin = (P_pred^-1 + J^T S^-1 J)^-1 = (I + P_pred J^T S^-1 J)^-1 P_pred`` both
    come from one LU solve with ``A = I + P_pred J^T S^-1 J``: ``P_lin P_pred^-1 = A^-1``,
    ``K = A^-1 P_pred J^T S^-1`` (no inverse of ``P_pred``; the same matrices as the two
    inverses of the formulas to rounding, tests/test_tracker_intervals.py).
    """
    P_pred = F[:, None] * P_prev * F[None, :]
    P_pred.flat[::P_pred.shape[0] + 1] += Q
    m = P_pred.shape[0]
    a = P_pred @ info
    a.flat[::m + 1] += 1.0
    rhs = np.eye(m) if S_inv_J is None else np.hstack([np.eye(m), P_pred @ S_inv_J.T])
    *_, sol, info_ = _gesv(a, rhs, overwrite_a=1, overwrite_b=1)
    if info_ != 0:  # singular in floating point: NumPy's error, as np.linalg.inv raises
        raise np.linalg.LinAlgError("Singular matrix")
    return sol[:, :m], None if S_inv_J is None else sol[:, m:]


def sandwich_step(G: FloatArray, P_prev: FloatArray, J: FloatArray, S_inv_J: FloatArray,
                  F: FloatArray, Q: FloatArray) -> FloatArray:
    """The next sensitivity ``G`` (m, n_t) of the estimate to a persistent curve error
    (module doc) from the previous ``G`` (m, n_t), the previous posterior covariance
    ``P_prev`` (m, m), the Jacobian ``J`` (n_t, m), ``S^-1 J`` (n_t, m), the transition
    factors ``F`` (m,) and the process-noise variances ``Q`` (m,).

    >>> import numpy as np   # scalar state, one sample: K = P_lin / s, A = P_lin / P_pred
    >>> G = sandwich_step(np.zeros((1, 1)), np.eye(1), np.eye(1), np.eye(1) / 2.0,
    ...                   np.ones(1), np.ones(1))
    >>> round(float(G[0, 0]), 6)   # P_pred = 2, P_lin = 1 / (1/2 + 1/2) = 1, K = 1/2
    0.5
    """
    M, K = _gains(P_prev, J.T @ S_inv_J, S_inv_J, F, Q)
    assert K is not None
    return _next_G(M, K, F, G)


def _next_G(M: FloatArray, K: FloatArray, F: FloatArray, G: FloatArray) -> FloatArray:
    """``G = A G' + K`` with ``A = M F`` (:func:`sandwich_step`)."""
    out: FloatArray = (M * F[None, :]) @ G + K
    return out


def _next_G_mu(M: FloatArray, F: FloatArray, G_mu: FloatArray,
               drive: FloatArray | None = None) -> FloatArray:
    """``G_mu = M (F G_mu' + [diag(1 - rho); 0])`` (:func:`mu_step`); ``drive`` the
    constant ``[diag(1 - rho); 0]`` (m, n_x) when the caller keeps it."""
    if drive is None:
        drive = np.eye(F.size, G_mu.shape[1]) * (1.0 - F[:G_mu.shape[1]])
    out: FloatArray = M @ (F[:, None] * G_mu + drive)
    return out


def mu_step(G_mu: FloatArray, P_prev: FloatArray, J: FloatArray, S_inv_J: FloatArray,
            F: FloatArray, Q: FloatArray) -> FloatArray:
    """The next sensitivity ``G_mu`` (m, n_x) of the estimate's error to an offset ``d``
    (n_x,) of the assumed mu from the line's (module doc): the state's prediction error
    gains ``(1 - rho) d``, the update keeps ``I - K J`` of it,
    ``G_mu = (I - K J) (F G_mu' + [diag(1 - rho); 0])`` (arguments as
    :func:`sandwich_step`; the first ``n_x`` of ``F`` are rho).

    >>> import numpy as np   # no data (J = 0): the estimate keeps the whole offset
    >>> G = np.eye(2, 1)
    >>> for _ in range(3):
    ...     G = mu_step(G, np.eye(2), np.zeros((1, 2)), np.zeros((1, 2)),
    ...                 np.array([0.5, 1.0]), np.ones(2))
    >>> G.ravel().tolist()
    [1.0, 0.0]
    """
    return _next_G_mu(_gains(P_prev, J.T @ S_inv_J, None, F, Q)[0], F, G_mu)


class Sandwich:
    """The linearised filter's error terms of one tracker: ``update`` after each step gives
    the variance to add to the reported std of the augmented state (18,) and of the angles
    (2,): ``G K_res G^T`` of a persistent metamodel error (``metamodel``) and
    ``G_mu E[d d^T] G_mu^T`` of an assumed mu (``mu_assumed``)."""

    def __init__(self, ssm: Any, gated: bool = False, metamodel: bool = True,
                 mu_assumed: bool = False) -> None:
        """For the tracker's model ``ssm`` (:class:`~formtwin.tracker.BendingSSM`);
        ``gated``: ``B`` times the posterior probability of ``kappa > 0``; ``metamodel``:
        the metamodel error's term; ``mu_assumed``: the assumed mu's term, with the offset
        ``d = mu_line - mu`` of the line's mu drawn from ``U(mu_min, mu_max)``:
        ``E[d d^T] = diag(range^2 / 12) + (mid - mu)(mid - mu)^T``."""
        self.ssm = ssm
        self.gated = gated
        nx, self.m = ssm.n_x, ssm.n_varying
        lo, hi = ssm._lo[:self.m], ssm._hi[:self.m]
        self.F = np.r_[ssm._rho, np.ones(self.m - nx)]
        self.Q = np.r_[(1.0 - ssm._rho**2) * ssm._sigma**2,
                       (ssm.config.alpha * (hi[nx:] - lo[nx:])) ** 2]
        k_res = residual_covariance(ssm.model) if metamodel else None
        n_t = ssm.spec.n_t
        self.k_half: FloatArray = np.zeros((n_t, 0))  # K_res = R R^T; none: no term
        if k_res is not None:
            lam, vec = np.linalg.eigh(0.5 * (k_res + k_res.T))
            self.k_half = vec * np.sqrt(np.maximum(lam, 0.0))
        mid, var = ssm.mu_prior
        #: E[d d^T] = R_mu R_mu^T (n_x, n_x + 1); zeros when mu is known or learned
        self.mu_half: FloatArray = np.c_[np.diag(np.sqrt(var)), mid - ssm._mu] \
            if mu_assumed else np.zeros((nx, 0))
        self.G = np.zeros((self.m, n_t))
        self.G_mu = self.G_mu0 = np.eye(self.m, nx)  # the initial law's mean is mu
        self._drive = np.eye(self.m, nx) * (1.0 - self.F[:nx])  # G_mu's constant input
        self._n_in, self._n_aug = ssm.n_in, ssm.n_aug
        self.P = self.P0 = np.diag(np.r_[ssm._sigma**2, (hi[nx:] - lo[nx:]) ** 2 / 12.0])
        self.J: FloatArray | None = None
        self.Ja: FloatArray | None = None
        #: ``(J, T, T J)``: the Jacobian in the adaptive likelihood's whitened coordinates
        self._tj: tuple[FloatArray, FloatArray, FloatArray] | None = None
        self._j_finite = False  # every entry of J finite (checked when J changes)

    def weight(self) -> float:
        """The factor on ``B``: 1, or (gated, adaptive likelihood) ``P(kappa > 0)``."""
        d = self.ssm.discrepancy
        if not self.gated or d is None or d.shared:
            return 1.0
        return float(np.exp(self.ssm.share_logpost) @ (d.shares > 0))

    def update(self, x: FloatArray, w: FloatArray, y: FloatArray, t: int,
               u: FloatArray | None, mean: FloatArray | None = None,
               cov: FloatArray | None = None) -> tuple[FloatArray, FloatArray]:
        """After product ``t`` (0-based) with particles ``x`` (N, d), weights ``w`` (N,)
        and curve ``y`` (n_t,): the variances (n_aug,) and (2,) to add to the cloud's
        for the state and the angles at setting ``u``; ``mean`` (d,) ``w @ x`` and
        ``cov`` the cloud's covariance (m, m) of the :attr:`m` columns that vary
        (:func:`~formtwin.tracker._kernels.cloud_moments`) when the caller has them
        (None: computed here)."""
        m, n_in = self.m, self._n_in
        mean = w @ x if mean is None else mean
        P = cloud_moments(x, w, mean, m)[1] if cov is None else cov
        finite = bool(np.all(np.isfinite(P)))
        if self.J is None or t % EVERY == 0:
            self._refresh(mean, np.sqrt(np.maximum(np.diag(P), 0.0)), y, u)
        assert self.J is not None and self.Ja is not None
        if self._j_finite and finite:
            info, s_inv_j = self._information()
            if self.ssm.ahead:  # a state variable's value in this step: its information too
                info = info.copy()
                for j, (_, r2) in self.ssm.ahead.items():
                    info[j, j] += 1.0 / r2
            if self.k_half.size:  # the gain K too: one LAPACK solve for both terms
                M, K = _gains(self.P, info, s_inv_j, self.F, self.Q)
                assert K is not None
                self.G = _next_G(M, K, self.F, self.G)
                if self.mu_half.size:
                    self.G_mu = _next_G_mu(M, self.F, self.G_mu, self._drive)
            elif self.mu_half.size:  # G_mu alone: one kernel solves for it
                self.G_mu, ok = mu_gain_step(self.P, info, self.F, self.Q, self.G_mu,
                                             self._drive)
                if not ok:  # singular in floating point: NumPy's error, as before
                    raise np.linalg.LinAlgError("Singular matrix")
            self.P = P
        # each term present adds its variances (m,) and the angles' (n_out,); a term left
        # out would add exactly 0, so it is not computed
        var, avar = np.zeros(self._n_aug), np.zeros(self.Ja.shape[0])
        if self.k_half.size:
            c = self.weight()
            H = self.G @ self.k_half  # B = H H^T
            Ha = self.Ja @ H[:n_in]
            var[:m] += c * np.sum(H * H, axis=1)
            avar += c * np.sum(Ha * Ha, axis=1)
        if self.mu_half.size:
            var_mu, avar_mu = term_variances(self.G_mu, self.mu_half, self.Ja, n_in)
            var[:m] += var_mu
            avar += avar_mu
        return var, avar

    def _information(self) -> tuple[FloatArray, FloatArray | None]:
        """``J^T S^-1 J`` (m, m) and, for the metamodel's term, ``S^-1 J`` (n_t, m) under
        the likelihood's covariance ``S`` of this product: with the adaptive likelihood
        from ``T J`` (kept until ``J`` or the whitening ``T`` changes) as
        ``(TJ)^T diag(1/v) TJ`` and ``T^T diag(1/v) TJ`` (``S = T^-1 diag(v) T^-T``), else
        by a solve with ``S``."""
        assert self.J is not None
        want = self.k_half.size > 0
        white = self.ssm._lik_whitening()
        if white is None:
            S_inv_J = np.linalg.solve(np.asarray(self.ssm._lik_cov()), self.J)
            return self.J.T @ S_inv_J, S_inv_J if want else None
        T, v = white
        if self._tj is None or self._tj[0] is not self.J or self._tj[1] is not T:
            self._tj = (self.J, T, T @ self.J)
        TJ = self._tj[2]
        if not want:
            return information(TJ, v), None
        scaled = TJ / v[:, None]
        return TJ.T @ scaled, T.T @ scaled

    def _refresh(self, mean: FloatArray, spread: FloatArray, y: FloatArray,
                 u: FloatArray | None) -> None:
        """The curve's Jacobian (n_t, m) and the angles' gradient (2, n_in) at ``mean``:
        the model's own derivatives where it has them (``model.differentiable``: its
        ``curve_jacobian`` and ``angle_gradient``; forward differences in ``theta_d``),
        else forward differences (module doc)."""
        ssm, n_in = self.ssm, self.ssm.n_in
        J, step = ssm._cloud_jacobian(mean, spread[ssm.n_x:], y, exact=True)
        if getattr(ssm.model, "differentiable", False):
            Ja = ssm.model.angle_gradient(mean[None, :n_in], u)[0]
        else:
            base = np.repeat(mean[None, :n_in], n_in + 1, axis=0)
            base[1:] += np.diag(step[:n_in])
            a = ssm.model.predict_angles(base, u)
            Ja = (a[1:] - a[0]).T / step[:n_in]
        # C order, as restored from a checkpoint: the same BLAS path, the same last bits
        self.J = np.ascontiguousarray(J)
        self.Ja = np.ascontiguousarray(Ja)
        self._j_finite = bool(np.all(np.isfinite(self.J)))

    def snapshot(self) -> tuple[Any, ...]:
        """The recursion's arrays, for :meth:`restore` (they are replaced, never changed in
        place, so references suffice)."""
        return self.G, self.P, self.J, self.Ja, self.G_mu

    def restore(self, snap: tuple[Any, ...]) -> None:
        """Back to a :meth:`snapshot`."""
        self.G, self.P, self.J, self.Ja, self.G_mu = snap
        self._j_finite = self.J is not None and bool(np.all(np.isfinite(self.J)))

    def state(self) -> dict[str, FloatArray]:
        """The recursion's arrays (for the tracker's checkpoint; not copies: they are
        replaced, never changed in place)."""
        if self.J is None or self.Ja is None:
            return {}
        return dict(zip(STATE_KEYS, (self.G, self.P, self.J, self.Ja, self.G_mu),
                        strict=True))

    def set_state(self, d: dict[str, Any]) -> None:
        """Continue from :meth:`state` (arrays, or lists of numbers as in version 1's
        states; an empty dict: the start)."""
        n_t, m, n_in, nx = self.G.shape[1], self.m, self.ssm.n_in, self.ssm.n_x
        if not d:
            self.G, self.P, self.J, self.Ja = np.zeros((m, n_t)), self.P0, None, None
            self.G_mu = self.G_mu0
            return
        self.G = np.array(d["sandwich_G"], dtype=np.float64).reshape(m, n_t)
        self.P = np.array(d["sandwich_P"], dtype=np.float64).reshape(m, m)
        self.J = np.array(d["sandwich_J"], dtype=np.float64).reshape(n_t, m)
        self._j_finite = bool(np.all(np.isfinite(self.J)))
        self.Ja = np.array(d["sandwich_Ja"], dtype=np.float64).reshape(2, n_in)
        self.G_mu = np.array(d["sandwich_Gmu"], dtype=np.float64).reshape(m, nx) \
            if "sandwich_Gmu" in d else self.G_mu0
