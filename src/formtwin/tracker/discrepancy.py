"""The metamodel's error as a discrepancy learned online (``likelihood="discrepancy"``).

The calibrated likelihood treats the metamodel's error as independent noise per product,
``r_i = z_i - z~(x_i) ~ N(0, Sigma_e + K_res)``. But the error of a metamodel near one
operating point is mostly *systematic*: the same smooth misfit of the curve for product
after product (``docs/explanation/likelihood.md``). Treating it as fresh noise every time
throws away information where there is no error (metamodel data: the state error grows)
and leaves the filter free to absorb a persistent misfit with wrong static parameters.

Here the error is split into a discrepancy ``b`` shared by the products (Kennedy &
O'Hagan 2001) and a part that changes from product to product, a share ``kappa`` of
``K_res``::

    r_i = b + e_i,   b ~ N(0, (1 - kappa) K_res),   e_i ~ N(0, Sigma + kappa K_res),

``Sigma = fraction^2 K_MC + sigma_n^2 I`` the paper's covariance. ``kappa = 1`` is the
calibrated likelihood, ``kappa = 0`` an error that is all shared. Given a particle's path
this is linear-Gaussian in ``b``, so ``b`` is integrated out exactly per particle (Storvik
2002, as the learned mu): each particle carries the sufficient statistics of its residuals.
``Sigma`` and ``K_res`` are diagonalised together once: with ``Sigma = L L^T`` and
``L^-1 K_res L^-T = V diag(gamma) V^T``, the coordinates ``c = T r``, ``T = V^T L^-1``,
make every covariance above diagonal for every ``kappa``: per coordinate the noise has
variance ``s = 1 + kappa gamma`` and ``b`` the prior variance ``q = (1 - kappa) gamma``.
After ``n`` products with coordinates summing to ``S`` (n_t,), ``b`` is ``N(p S / s,
diag(p))`` with ``p = q s / (s + n q)``, and the next residual's predictive is

    c ~ N(p S / s, diag(s + p)),

an O(n_t) evaluation per particle after one (n_t, n_t) product. Then ``S += c``, ``n += 1``.
The statistics do not depend on ``kappa``, so one set serves a whole grid of ``kappa``:
``kappa`` is learned by Bayes' rule as a hyperparameter shared by all particles (a
posterior over the grid, updated by each product's evidence under each ``kappa``; the
particles are weighted by the posterior mixture). With no error in the data the evidence
picks ``kappa = 0`` and ``p -> 1/n``: the likelihood tends to the paper's.

Forgetting (``memory`` products, ``lambda = 1 - 1/memory``): ``S <- lambda S + c``,
``n <- lambda n + 1`` (exponentially discounted information), so the discrepancy can
follow a slowly moving operating point; ``inf`` keeps everything. The statistics are the
last ``n_t + 1`` particle columns, so they are resampled with their paths and saved in
checkpoints with the particles.

>>> import numpy as np
>>> d = Discrepancy.from_covariances(np.eye(2), np.diag([4.0, 0.0]))
>>> stats = np.zeros((1, 3))
>>> ll0 = d.loglik(np.zeros((1, 2)), stats)     # first product: c ~ N(0, diag(1 + gamma))
>>> bool(np.isclose(ll0[0, 0], -0.5 * (np.log(5.0) + 2 * np.log(2 * np.pi))))
True
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.special import gammaln

FloatArray = NDArray[np.float64]


@dataclass(frozen=True, eq=False)
class Discrepancy:
    """Conjugate learning of a curve discrepancy shared by products (module doc).

    Attributes
    ----------
    transform : (n_t, n_t) ``T = V^T L^-1``: residuals (N) to coordinates where ``Sigma``
        is ``I`` and ``K_res`` is ``diag(gamma)``.
    inverse : (n_t, n_t) ``T^-1 = L V`` (back to N).
    gamma : (n_t,) the variances of ``K_res`` in those coordinates (>= 0).
    logdet_t : ``log |det T|`` (the Jacobian of the change of coordinates).
    shares : (n_k,) the grid of ``kappa`` (independent share of ``K_res``), in [0, 1].
    forget : ``lambda`` in [0, 1], the factor on the statistics per product.
    shared : whether a shared part is learned (else ``Sigma + kappa K_res`` alone).
    nu : Student-t degrees of freedom (robust option; nothing shared only), ``inf``:
        Gaussian.
    """

    transform: FloatArray
    inverse: FloatArray
    gamma: FloatArray
    logdet_t: float
    shares: FloatArray
    forget: float = 1.0
    shared: bool = True
    nu: float = math.inf

    @classmethod
    def from_covariances(cls, noise_cov: FloatArray, error_cov: FloatArray,
                         shares: FloatArray | float = 0.0,
                         memory: float = math.inf, shared: bool = True,
                         nu: float = math.inf) -> Discrepancy:
        """From ``Sigma`` (n_t, n_t, positive definite) and ``K_res`` (n_t, n_t, positive
        semi-definite), N^2, the grid ``shares`` of ``kappa`` (or one value),
        ``memory`` (products, >= 1): ``lambda = 1 - 1/memory``, ``shared`` and ``nu``."""
        a = np.asarray(noise_cov, dtype=np.float64)
        b = np.asarray(error_cov, dtype=np.float64)
        if a.ndim != 2 or a.shape[0] != a.shape[1] or b.shape != a.shape:
            raise ValueError(f"covariances of shape {a.shape} and {b.shape}: expected two "
                             "(n_t, n_t)")
        k = np.atleast_1d(np.asarray(shares, dtype=np.float64))
        if k.ndim != 1 or k.size < 1 or np.any((k < 0) | (k > 1)):
            raise ValueError(f"shares {k}: expected values in [0, 1]")
        if not memory >= 1:
            raise ValueError(f"memory = {memory}, expected >= 1 product (inf: no forgetting)")
        if not (nu > 0 and (math.isinf(nu) or not shared)):
            raise ValueError(f"nu = {nu}: expected > 0, and inf when a part is shared")
        chol = np.linalg.cholesky(0.5 * (a + a.T))
        li = np.linalg.inv(chol)
        gam, v = np.linalg.eigh(li @ (0.5 * (b + b.T)) @ li.T)
        return cls(transform=v.T @ li, inverse=chol @ v, gamma=np.maximum(gam, 0.0),
                   logdet_t=-float(np.sum(np.log(np.diag(chol)))), shares=k,
                   forget=1.0 - 1.0 / memory, shared=shared, nu=float(nu))

    @property
    def n_t(self) -> int:
        """Samples per curve."""
        return int(self.gamma.size)

    @property
    def width(self) -> int:
        """Particle columns of the statistics: ``S`` (n_t) and ``n`` (1)."""
        return self.n_t + 1

    @cached_property
    def _coefficients0(self) -> tuple[FloatArray, FloatArray]:
        """:meth:`_coefficients` before any product (``n = 0``, also nothing shared): the
        same arrays every product, computed once (read-only)."""
        a, v = self._coefficients(0.0, cache=False)
        a.flags.writeable = v.flags.writeable = False
        return a, v

    def _coefficients(self, n: float, cache: bool = True) -> tuple[FloatArray, FloatArray]:
        """After ``n`` products: ``a = p / s`` (the predictive mean is ``a S``) and the
        predictive variance ``v = s + p``, both (n_k, n_t)."""
        if cache and n == 0.0:
            return self._coefficients0
        s = 1.0 + self.shares[:, None] * self.gamma
        q = (1.0 - self.shares[:, None]) * self.gamma * self.shared
        p = q * s / (s + n * q)  # q = 0 gives p = 0
        return p / s, s + p

    def whiten(self, residuals: FloatArray) -> FloatArray:
        """Coordinates ``c = T r`` (N, n_t) of residuals (N, n_t) N."""
        out: FloatArray = residuals @ self.transform.T
        return out

    def loglik(self, residuals: FloatArray, stats: FloatArray | None,
               c: FloatArray | None = None) -> FloatArray:
        """Predictive log-density (N, n_k) of residuals ``obs - model`` (N, n_t) N under
        each ``kappa`` given each particle's statistics (N, n_t + 1) (every path has seen
        the same number of products: the first row's ``n`` counts; ``None``: nothing
        shared, ``Sigma + kappa K_res`` alone); ``c`` their :meth:`whiten` if already
        known. A row with NaN gives ``-inf``."""
        c = self.whiten(residuals) if c is None else c
        if stats is None or not self.shared:
            a, v = self._coefficients(0.0)
            m2 = (c * c) @ (1.0 / v).T
        else:
            a, v = self._coefficients(float(stats[0, -1]))
            S = stats[:, :-1]
            # sum_t (c - a S)^2 / v, expanded into three products over t
            m2 = (c * c) @ (1.0 / v).T - 2.0 * (c * S) @ (a / v).T + (S * S) @ (a * a / v).T
        out: FloatArray = (self.logdet_t - 0.5 * np.sum(np.log(v), axis=1)
                           - 0.5 * self.n_t * math.log(2.0 * math.pi) - 0.5 * m2)
        if not math.isinf(self.nu):  # multivariate t with the same scale matrix
            nu, p = self.nu, self.n_t
            out = (out + 0.5 * m2 + float(gammaln(0.5 * (nu + p)) - gammaln(0.5 * nu))
                   - 0.5 * p * math.log(0.5 * nu) - 0.5 * (nu + p) * np.log1p(m2 / nu))
        return np.where(np.isnan(out), -np.inf, out)

    def bias(self, stats: FloatArray, weights: FloatArray) -> FloatArray:
        """Posterior mean of the discrepancy (N, n_t), N, per particle, averaged over the
        grid with ``weights`` (n_k,)."""
        out: FloatArray = self.bias_whitened(stats, weights) @ self.inverse.T
        return out

    def bias_whitened(self, stats: FloatArray, weights: FloatArray) -> FloatArray:
        """:meth:`bias` in the coordinates of :meth:`whiten` (N, n_t)."""
        a = weights @ self._coefficients(float(stats[0, -1]))[0]
        out: FloatArray = stats[:, :-1] * a
        return out

    def predictive_var(self, stats: FloatArray | None, weights: FloatArray) -> FloatArray:
        """The predictive covariance of the next residual in the coordinates of
        :meth:`whiten`, where it is diagonal: its variances (n_t,) (``stats`` None: nothing
        shared), averaged over the grid with ``weights`` (n_k,)."""
        n = 0.0 if stats is None or not self.shared else float(stats[0, -1])
        out: FloatArray = weights @ self._coefficients(n)[1]
        return out

    def covariance_from_var(self, var: FloatArray) -> FloatArray:
        """``T^-1 diag(var) T^-T`` (n_t, n_t) N^2: a covariance from its variances (n_t,)
        in the coordinates of :meth:`whiten`."""
        out: FloatArray = (self.inverse * var) @ self.inverse.T
        return out

    def predictive_cov(self, stats: FloatArray | None, weights: FloatArray) -> FloatArray:
        """Predictive covariance (n_t, n_t) N^2 of the next residual given the
        discrepancy (``stats`` None: nothing shared), averaged over the grid with
        ``weights`` (n_k,)."""
        return self.covariance_from_var(self.predictive_var(stats, weights))

    def update(self, stats: FloatArray, c: FloatArray) -> None:
        """Add this product's coordinates ``c`` (N, n_t) to ``stats`` in place (rows with
        NaN, which have no likelihood, keep their sums; every row counts the product)."""
        good = np.all(np.isfinite(c), axis=1)
        lam = self.forget
        stats[good, :-1] = lam * stats[good, :-1] + c[good]
        stats[:, -1] = lam * stats[:, -1] + 1.0


def residual_covariance(model: Any) -> FloatArray | None:
    """``K_res`` (n_t, n_t) of ``model``: the curve covariance of its k-fold held-out
    residuals (:class:`formtwin.metamodel.ResidualModel`), or ``None`` if it has none."""
    res = getattr(model, "residuals", None)
    return None if res is None else np.asarray(res.curve_cov, dtype=np.float64)


def angle_residual_variance(model: Any) -> FloatArray | None:
    """Variance (2,) deg^2 of the metamodel's held-out angle residuals, or ``None``."""
    res = getattr(model, "residuals", None)
    return None if res is None else np.diag(np.asarray(res.angle_cov, dtype=np.float64))
