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

Kernels live in :mod:`formtwin.metamodel.kernels`, the leave-one-out criterion and its
gradient in :mod:`formtwin.metamodel.loo`.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from typing import Any

import numpy as np
import scipy.linalg
from numpy.typing import DTypeLike, NDArray

from formtwin.metamodel._fused import cubic_from_gram, cubic_value_slope
from formtwin.metamodel.kernels import (
    KERNEL_SLOPES,
    KERNELS,
    SCALE_FREE,
    kernel_function,
    linear_plan,
    monomial_powers,
    polynomial,
    polynomial_gradient,
)
from formtwin.metamodel.loo import interpolation_matrix, loo_objective, loo_residuals

FloatArray = NDArray[np.float64]

log = logging.getLogger(__name__)

# range and start of the smoothing chosen by leave-one-out (kernel units)
_SMOOTHING_MIN, _SMOOTHING_START, _SMOOTHING_MAX = 1e-10, 1e-4, 1e4


def merge_duplicates(U: FloatArray, Y: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Repeated rows of ``U`` (n, d) merged into one with the mean of their outputs ``Y``
    (n, k): an interpolant cannot pass through two values at one point, and a repeated
    centre makes the interpolation matrix singular (the bundled DOE's corner runs differ
    only in the press setting, which a stage-1 model does not take).

    >>> U, Y = merge_duplicates(np.array([[0.0], [1.0], [0.0]]), np.array([[1.0], [5.0], [3.0]]))
    >>> U.ravel().tolist(), Y.ravel().tolist()
    ([0.0, 1.0], [2.0, 5.0])
    """
    unique, inverse, counts = np.unique(U, axis=0, return_inverse=True, return_counts=True)
    if unique.shape[0] == U.shape[0]:
        return U, Y
    merged = np.zeros((unique.shape[0], Y.shape[1]))
    np.add.at(merged, inverse.reshape(-1), Y)
    return unique, merged / counts[:, None]


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
            kernel_function(name)
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
        # float64 scaled centres and, for a tail of degree <= 1, its constant gradient
        # (d, k): what :meth:`value_and_gradient` reuses
        self._grad_parts: tuple[FloatArray, FloatArray | None] | None = None

    @property
    def powers(self) -> NDArray[np.int64]:
        """Exponents (q, d) of the polynomial part's monomials."""
        return self._powers

    @powers.setter
    def powers(self, value: NDArray[np.int64]) -> None:
        self._powers = value
        self._plan = linear_plan(value)  # the evaluation's plan, made with the exponents

    def __repr__(self) -> str:
        return (f"RBF(kernel={self.kernels if len(self.kernels) > 1 else self.kernels[0]!r}, "
                f"degree={self.degree}, smoothing={self.smoothing}, "
                f"n_centres={self.n_centres}, dtype={self.dtype.name})")

    def settings(self) -> dict[str, Any]:
        """The constructor's settings (JSON-safe): what a fit with this template is made
        with (:func:`~formtwin.metamodel.identity.fit_id`)."""
        scales = self.length_scales if isinstance(self.length_scales, str) \
            else [float(v) for v in np.asarray(self.length_scales).ravel()]
        return {"kind": self.kind, "kernels": list(self.kernels), "degree": self.degree,
                "smoothing": "loo" if self.tune_smoothing else self.smoothing,
                "length_scales": scales, "epsilon": self.epsilon,
                "n_centres": self.n_centres, "n_tune": self.n_tune, "seed": self.seed,
                "dtype": self.dtype.name}

    # ------------------------------------------------------------------ fitting
    def fit(self, U: FloatArray, Y: FloatArray) -> RBF:
        """Fit to unit-box inputs ``U`` (n, d) and outputs ``Y`` (n, k) or (n,) (repeated inputs
        merged, :func:`merge_duplicates`); returns self."""
        U = np.asarray(U, dtype=np.float64)
        Y = np.asarray(Y, dtype=np.float64).reshape(U.shape[0], -1)
        U, Y = merge_duplicates(U, Y)
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
        self._fast, self._grad_parts = {}, None
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
            from scipy.optimize import minimize  # on use: a command that only evaluates a
            # metamodel starts without scipy.optimize (~0.2 s CPU to import)

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
        from scipy.spatial.distance import cdist  # on use, as minimize

        n = U.shape[0]
        Z = U * self.scales
        P = polynomial(U, self.powers)
        rhs = np.vstack([Y, np.zeros((P.shape[1], Y.shape[1]))])
        sol = scipy.linalg.solve(interpolation_matrix(cdist(Z, Z, "sqeuclidean"), P, self.kernel,
                                         self.smoothing), rhs,
                                 assume_a="sym", check_finite=False)
        self.centres, self.weights, self.poly_coef = U.copy(), sol[:n], sol[n:]

    def _least_squares(self, U: FloatArray, Y: FloatArray, centres: NDArray[np.intp]) -> None:
        """Least-squares fit to all points with the centres ``U[centres]``."""
        from scipy.spatial.distance import cdist  # on use, as minimize

        Z = U * self.scales
        B = np.hstack([kernel_function(self.kernel)(cdist(Z, Z[centres], "sqeuclidean")),
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
        if self.kernel == "cubic" and r2.flags.c_contiguous:  # one pass, the same numbers
            phi = cubic_from_gram(r2, np.einsum("ij,ij->i", Z, Z), cc)
        else:
            r2 *= -2.0
            r2 += np.einsum("ij,ij->i", Z, Z)[:, None]
            r2 += cc[None, :]
            np.maximum(r2, 0.0, out=r2)
            phi = kernel_function(self.kernel)(r2)
        out: FloatArray = (phi @ W).astype(np.float64)
        if self.powers.shape[0]:
            out += polynomial(U, self.powers, self._plan) @ self.poly_coef
        return out

    def value_and_gradient(self, U: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Outputs (N, k) and their derivatives (N, d, k) ``d s_k / d u_i`` at unit-box
        inputs ``U`` (N, d), in float64: the interpolant of the module doc and its exact
        gradient ``sum_j w_j 2 phi'(r_j^2) S^2 (u - c_j) + grad p(u) b`` (the evaluation in
        ``dtype`` rounds the same interpolant). ``N`` times (m, d) temporaries: meant for
        a few points (a linearisation), not for a cloud."""
        U = np.atleast_2d(np.asarray(U, dtype=np.float64))
        if self._grad_parts is None:
            d = self.centres.shape[1]
            tail = polynomial_gradient(np.zeros((1, d)), self.powers, self._plan)[0] \
                @ self.poly_coef if self._plan is not None else None
            self._grad_parts = (self.centres * self.scales, tail)
        centres, tail = self._grad_parts
        if self.kernel == "cubic":  # the kernel and its slope in one pass (Numba)
            phi, S = cubic_value_slope(np.ascontiguousarray(U * self.scales), centres)
            value = phi @ self.weights
            grad = np.matmul(S, self.weights)  # (N, d, k)
        else:
            D = (U * self.scales)[:, None, :] - centres[None]  # (N, m, d)
            r2 = np.einsum("nmd,nmd->nm", D, D)
            value = kernel_function(self.kernel)(r2) @ self.weights
            slope = KERNEL_SLOPES[self.kernel](r2)  # d phi / d r^2 (N, m)
            D *= 2.0 * slope[:, :, None]
            grad = np.matmul(D.transpose(0, 2, 1), self.weights)  # (N, d, k)
        grad *= self.scales[None, :, None]
        if self.powers.shape[0]:
            value += polynomial(U, self.powers, self._plan) @ self.poly_coef
            grad += tail if tail is not None else \
                polynomial_gradient(U, self.powers, self._plan) @ self.poly_coef
        return value, grad

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


__all__ = ["KERNELS", "RBF", "loo_objective", "loo_residuals", "merge_duplicates"]
