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
  is a least-squares RBF: ``m`` centres (a seeded random subset of the data points, the
  same points the scales were tuned on first) fitted to all n points -- a model ``n/m``
  times cheaper to evaluate that still uses every run.
* Evaluation runs in ``dtype`` (float32 by default: the distance and kernel matrices are
  the hot path; the polynomial tail stays float64). :meth:`RBF.fit` checks float32
  against float64 on the data and falls back to float64 where cancellation in the
  weighted kernel sum costs more than 5 % of the LOO error.

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
from typing import Any

import numpy as np
import scipy.linalg
from numpy.typing import DTypeLike, NDArray
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

#: d phi / d(r^2) per kernel (its value at r = 0 is never used)
KERNEL_SLOPES: dict[str, Kernel] = {
    "thin_plate_spline": lambda r2: 0.5 * (np.log(np.maximum(r2, 1e-300)) + 1.0),
    "cubic": lambda r2: 1.5 * np.sqrt(r2),
    "quintic": lambda r2: -2.5 * r2 * np.sqrt(r2),
    "linear": lambda r2: -0.5 / np.sqrt(np.maximum(r2, 1e-300)),
    "gaussian": lambda r2: -np.exp(-r2),
    "multiquadric": lambda r2: -0.5 / np.sqrt(1.0 + r2),
    "inverse_multiquadric": lambda r2: -0.5 * (1.0 + r2) ** -1.5,
}

# range and start of the smoothing chosen by leave-one-out (kernel units)
_SMOOTHING_MIN, _SMOOTHING_START, _SMOOTHING_MAX = 1e-10, 1e-4, 1e4

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


def _system(R2: FloatArray, P: FloatArray, kernel: str, smoothing: float) -> FloatArray:
    """The symmetric interpolation matrix ``[[K + smoothing I, P], [P^T, 0]]`` for the
    squared scaled distances ``R2`` (n, n) and the polynomial tail ``P`` (n, q)."""
    n, q = P.shape
    A = np.zeros((n + q, n + q))
    A[:n, :n] = _kernel(kernel)(R2)
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
    R2 = cdist(Z, Z, "sqeuclidean")
    return _loo(R2, P, Y, kernel, smoothing)[0]


