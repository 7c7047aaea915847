"""Absolute goodness of fit of a curve, from the measurement model itself.

A filter always produces an estimate, even from a curve that no particle explains (a
metamodel of another press, a dead sensor, wrong units); its weights then sit on the least
bad particle and its posterior std goes to zero, which looks like certainty. This module
says whether the *measurement model* explains the curve, with no baseline learned from the
stream (a model that never fits would teach a learned baseline that misfit is normal).

The statistic is the Mahalanobis distance of the curve from its predictive distribution
``p(z_i | Z_{i-1})``. For predicted particle ``k`` (predictive weight ``v_k``) the
measurement model says ``r_k = obs_k - model_k ~ N(0, Sigma)`` (with the default
``compare="measurement"`` ``obs_k = z`` and ``model_k = g(z~(x_k, theta_k), theta_d_k)``;
in the paper's eq. 12 ``obs_k = g^-1(z, theta_d_k)`` and ``model_k = z~(x_k, theta_k)``),
with ``Sigma`` the likelihood's own
covariance (:meth:`~formtwin.measurement.MeasurementModel.covariance`, whatever the
likelihood is configured with). Over the cloud the residual has mean ``r_bar = sum v_k r_k``
and covariance ``Sigma + C`` with ``C`` the weighted covariance of the ``r_k`` (the cloud's
own spread; at start-up and after a process change the cloud is wide, and a curve far from
every particle is still explained by the spread). Then::

    distance2 = r_bar^T (Sigma + C)^-1 r_bar  ~  chi2(n_t)      (Gaussian approximation)
    quantile  = F_chi2(distance2; n_t),      log10_p = log10(1 - quantile)

(for the Student-t likelihood with ``nu`` degrees of freedom ``distance2 / n_t`` is
referred to ``F(n_t, nu)``). ``C`` comes from at most :data:`MAX_SPREAD` particles taken
at a regular stride (bounds the cost at ~0.3 ms for any N).

Health of the estimate (:data:`formtwin.estimates.HEALTH`), with :class:`FitRule`:

* ``no_fit``: ``1 - quantile < p_fail`` (default 1e-3: the curve lies beyond the 99.9 %
  quantile of what the measurement model allows), or the step collapsed;
* ``degraded``: ``1 - quantile < p_warn`` (default 1e-2), or ``ESS / N < ess_share_min``
  (default 0.01: fewer than 5 effective particles of 500);
* ``ok`` otherwise.

>>> import numpy as np
>>> from formtwin.measurement import MeasurementModel
>>> mm = MeasurementModel(basis=np.eye(4)[:, :2], lam=np.array([4.0, 1.0]), s2=1.0)
>>> r = np.zeros((10, 4)); r[:, 1] = 1.0          # every particle 1 std off, no spread
>>> f = assess(r, np.full(10, 0.1), ess=10.0, measurement=mm)
>>> f.health, round(f.distance2, 6), f.dof
('ok', 1.0, 4)
>>> assess(r * 20.0, np.full(10, 0.1), ess=10.0, measurement=mm).health
'no_fit'
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.linalg.blas import dsyrk as _syrk
from scipy.linalg.lapack import dpotrf as _potrf
from scipy.linalg.lapack import dtrtrs as _trtrs
from scipy.special import gammaincc, gammaln

from formtwin.estimates import Fit
from formtwin.measurement import MeasurementModel
from formtwin.tracker._kernels import centred_spread

FloatArray = NDArray[np.float64]

_LN10 = math.log(10.0)

#: at most this many particles (at a regular stride) give the cloud's spread ``C``
MAX_SPREAD = 256


@dataclass(frozen=True)
class FitRule:
    """Thresholds from :class:`~formtwin.estimates.Fit` to health (see module doc).

    Attributes
    ----------
    p_fail : posterior predictive p-value below which the curve is not explained.
    p_warn : p-value below which the estimate is ``degraded``.
    ess_share_min : ESS / N below which the estimate is ``degraded``.
    """

    p_fail: float = 1e-3
    p_warn: float = 1e-2
    ess_share_min: float = 0.01

    def __post_init__(self) -> None:
        if not 0 < self.p_fail <= self.p_warn < 1:
            raise ValueError(f"expected 0 < p_fail ({self.p_fail}) <= p_warn "
                             f"({self.p_warn}) < 1")
        if not 0 <= self.ess_share_min < 1:
            raise ValueError(f"ess_share_min = {self.ess_share_min}, expected in [0, 1)")


def _stride(n: int) -> int:
    """The stride of the rows of ``n`` that give the cloud's spread (at most
    :data:`MAX_SPREAD` rows)."""
    return max(1, -(-n // MAX_SPREAD))


def distance_logsf(m2: FloatArray, measurement: MeasurementModel) -> FloatArray:
    """``log P(D >= m2)`` (N,) for the squared distance ``D`` of a curve drawn from the
    measurement model: ``chi2(n_t)`` (Gaussian) or ``n_t F(n_t, nu)`` (Student-t).

    Far in the tail, where scipy's ``logsf`` underflows to ``-inf``, the chi-square tail
    uses the leading term of the continued fraction of the upper incomplete gamma function
    (exact to within ``(a - 1) / (x - a + 1)`` relative in the tail probability).
    """
    m2 = np.asarray(m2, dtype=np.float64)
    n_t, nu = measurement.n_t, measurement.nu
    if math.isinf(nu):
        with np.errstate(divide="ignore"):  # chi2.logsf without scipy.stats' overhead
            out = np.log(gammaincc(0.5 * n_t, np.maximum(0.5 * m2, 0.0)))
        far = np.isneginf(out) & np.isfinite(m2)
        if far.any():  # Q(a, x) ~ x^(a-1) e^-x / Gamma(a) / (1 - (a-1)/x), x = m2/2
            a, x = 0.5 * n_t, 0.5 * m2[far]
            out[far] = ((a - 1) * np.log(x) - x - gammaln(a)
                        - np.log1p(-np.minimum((a - 1) / x, 0.5)))
    else:
        from scipy.stats import f as fdist  # on use: ~1.3 s CPU to import

        out = np.asarray(fdist.logsf(m2 / n_t, n_t, nu), dtype=np.float64)
    return np.where(np.isnan(m2), -np.inf, out)


def _distance_logsf1(m2: float, measurement: MeasurementModel) -> float:
    """:func:`distance_logsf` of one squared distance, in scalars (the same functions)."""
    n_t, nu = measurement.n_t, measurement.nu
    if math.isnan(m2):
        return -math.inf
    if not math.isinf(nu):
        from scipy.stats import f as fdist  # on use: ~1.3 s CPU to import

        return float(fdist.logsf(m2 / n_t, n_t, nu))
    q = float(gammaincc(0.5 * n_t, max(0.5 * m2, 0.0)))
    if q > 0.0:
        return float(np.log(q))
    if math.isinf(m2):
        return -math.inf
    a, x = 0.5 * n_t, 0.5 * m2  # far in the tail: the continued fraction's leading term
    return float((a - 1) * np.log(x) - x - gammaln(a) - np.log1p(-min((a - 1) / x, 0.5)))


def assess(residuals: FloatArray, v: FloatArray, ess: float,
           measurement: MeasurementModel, collapsed: bool = False,
           rule: FitRule | None = None, scale: float = 1.0,
           covariance: FloatArray | None = None) -> Fit:
    """The goodness of fit of one step.

    Parameters
    ----------
    residuals : (N, n_t) ``obs_k - model_k`` of the predicted particles, N.
    v : (N,) their predictive weights (before the update; uniform after resampling).
    ess : the step's effective sample size (of the N particles of the filter).
    measurement : the likelihood (gives ``Sigma``, ``n_t`` and ``nu``).
    collapsed : the step collapsed (no particle explained the curve).
    rule : thresholds; default :class:`FitRule()`.
    scale : factor on ``Sigma`` (the learned likelihood scale, ``learn_scale``; else 1).
    covariance : (n_t, n_t) the residuals' predictive covariance N^2 when it is not
        ``scale * Sigma`` (the discrepancy likelihood), else ``None``; or (n_t,) its
        variances when ``residuals`` are given in coordinates where it is diagonal (the
        likelihood's whitened ones, which the step computed: the same distance, without
        the (n_t, n_t) covariance).
    """
    rule = FitRule() if rule is None else rule
    r = np.ascontiguousarray(residuals, dtype=np.float64)
    v = np.ascontiguousarray(v, dtype=np.float64)
    share = min(float(ess) / max(r.shape[0], 1), 1.0)
    every = False
    if not collapsed and r.shape[0]:  # the usual case: every row weighted, and a NaN or
        # inf in a row carries into the mean: the weights normalised, the mean and the
        # spread's rows in one pass (Numba)
        r_bar, every, rc = centred_spread(r, v, _stride(r.shape[0]))
    if not every:
        ok = np.isfinite(r.sum(axis=1)) & (v > 0)  # rows with NaN or inf (a row sum is
        if collapsed or not ok.any():              # finite below ~1e306 N: any curve)
            return Fit(distance2=math.inf, dof=measurement.n_t, quantile=1.0,
                       log10_p=-math.inf, ess_share=share, health="no_fit")
        if not ok.all():
            r, v = r[ok], v[ok]
        r_bar, _, rc = centred_spread(r, v, _stride(r.shape[0]))
    # rc^T rc, its lower triangle (all potrf reads), as A A^T of A = rc^T (n_t, rows):
    # Fortran order, no copy
    cov = _syrk(1.0, rc.T, trans=0, lower=1)
    if covariance is None:
        cov += scale * measurement.covariance()
    elif covariance.ndim == 1:
        cov.flat[::cov.shape[0] + 1] += covariance
    else:
        cov += covariance
    # the Cholesky factor and one triangular solve, straight from LAPACK (scipy.linalg's
    # wrappers check and copy: ~0.1 ms per product)
    chol, info = _potrf(cov, lower=1, clean=0, overwrite_a=1)
    if info != 0:  # not positive definite in floating point: NumPy's error, as before
        raise np.linalg.LinAlgError("Matrix is not positive definite")
    z, info = _trtrs(chol, r_bar, lower=1)
    d2 = float(z @ z)
    logp = min(_distance_logsf1(d2, measurement), 0.0)
    p = math.exp(logp)
    if p < rule.p_fail:
        health = "no_fit"
    elif p < rule.p_warn or share < rule.ess_share_min:
        health = "degraded"
    else:
        health = "ok"
    return Fit(distance2=d2, dof=measurement.n_t, quantile=-math.expm1(logp),
               log10_p=logp / _LN10, ess_share=share, health=health)
