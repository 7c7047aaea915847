"""What any chart can see of a step in a state's mean from the force curves: a bound from
the linear-Gaussian approximation of the process.

Linearise the curves about the line's mean, ``z_i = z(mu) + J (x_i - mu) + v_i`` with ``J``
(n_t, 7) the curve's Jacobian in the state (:func:`curve_jacobian`) and ``v_i ~ N(0, R)``
the measurement noise; the state follows eq. 4 (AR(1) about ``mu``). The Kalman filter is
then the optimal tracker (:func:`steady_filter`: steady state; everything follows from the
7 x 7 information ``M = J^T R^-1 J`` of one curve), and its innovations ``nu_i`` hold all
the information the curves carry about a change. A level step ``delta`` of state ``j`` at
product 0 moves the innovations' mean by ``r_k = J (delta e_j - A m_{k-1})`` at lag ``k``,
``m_k = A m_{k-1} + K r_k`` the estimate's mean offset (Willsky & Jones 1976; Basseville &
Nikiforov 1993, ch. 7). So:

* the GLR on all the innovations (``full``) has the noncentrality ``sum_k r_k^T S^-1 r_k``
  after ``n`` products: no test on the curves does better;
* the GLR on state ``j``'s own estimate residual ``(K nu_i)_j``, what the monitor's GLR
  chart watches, has the signature ``(K r_k)_j / sqrt((K S K^T)_jj)`` (:func:`step_in_filter`);
* the delays of that optimal GLR at a design ``ARL0`` follow by simulation
  (:func:`glr_delays`).

With the state observed exactly (``R`` -> 0) the signature is the level signature of the
true state's AR(1) model (:func:`~formtwin.monitoring.glr.level_signature`): the oracle.

The approximation knows the machine parameters, the noise law and the model (the particle
filter learns the first and approximates the rest), so it bounds what a monitor of the
estimates can reach; the particle filter's estimates lose more (docs/explanation/monitoring.md).

>>> f = steady_filter(np.ones((1, 1)), np.eye(1), rho=np.array([0.8]), sigma=np.ones(1))
>>> s = step_in_filter(f, 0, 2.0, 200)
>>> k = f.gain_state[0, 0]                  # the long-run share of a step: K / (1 - rho + K rho)
>>> bool(abs(s.share[-1] - k / (1 - 0.8 + 0.8 * k)) < 1e-9)
True
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from formtwin.measurement import ProcessModel
from formtwin.monitoring.glr import glr_h, glr_statistics

FloatArray = NDArray[np.float64]


def curve_jacobian(model: ProcessModel, inputs: FloatArray, steps: FloatArray) -> FloatArray:
    """``d z / d x`` (n_t, n_x) of the model's curve at ``inputs`` (n_in,) by central
    differences of ``steps`` (n_x,) in the first ``n_x`` inputs (the state)."""
    x0 = np.asarray(inputs, dtype=np.float64)
    h = np.asarray(steps, dtype=np.float64)
    nx = h.size
    plus = np.tile(x0, (nx, 1)) + np.diag(h) @ np.eye(nx, x0.size)
    minus = np.tile(x0, (nx, 1)) - np.diag(h) @ np.eye(nx, x0.size)
    diff = np.asarray(model.predict_curves(plus)) - np.asarray(model.predict_curves(minus))
    out: FloatArray = (diff / (2.0 * h[:, None])).T
    return out


@dataclass(frozen=True)
class SteadyFilter:
    """The steady-state Kalman filter of the linearised process.

    Attributes
    ----------
    rho : (n_x,) the state's AR(1) coefficients (``A = diag(rho)``).
    info : (n_x, n_x) information of one curve ``J^T R^-1 J``.
    predicted : (n_x, n_x) covariance of the one-step prediction ``P^-``.
    posterior : (n_x, n_x) covariance after the update ``P``.
    """

    rho: FloatArray
    info: FloatArray
    predicted: FloatArray
    posterior: FloatArray

    @property
    def gain_state(self) -> FloatArray:
        """``K J = P M`` (n_x, n_x): how a state offset seen in a curve moves the estimate."""
        out: FloatArray = self.posterior @ self.info
        return out

    @property
    def own_variance(self) -> FloatArray:
        """Variance (n_x,) of each estimate's residual ``(K nu)_j``: ``diag(K S K^T)`` =
        ``diag(P (M P^- M + M) P)``."""
        m, p = self.info, self.posterior
        return np.diag(p @ (m @ self.predicted @ m + m) @ p).copy()

    @property
    def innovation_info(self) -> FloatArray:
        """``J^T S^-1 J`` (n_x, n_x) = ``M - M (P^-^-1 + M)^-1 M`` (Woodbury)."""
        m = self.info
        out: FloatArray = m - m @ self.posterior @ m
        return out


def steady_filter(jacobian: FloatArray, noise: FloatArray, rho: FloatArray, sigma: FloatArray,
                  iterations: int = 2000) -> SteadyFilter:
    """The steady-state filter for curves ``J x + v``, ``v ~ N(0, noise)`` (n_t, n_t), of a
    state with AR(1) coefficients ``rho`` (n_x,) and stationary std ``sigma`` (n_x,),
    by iterating the Riccati recursion from the stationary prior."""
    j = np.asarray(jacobian, dtype=np.float64)
    rinv_j = np.linalg.lstsq(np.asarray(noise, dtype=np.float64), j, rcond=None)[0]
    m = j.T @ rinv_j
    m = 0.5 * (m + m.T)
    a = np.diag(np.asarray(rho, dtype=np.float64))
    q = np.diag(np.asarray(sigma, dtype=np.float64) ** 2 * (1.0 - np.asarray(rho) ** 2))
    p: FloatArray = np.diag(np.asarray(sigma, dtype=np.float64) ** 2)
    pm: FloatArray = p
    for _ in range(iterations):
        pm = a @ p @ a.T + q
        new = np.asarray(np.linalg.inv(np.linalg.inv(pm) + m), dtype=np.float64)
        done = bool(np.allclose(new, p, rtol=1e-12, atol=0.0))
        p = new
        if done:
            break
    return SteadyFilter(np.asarray(rho, dtype=np.float64), m, pm, p)


@dataclass(frozen=True)
class StepInFilter:
    """What a level step of one state leaves in the linearised filter, by lag (n,) after it.

    Attributes
    ----------
    share : the estimate's mean offset over the step (1: it shows all of it).
    own : mean of the standardised residual of the state's own estimate (the signature,
        in residual sigmas, that the monitor's GLR chart of that state is matched to).
    full : noncentrality increments ``r_k^T S^-1 r_k`` of all the innovations.
    """

    share: FloatArray
    own: FloatArray
    full: FloatArray

    def expected_glr(self, n: int, full: bool = False) -> float:
        """The GLR statistic's mean at the true change time ``n`` products after it:
        ``(1 + noncentrality) / 2``."""
        inc = self.full if full else self.own**2
        return float((1.0 + np.sum(inc[:n])) / 2.0)


def step_in_filter(f: SteadyFilter, j: int, delta: float, n: int) -> StepInFilter:
    """The response of filter ``f`` to a step ``delta`` (internal units) of state ``j``'s
    level, over ``n`` products (see the module doc)."""
    nx = f.rho.size
    step = np.zeros(nx)
    step[j] = delta
    kj, ii, sd = f.gain_state, f.innovation_info, np.sqrt(f.own_variance[j])
    m = np.zeros(nx)
    share, own, full = np.empty(n), np.empty(n), np.empty(n)
    for k in range(n):
        e = step - f.rho * m  # the prediction error's mean
        full[k] = e @ ii @ e
        dm = kj @ e
        own[k] = dm[j] / sd
        m = f.rho * m + dm
        share[k] = m[j] / delta
    return StepInFilter(share, own, full)


def glr_delays(signature: FloatArray, arl0: float, window: int = 200, runs: int = 1000,
               horizon: int = 150, before: int = 100, seed: int = 0) -> FloatArray:
    """Delays (runs,) of a GLR chart matched to ``signature`` (residual sigmas by lag,
    the change's true size) at the design ``arl0`` (:func:`~formtwin.monitoring.glr.glr_h`):
    independent N(0, 1) scores, ``before`` products in control, then the change; the
    products from the change to the first crossing (``horizon + 1``: none within
    ``horizon``)."""
    s = np.asarray(signature, dtype=np.float64)
    shape = tuple(s / np.max(np.abs(s)))
    h = glr_h(shape, window, arl0)
    z = np.random.default_rng(seed).standard_normal((runs, before + horizon))
    n = min(horizon, s.size)
    z[:, before:before + n] += s[:n]
    if s.size < horizon:
        z[:, before + n:] += s[-1]
    crossed = glr_statistics(shape, window, z)[:, before:] > h
    out: FloatArray = np.where(crossed.any(axis=1), crossed.argmax(axis=1) + 1.0,
                               horizon + 1.0)
    return out


__all__ = ["SteadyFilter", "StepInFilter", "curve_jacobian", "glr_delays", "step_in_filter",
           "steady_filter"]