def _loo(R2: FloatArray, P: FloatArray, Y: FloatArray, kernel: str, smoothing: float
         ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Rippa's LOO residuals ``e`` plus ``B = A^{-1}``, coefficients ``w`` and ``diag(B)``."""
    n = R2.shape[0]
    B = scipy.linalg.inv(_system(R2, P, kernel, smoothing), check_finite=False)
    Bn = B[:n, :n]
    g = np.diag(Bn).copy()
    w = Bn @ Y
    return w / g[:, None], Bn, w, g


def loo_objective(params: FloatArray, U: FloatArray, P: FloatArray, Y: FloatArray,
                  kernel: str, smoothing: float = 0.0) -> tuple[float, FloatArray]:
    """``log`` of the mean squared LOO residual and its gradient in ``params``.

    ``params`` holds the log length scales (d,), or (d + 1,) with the log smoothing last
    (then ``smoothing`` is ignored). The gradient is exact and costs about two more matrix
    products of size n: with ``L = sum e^2``, ``e_i = w_i / g_i`` and ``dB = -B dA B``,
    ``dL = sum_jl dA_jl (M - Q)_jl`` where ``Q = (B a) w^T``, ``a = 2 e / g`` and
    ``M = B diag(2 sum_k e_ik^2 / g_i) B``; for a length scale ``dA`` is ``phi'(r^2)``
    times ``2 s_d^2 (u_jd - u_ld)^2``, for the log smoothing it is ``smoothing * I``.
    """
    d = U.shape[1]
    s2 = np.exp(2.0 * params[:d])
    if params.size > d:
        smoothing = float(np.exp(params[d]))
    R2 = cdist(U * np.sqrt(s2), U * np.sqrt(s2), "sqeuclidean")
    e, Bn, w, g = _loo(R2, P, Y, kernel, smoothing)
    L = float(np.sum(e**2))
    a = 2.0 * e / g[:, None]
    M = (Bn * (2.0 * np.sum(e**2, axis=1) / g)) @ Bn
    M -= (Bn @ a) @ w.T
    d_smoothing = smoothing * float(np.trace(M))
    M *= KERNEL_SLOPES[kernel](R2)
    np.fill_diagonal(M, 0.0)
    rows, cols = M.sum(axis=1), M.sum(axis=0)
    quad = (U**2 * (rows + cols)[:, None]).sum(axis=0) - 2.0 * np.einsum("jd,jl,ld->d", U, M, U)
    grad = 2.0 * s2 * quad
    if params.size > d:
        grad = np.append(grad, d_smoothing)
    return float(np.log(L / e.size)), grad / L


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
    smoothing : float or "loo"
        Added to the kernel matrix's diagonal (0 interpolates exactly); ``"loo"``: chosen
        with the length scales by leave-one-out (for noisy or rough data). Used by the
        interpolating model; the least-squares model (``n_centres``) smooths by itself and
        uses it only while choosing the scales.
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
                 smoothing: float | str = 0.0, length_scales: str | FloatArray = "loo",
                 epsilon: float = 1.0, n_centres: int | None = None, n_tune: int = 800,
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
        if isinstance(smoothing, str) and smoothing != "loo":
            raise ValueError(f"RBF smoothing = {smoothing!r}, expected a number or 'loo'")
        if isinstance(smoothing, str) and length_scales != "loo":
            raise ValueError("RBF smoothing = 'loo' needs length_scales = 'loo'")
        self.tune_smoothing = smoothing == "loo"
        self.smoothing = 0.0 if isinstance(smoothing, str) else float(smoothing)
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
        self._fast: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}

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
        order = np.random.default_rng(self.seed).permutation(n)
        tune = order[:self.n_tune]
        best: tuple[float, str, FloatArray, float] | None = None
        for name in self.kernels:
            scales, smoothing, err = self._tune(U[tune], Y[tune], name)
            log.info("RBF kernel %s: LOO rmse %.4g on %d points (smoothing %.3g)", name, err,
                     tune.size, smoothing)
            if best is None or err < best[0]:
                best = (err, name, scales, smoothing)
        assert best is not None
        self.loo_rmse, self.kernel, self.scales, self.smoothing = best
        if self.n_centres is None or self.n_centres >= n:
            self._interpolate(U, Y)
        else:
            self._least_squares(U, Y, order[:self.n_centres])
        self._fast = {}
        self._check_precision(U[order[:500]])
        return self

    def _tune(self, U: FloatArray, Y: FloatArray, kernel: str
              ) -> tuple[FloatArray, float, float]:
        """Length scales and smoothing for ``kernel`` and their LOO rmse on ``(U, Y)``."""
        d = U.shape[1]
        P = polynomial(U, self.powers)
        eps = 1.0 if kernel in SCALE_FREE else self.epsilon
        smoothing = self.smoothing

        def loo(params: FloatArray) -> tuple[float, FloatArray]:
            return loo_objective(params, U, P, Y, kernel, smoothing)

        if isinstance(self.length_scales, str) and self.length_scales == "box":
            scales = np.full(d, eps)
        elif isinstance(self.length_scales, str):
            x0 = np.full(d, np.log(eps))
            bounds = [(np.log(eps) - 4.0, np.log(eps) + 4.0)] * d
            if self.tune_smoothing:
                x0 = np.append(x0, np.log(_SMOOTHING_START))
                bounds.append((np.log(_SMOOTHING_MIN), np.log(_SMOOTHING_MAX)))
            res = minimize(loo, x0, jac=True, method="L-BFGS-B", bounds=bounds,
                           options={"maxiter": 30})
            scales = np.exp(res.x[:d])
            if self.tune_smoothing:
                smoothing = float(np.exp(res.x[d]))
            elif kernel in SCALE_FREE:  # the interpolant ignores a common factor
                scales /= np.exp(np.mean(res.x))
        else:
            scales = np.asarray(self.length_scales, dtype=np.float64).reshape(d)
        return scales, smoothing, float(np.exp(0.5 * loo(np.log(scales))[0]))

    def _interpolate(self, U: FloatArray, Y: FloatArray) -> None:
        n = U.shape[0]
        Z = U * self.scales
        P = polynomial(U, self.powers)
        rhs = np.vstack([Y, np.zeros((P.shape[1], Y.shape[1]))])
        sol = scipy.linalg.solve(_system(cdist(Z, Z, "sqeuclidean"), P, self.kernel,
                                         self.smoothing), rhs,
                                 assume_a="sym", check_finite=False)
        self.centres, self.weights, self.poly_coef = U.copy(), sol[:n], sol[n:]

    def _least_squares(self, U: FloatArray, Y: FloatArray, centres: NDArray[np.intp]) -> None:
        """Least-squares fit to all points with the centres ``U[centres]``."""
        Z = U * self.scales
        B = np.hstack([_kernel(self.kernel)(cdist(Z, Z[centres], "sqeuclidean")),
                       polynomial(U, self.powers)])
        sol, *_ = scipy.linalg.lstsq(B, Y, check_finite=False, lapack_driver="gelsy")
        m = centres.size
        self.centres, self.weights, self.poly_coef = U[centres].copy(), sol[:m], sol[m:]

    # --------------------------------------------------------------- evaluation
    def predict(self, U: FloatArray) -> FloatArray:
        """Outputs (N, k) at unit-box inputs ``U`` (N, d)."""
        return self._evaluate(np.asarray(U, dtype=np.float64), self.dtype)

    def _evaluate(self, U: FloatArray, dtype: np.dtype[Any]) -> FloatArray:
        fast = self._fast.get(dtype.name)
        if fast is None:
            C = (self.centres * self.scales).astype(dtype)
            fast = self._fast[dtype.name] = (C, np.einsum("ij,ij->i", C, C),
                                              self.weights.astype(dtype))
        C, cc, W = fast
        Z = (U * self.scales).astype(dtype)
        r2 = Z @ C.T
        r2 *= -2.0
        r2 += np.einsum("ij,ij->i", Z, Z)[:, None]
        r2 += cc[None, :]
        np.maximum(r2, 0.0, out=r2)
        out: FloatArray = (_kernel(self.kernel)(r2) @ W).astype(np.float64)
        if self.powers.shape[0]:
            out += polynomial(U, self.powers) @ self.poly_coef
        return out

    def _check_precision(self, U: FloatArray) -> None:
        """Fall back to float64 evaluation where float32 loses accuracy.

        Large weights of alternating sign cancel in ``sum_j w_j phi_j``; if the float32
        result differs from the float64 one on the probe points ``U`` by more than 5 % of
        the LOO error, evaluation switches to float64 (and says so in the log).
        """
        if self.dtype == np.float64:
            return
        gap = self._evaluate(U, self.dtype) - self._evaluate(U, np.dtype(np.float64))
        rms = float(np.sqrt(np.mean(gap**2)))
        if not rms <= 0.05 * self.loo_rmse:
            log.warning("RBF: %s evaluation is off by %.3g (LOO error %.3g); using float64",
                        self.dtype.name, rms, self.loo_rmse)
            self.dtype = np.dtype(np.float64)

    # ------------------------------------------------------------------ storage
    def state(self) -> dict[str, np.ndarray]:
        """Arrays that define the fitted model (for the metamodel file)."""
        return {"kernel": np.array(self.kernel), "kernels": np.array(self.kernels),
                "degree": np.array(self.degree), "smoothing": np.array(self.smoothing),
                "tune_smoothing": np.array(self.tune_smoothing),
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
        rbf.tune_smoothing = bool(arrays["tune_smoothing"])
        rbf.scales = np.asarray(arrays["scales"], dtype=np.float64)
        rbf.centres = np.asarray(arrays["centres"], dtype=np.float64)
        rbf.weights = np.asarray(arrays["weights"], dtype=np.float64)
        rbf.poly_coef = np.asarray(arrays["poly_coef"], dtype=np.float64)
        rbf.powers = monomial_powers(rbf.centres.shape[1], rbf.degree)
        rbf.loo_rmse = float(arrays["loo_rmse"])
        return rbf
