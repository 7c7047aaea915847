"""State evolution (paper eq. 4-5) and parameter jitter (eq. 10).

Each state variable follows an AR(1) process

    x_i = (1 - rho) mu + rho x_{i-1} + v,    v ~ N(0, (1 - rho^2) sigma^2),

whose stationary distribution is N(mu, sigma^2). Constant parameters get a small random
walk, ``theta_i = theta_{i-1} + u`` with ``u ~ N(0, (alpha (max - min))^2)``, so that the
particle filter cannot get stuck on a wrong value.

Bounds
------
The metamodel is valid only inside the design box ``[min, max]``. Values that leave it are
**reflected** back at the bound (``x -> 2 max - x``, repeatedly if needed). Reflection keeps
the random walk unbiased and its step size intact, whereas clipping would pile particles up
exactly on the bound. It is applied to the filter's particles and to generated truth alike.

>>> import numpy as np
>>> reflect(np.array([1.2, -0.3, 0.5]), np.zeros(3), np.ones(3))
array([0.8, 0.3, 0.5])
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.special import log_ndtr, ndtri_exp

FloatArray = NDArray[np.float64]

DEFAULT_ALPHA = 0.01


def reflect(values: FloatArray, lo: FloatArray, hi: FloatArray) -> FloatArray:
    """Fold ``values`` (..., d) into the box ``[lo, hi]`` (d,) by mirror reflection."""
    width = hi - lo
    u = np.mod(values - lo, 2.0 * width)
    return lo + np.where(u > width, 2.0 * width - u, u)


def into_box(values: FloatArray, lo: FloatArray, hi: FloatArray) -> FloatArray:
    """:func:`reflect` applied, in place, to the rows of ``values`` (N, d) that left the box
    ``[lo, hi]`` (d,); the other rows are kept as they are (most rows stay inside, and
    ``reflect`` costs a float modulo per entry and rounds a value inside the box through
    ``lo + (value - lo)``: by at most an ulp)."""
    rows = np.any((values < lo) | (values > hi), axis=1)
    if rows.any():
        values[rows] = reflect(values[rows], lo, hi)
    return values


def evolve(
    x: FloatArray,
    mu: FloatArray,
    sigma: FloatArray,
    rho: FloatArray,
    rng: np.random.Generator,
    lo: FloatArray | None = None,
    hi: FloatArray | None = None,
) -> FloatArray:
    """One AR(1) step (eq. 4-5) for a batch of states.

    Parameters
    ----------
    x : (N, d) states of product i-1.
    mu, sigma, rho : (d,) or (N, d) statistics ``theta_s``.
    rng : source of the noise ``v``.
    lo, hi : (d,) optional box; states leaving it are reflected back.

    Returns
    -------
    (N, d) states of product i.
    """
    noise = rng.standard_normal(x.shape) * (np.sqrt(1.0 - rho**2) * sigma)
    out: FloatArray = (1.0 - rho) * mu + rho * x + noise
    if lo is not None and hi is not None:
        out = reflect(out, lo, hi)
    return out


def stationary(
    n: int,
    mu: FloatArray,
    sigma: FloatArray,
    rng: np.random.Generator,
    lo: FloatArray | None = None,
    hi: FloatArray | None = None,
) -> FloatArray:
    """``n`` draws ``(n, d)`` from the stationary distribution N(mu, sigma^2), reflected."""
    out: FloatArray = mu + sigma * rng.standard_normal((n, np.size(mu)))
    if lo is not None and hi is not None:
        out = reflect(out, lo, hi)
    return out


def simulate(
    n: int,
    mu: FloatArray,
    sigma: FloatArray,
    rho: FloatArray,
    rng: np.random.Generator,
    lo: FloatArray | None = None,
    hi: FloatArray | None = None,
) -> FloatArray:
    """A state sequence ``(n, d)`` of ``n`` products, started from the stationary law."""
    d = np.size(mu)
    out = np.empty((n, d))
    out[0] = stationary(1, mu, sigma, rng, lo, hi)[0]
    noise = rng.standard_normal((n, d)) * (np.sqrt(1.0 - rho**2) * sigma)
    for i in range(1, n):  # sequential by nature: product i depends on product i-1
        step = (1.0 - rho) * mu + rho * out[i - 1] + noise[i]
        out[i] = step if lo is None or hi is None else reflect(step, lo, hi)
    return out


def jitter(
    theta: FloatArray,
    lo: FloatArray,
    hi: FloatArray,
    rng: np.random.Generator,
    alpha: float = DEFAULT_ALPHA,
) -> FloatArray:
    """Random-walk step (eq. 10) of parameters ``(N, d)``, std ``alpha (hi - lo)``, the rows
    that left the box reflected back (:func:`into_box`)."""
    if alpha < 0:
        raise ValueError(f"alpha = {alpha}, expected alpha >= 0")
    return into_box(theta + rng.standard_normal(theta.shape) * (alpha * (hi - lo)), lo, hi)


# ---------------------------------------------------------------- conjugate learning of mu
# Given the states, eq. 4 is linear-Gaussian in mu: y_i = x_i - rho x_{i-1} = (1 - rho) mu + v
# with v ~ N(0, (1 - rho^2) sigma^2). A Normal prior mu ~ N(m, P) stays Normal; (m, P) per
# particle are the sufficient statistics of its path (Storvik 2002; Carvalho et al. 2010,
# particle learning), and x can be drawn from the predictive with mu integrated out.


def mu_predictive(m: FloatArray, P: FloatArray, x: FloatArray, sigma: FloatArray,
                  rho: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Mean and variance ``(N, d)`` of ``x_i`` given ``x_{i-1} = x`` with ``mu ~ N(m, P)``:
    ``(1 - rho) m + rho x`` and ``(1 - rho)^2 P + (1 - rho^2) sigma^2``."""
    a = 1.0 - rho
    return a * m + rho * x, a * a * P + (1.0 - rho**2) * sigma**2


