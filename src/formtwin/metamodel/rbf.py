"""Radial basis function (RBF) interpolation with anisotropic length scales.

The interpolant of outputs ``Y`` (n, k) at inputs ``U`` (n, d) (inputs already mapped to the
unit box ``[0, 1]^d`` by the metamodel's scaler) is

    s(u) = sum_j w_j phi(|S (u - c_j)|) + sum_l b_l p_l(u),

with centres ``c_j``, a kernel ``phi``, per-dimension length scales ``S = diag(scales)``
and a polynomial tail ``p_l`` (monomials up to ``degree`` in ``2u - 1``). Each output
column is an independent interpolant; columns share centres, kernel and scales.

* The length scales (and, optionally, the kernel among candidates) are chosen by
  leave-one-out cross-validation on a random subset of ``n_tune`` points, using Rippa's
  closed form :func:`loo_residuals` (one matrix inverse instead of n fits).
* With ``n_centres=None`` the model interpolates every point. With ``n_centres=m < n`` it
  is a least-squares RBF: ``m`` centres (a seeded subset of the data spread by k-means in
  the scaled space) fitted to all n points -- a model ``n/m`` times cheaper to evaluate.
* Evaluation runs in ``dtype`` (float32 by default: the distance and kernel matrices are
  the hot path; the polynomial tail stays float64).

>>> rng = np.random.default_rng(0)
>>> U = rng.random((200, 2))
>>> y = np.sin(3 * U[:, :1]) + U[:, 1:] ** 2
>>> rbf = RBF(length_scales="box", dtype=np.float64).fit(U, y)
>>> float(np.abs(rbf.predict(U) - y).max()) < 1e-8
True
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from itertools import combinations_with_replacement

import numpy as np
import scipy.linalg
from numpy.typing import DTypeLike, NDArray
from scipy.cluster.vq import kmeans2
from scipy.optimize import minimize
from scipy.spatial.distance import cdist

FloatArray = NDArray[np.float64]
Kernel = Callable[[np.ndarray], np.ndarray]

log = logging.getLogger(__name__)


def _tps(r2: np.ndarray) -> np.ndarray:
    out: np.ndarray = np.log(np.maximum(r2, np.finfo(r2.dtype).tiny))
    out *= r2
    out *= 0.5
    return out


def _cubic(r2: np.ndarray) -> np.ndarray:
    out: np.ndarray = np.sqrt(r2)
    out *= r2
    return out


def _quintic(r2: np.ndarray) -> np.ndarray:
    out: np.ndarray = np.sqrt(r2)
    out *= r2
    out *= -r2
    return out


def _linear(r2: np.ndarray) -> np.ndarray:
    out: np.ndarray = np.sqrt(r2)
    out *= -1.0
    return out


def _gaussian(r2: np.ndarray) -> np.ndarray:
    out: np.ndarray = np.exp(-r2)
    return out


def _multiquadric(r2: np.ndarray) -> np.ndarray:
    out: np.ndarray = np.sqrt(r2 + 1.0)
    out *= -1.0
    return out


def _inverse_multiquadric(r2: np.ndarray) -> np.ndarray:
    out: np.ndarray = np.sqrt(r2 + 1.0)
    np.reciprocal(out, out=out)
    return out


#: kernel name -> (phi of the squared scaled distance, lowest polynomial degree it needs)
KERNELS: dict[str, tuple[Kernel, int]] = {
    "thin_plate_spline": (_tps, 1),
    "cubic": (_cubic, 1),
    "quintic": (_quintic, 2),
    "linear": (_linear, 0),
    "gaussian": (_gaussian, -1),
    "multiquadric": (_multiquadric, 0),
    "inverse_multiquadric": (_inverse_multiquadric, -1),
}

#: kernels whose interpolant does not change when all length scales are multiplied
SCALE_FREE = frozenset({"thin_plate_spline", "cubic", "quintic", "linear"})


def _kernel(name: str) -> Kernel:
    try:
        return KERNELS[name][0]
    except KeyError:
        raise ValueError(f"unknown RBF kernel {name!r}; known: {', '.join(KERNELS)}") from None


def monomial_powers(d: int, degree: int) -> NDArray[np.int64]:
    """Exponents (q, d) of all monomials in d variables up to ``degree`` (none if < 0)."""
    rows = [np.zeros(d, dtype=np.int64)] if degree >= 0 else []
    for deg in range(1, degree + 1):
        for combo in combinations_with_replacement(range(d), deg):
            p = np.zeros(d, dtype=np.int64)
            np.add.at(p, list(combo), 1)
            rows.append(p)
    return np.array(rows, dtype=np.int64).reshape(-1, d)


def polynomial(U: FloatArray, powers: NDArray[np.int64]) -> FloatArray:
    """Monomials (n, q) of ``2U - 1`` for unit-box inputs ``U`` (n, d)."""
    V = 2.0 * U - 1.0
    out = np.ones((U.shape[0], powers.shape[0]))
    for j, p in enumerate(powers):
        for i in np.flatnonzero(p):
            out[:, j] *= V[:, i] ** p[i]
    return out


def _system(Z: FloatArray, P: FloatArray, kernel: str, smoothing: float) -> FloatArray:
    """The symmetric interpolation matrix ``[[K + smoothing I, P], [P^T, 0]]``."""
    n, q = P.shape
    A = np.zeros((n + q, n + q))
    A[:n, :n] = _kernel(kernel)(cdist(Z, Z, "sqeuclidean"))
    A[:n, :n][np.diag_indices(n)] += smoothing
    A[:n, n:] = P
    A[n:, :n] = P.T
    return A


def loo_residuals(Z: FloatArray, P: FloatArray, Y: FloatArray, kernel: str,
                  smoothing: float = 0.0) -> FloatArray:
    """Leave-one-out residuals (n, k) of the RBF interpolant by Rippa's closed form.

    With ``A`` the interpolation matrix and ``[w; b] = A^{-1} [Y; 0]``, the residual at
    point i of the interpolant fitted without point i is ``w_i / (A^{-1})_{ii}`` (Rippa
    1999, "An algorithm for selecting a good value for the parameter c in radial basis
    function interpolation"): one inverse of size n + q instead of n solves.

    Parameters
    ----------
    Z : ndarray, shape (n, d)
        Scaled inputs.
    P : ndarray, shape (n, q)
        Polynomial tail at the inputs.
    Y : ndarray, shape (n, k)
        Outputs.
    kernel, smoothing
        As in :class:`RBF`.

    Returns
    -------
    ndarray, shape (n, k)
        ``y_i - s_{-i}(z_i)`` for every point and output.
    """
    n = Z.shape[0]
    Ainv = scipy.linalg.inv(_system(Z, P, kernel, smoothing), check_finite=False)
    coef = Ainv[:n, :n] @ Y
    out: FloatArray = coef / np.diag(Ainv)[:n, None]
    return out


class RBF:
    """RBF interpolation of k outputs over the unit box (an :class:`Approximation`).

    Parameters
    ----------
    kernel : str or sequence of str
        Kernel name (see :data:`KERNELS`); several names -> the one with the least
        leave-one-out error on the tuning subset.
    degree : int
        Degree of the polynomial tail (at least the kernel's minimum, e.g. 1 for the
        thin-plate spline; -1 for none).
    smoothing : float
        Added to the kernel matrix's diagonal (0 interpolates exactly).
    length_scales : "loo", "box" or array of shape (d,)
        ``"loo"``: per-dimension scales minimising Rippa's leave-one-out error on the
        tuning subset; ``"box"``: all 1 (isotropic in the unit box); an array: given.
    epsilon : float
        Shape parameter for the kernels that have one (Gaussian, multiquadrics): all
        scales are multiplied by it. With ``"loo"`` it is only the starting point.
    n_centres : int or None
        ``None``: interpolate all points; ``m``: least-squares fit of m centres.
    n_tune : int
        Size of the random subset on which scales and kernel are chosen.
    seed : int
        Seed of the subset and centre choice.
    dtype : numpy dtype
        Dtype of the evaluation (float32 or float64).
    """

    kind = "RBF"

    def __init__(self, kernel: str | Sequence[str] = "thin_plate_spline", degree: int = 1,
                 smoothing: float = 0.0, length_scales: str | FloatArray = "loo",
                 epsilon: float = 1.0, n_centres: int | None = None, n_tune: int = 400,
                 seed: int = 0, dtype: DTypeLike = np.float32) -> None:
        names = [kernel] if isinstance(kernel, str) else list(kernel)
        for name in names:
            _kernel(name)
            if degree < KERNELS[name][1]:
                raise ValueError(f"RBF kernel {name!r} needs a polynomial degree >= "
                                 f"{KERNELS[name][1]}, got degree = {degree}")
        if isinstance(length_scales, str) and length_scales not in ("loo", "box"):
            raise ValueError(f"RBF length_scales = {length_scales!r}, expected 'loo', 'box' "
                             "or an array of per-dimension scales")
        if n_centres is not None and n_centres < 1:
            raise ValueError(f"RBF n_centres = {n_centres!r}, expected a positive int or None")
        self.kernels = tuple(names)
        self.degree = degree
        self.smoothing = float(smoothing)
        self.length_scales = length_scales
        self.epsilon = float(epsilon)
        self.n_centres = n_centres
        self.n_tune = n_tune
        self.seed = seed
        self.dtype = np.dtype(dtype)
        # fitted state
        self.kernel = names[0]
        self.scales = np.zeros(0)
        self.centres = np.zeros((0, 0))
        self.weights = np.zeros((0, 0))
        self.poly_coef = np.zeros((0, 0))
        self.powers = np.zeros((0, 0), dtype=np.int64)
        self.loo_rmse = np.nan
        self._fast: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None

    def __repr__(self) -> str:
        return (f"RBF(kernel={self.kernels if len(self.kernels) > 1 else self.kernels[0]!r}, "
                f"degree={self.degree}, smoothing={self.smoothing}, "
                f"n_centres={self.n_centres}, dtype={self.dtype.name})")

    # ------------------------------------------------------------------ fitting
    def fit(self, U: FloatArray, Y: FloatArray) -> RBF:
        """Fit to unit-box inputs ``U`` (n, d) and outputs ``Y`` (n, k) or (n,); returns self."""
        U = np.asarray(U, dtype=np.float64)
        Y = np.asarray(Y, dtype=np.float64).reshape(U.shape[0], -1)
        n, d = U.shape
        self.powers = monomial_powers(d, self.degree)
        rng = np.random.default_rng(self.seed)
        tune = rng.choice(n, size=min(n, self.n_tune), replace=False)
        best: tuple[float, str, FloatArray] | None = None
        for name in self.kernels:
            scales, err = self._tune(U[tune], Y[tune], name)
            log.info("RBF kernel %s: LOO rmse %.4g on %d points", name, err, tune.size)
            if best is None or err < best[0]:
                best = (err, name, scales)
        assert best is not None
        self.loo_rmse, self.kernel, self.scales = best
        if self.n_centres is None or self.n_centres >= n:
            self._interpolate(U, Y)
        else:
            self._least_squares(U, Y, rng)
        self._fast = None
        return self

    def _tune(self, U: FloatArray, Y: FloatArray, kernel: str) -> tuple[FloatArray, float]:
        """Length scales for ``kernel`` and their LOO rmse on ``(U, Y)``."""
        d = U.shape[1]
        P = polynomial(U, self.powers)
        eps = 1.0 if kernel in SCALE_FREE else self.epsilon

        def loo(log_s: FloatArray) -> float:
            r = loo_residuals(U * np.exp(log_s), P, Y, kernel, self.smoothing)
            return float(np.log(np.mean(r**2)))

        if isinstance(self.length_scales, str) and self.length_scales == "box":
            scales = np.full(d, eps)
        elif isinstance(self.length_scales, str):
            x0 = np.full(d, np.log(eps))
            res = minimize(loo, x0, method="L-BFGS-B",
                           bounds=[(np.log(eps) - 4.0, np.log(eps) + 4.0)] * d,
                           options={"maxiter": 30})
            scales = np.exp(res.x)
            if kernel in SCALE_FREE:
                scales /= np.exp(np.mean(res.x))
        else:
            scales = np.asarray(self.length_scales, dtype=np.float64).reshape(d)
        return scales, float(np.exp(0.5 * loo(np.log(scales))))

    def _interpolate(self, U: FloatArray, Y: FloatArray) -> None:
        n = U.shape[0]
        Z = U * self.scales
        P = polynomial(U, self.powers)
        rhs = np.vstack([Y, np.zeros((P.shape[1], Y.shape[1]))])
        sol = scipy.linalg.solve(_system(Z, P, self.kernel, self.smoothing), rhs,
                                 assume_a="sym", check_finite=False)
        self.centres, self.weights, self.poly_coef = U.copy(), sol[:n], sol[n:]

    def _least_squares(self, U: FloatArray, Y: FloatArray, rng: np.random.Generator) -> None:
        assert self.n_centres is not None
        Z = U * self.scales
        start = Z[rng.choice(U.shape[0], size=self.n_centres, replace=False)]
        C, _ = kmeans2(Z, start, iter=5, minit="matrix", seed=rng)
        B = np.hstack([_kernel(self.kernel)(cdist(Z, C, "sqeuclidean")),
                       polynomial(U, self.powers)])
        sol, *_ = scipy.linalg.lstsq(B, Y, check_finite=False, lapack_driver="gelsy")
        m = C.shape[0]
        self.centres, self.weights, self.poly_coef = C / self.scales, sol[:m], sol[m:]

    # --------------------------------------------------------------- evaluation
    def predict(self, U: FloatArray) -> FloatArray:
        """Outputs (N, k) at unit-box inputs ``U`` (N, d)."""
        U = np.asarray(U, dtype=np.float64)
        if self._fast is None:
            C = (self.centres * self.scales).astype(self.dtype)
            self._fast = (C, np.einsum("ij,ij->i", C, C), self.weights.astype(self.dtype))
        C, cc, W = self._fast
        Z = (U * self.scales).astype(self.dtype)
        r2 = Z @ C.T
        r2 *= -2.0
        r2 += np.einsum("ij,ij->i", Z, Z)[:, None]
        r2 += cc[None, :]
        np.maximum(r2, 0.0, out=r2)
        out: FloatArray = (_kernel(self.kernel)(r2) @ W).astype(np.float64)
        if self.powers.shape[0]:
            out += polynomial(U, self.powers) @ self.poly_coef
        return out

    # ------------------------------------------------------------------ storage
    def state(self) -> dict[str, np.ndarray]:
        """Arrays that define the fitted model (for the metamodel file)."""
        return {"kernel": np.array(self.kernel), "kernels": np.array(self.kernels),
                "degree": np.array(self.degree), "smoothing": np.array(self.smoothing),
                "epsilon": np.array(self.epsilon), "scales": self.scales,
                "centres": self.centres, "weights": self.weights, "poly_coef": self.poly_coef,
                "dtype": np.array(self.dtype.name), "loo_rmse": np.array(self.loo_rmse),
                "n_centres": np.array(-1 if self.n_centres is None else self.n_centres),
                "n_tune": np.array(self.n_tune), "seed": np.array(self.seed)}

    @classmethod
    def from_state(cls, arrays: dict[str, np.ndarray]) -> RBF:
        """Rebuild a fitted RBF from :meth:`state`."""
        n_centres = int(arrays["n_centres"])
        rbf = cls(kernel=[str(k) for k in arrays["kernels"]], degree=int(arrays["degree"]),
                  smoothing=float(arrays["smoothing"]), length_scales=arrays["scales"],
                  epsilon=float(arrays["epsilon"]),
                  n_centres=None if n_centres < 0 else n_centres,
                  n_tune=int(arrays["n_tune"]), seed=int(arrays["seed"]),
                  dtype=str(arrays["dtype"]))
        rbf.kernel = str(arrays["kernel"])
        rbf.scales = np.asarray(arrays["scales"], dtype=np.float64)
        rbf.centres = np.asarray(arrays["centres"], dtype=np.float64)
        rbf.weights = np.asarray(arrays["weights"], dtype=np.float64)
        rbf.poly_coef = np.asarray(arrays["poly_coef"], dtype=np.float64)
        rbf.powers = monomial_powers(rbf.centres.shape[1], rbf.degree)
        rbf.loo_rmse = float(arrays["loo_rmse"])
        return rbf