def mu_update(m: FloatArray, P: FloatArray, x_prev: FloatArray, x_new: FloatArray,
              sigma: FloatArray, rho: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Posterior ``(m, P)`` of mu after the step ``x_prev -> x_new`` (conjugate Normal update).

    >>> import numpy as np
    >>> m, P = mu_update(np.array([0.0]), np.array([1.0]), np.array([0.0]), np.array([1.0]),
    ...                  np.array([1.0]), np.array([0.0]))
    >>> float(m[0]), float(P[0])   # rho = 0: one draw x = 1 of N(mu, 1), prior N(0, 1)
    (0.5, 0.5)
    """
    a = 1.0 - rho
    q = (1.0 - rho**2) * sigma**2
    prec = 1.0 / P + a * a / q
    P_new = 1.0 / prec
    return P_new * (m / P + a * (x_new - rho * x_prev) / q), P_new


# With the paper's prior mu ~ U(mu_min, mu_max) (the law the study draws mu from) the
# posterior given a path is the Normal of the flat-prior update truncated to the range:
# (m, P) are the same sufficient statistics, started from x_0 (m = x_0, P = sigma^2).


def _lower_tail(m: FloatArray, s: FloatArray, lo: FloatArray, hi: FloatArray
                ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Standardised bounds ``(a, b)`` of ``N(m, s^2)`` truncated to ``[lo, hi]``, mirrored
    so that the interval lies mostly below the mean (``a + b <= 0``: the stable side of
    the normal CDF), the sign (+-1) of the mirror, and ``log Z = log(Phi(b) - Phi(a))``."""
    a, b = (lo - m) / s, (hi - m) / s
    flip = np.where(a + b > 0, -1.0, 1.0)
    a, b = np.where(flip > 0, a, -b), np.where(flip > 0, b, -a)
    la, lb = log_ndtr(a), log_ndtr(b)
    with np.errstate(divide="ignore"):
        log_z = lb + np.log1p(-np.exp(la - lb))
    return a, b, flip, log_z


def truncated_normal(m: FloatArray, P: FloatArray, lo: FloatArray, hi: FloatArray,
                     rng: np.random.Generator) -> FloatArray:
    """Draws (N, d) of ``N(m, P)`` truncated to ``[lo, hi]`` (inverse CDF in log space,
    exact also far in a tail).

    >>> import numpy as np
    >>> v = truncated_normal(np.array([[50.0]]), np.array([[1.0]]), np.array([0.0]),
    ...                      np.array([1.0]), np.random.default_rng(0))
    >>> bool(0.9 < v[0, 0] <= 1.0)   # the mean is 49 std above the range: at its top
    True
    """
    s = np.sqrt(P)
    a, b, flip, log_z = _lower_tail(m, s, lo, hi)
    log_u = np.logaddexp(log_ndtr(a), np.log(rng.random(np.shape(a))) + log_z)
    z = np.clip(ndtri_exp(np.minimum(log_u, 0.0)), a, b)
    out: FloatArray = m + flip * s * z
    return out


def truncated_moments(m: FloatArray, P: FloatArray, lo: FloatArray, hi: FloatArray
                      ) -> tuple[FloatArray, FloatArray]:
    """Mean and variance (N, d) of ``N(m, P)`` truncated to ``[lo, hi]``.

    >>> import numpy as np
    >>> mean, var = truncated_moments(np.zeros(1), np.ones(1), np.zeros(1), np.full(1, np.inf))
    >>> round(float(mean[0]), 4), round(float(var[0]), 4)   # half-normal: sqrt(2/pi), 1 - 2/pi
    (0.7979, 0.3634)
    """
    s = np.sqrt(P)
    a, b, flip, log_z = _lower_tail(m, s, lo, hi)
    half_log_2pi = 0.5 * np.log(2.0 * np.pi)
    with np.errstate(invalid="ignore", over="ignore"):
        ra = np.exp(-0.5 * a * a - half_log_2pi - log_z)
        rb = np.exp(-0.5 * b * b - half_log_2pi - log_z)
        mz = ra - rb
        vz = 1.0 + np.where(np.isfinite(a), a * ra, 0.0) - np.where(np.isfinite(b), b * rb,
                                                                     0.0) - mz * mz
    return m + flip * s * mz, P * np.clip(vz, 0.0, 1.0)
