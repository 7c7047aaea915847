"""Leave-one-out cross-validation of an RBF interpolant (Rippa's closed form) and its
exact gradient in the log length scales: how :class:`~formtwin.metamodel.rbf.RBF` chooses
its anisotropic scaling."""

from __future__ import annotations

import numpy as np
import scipy.linalg
from numpy.typing import NDArray

from formtwin.metamodel.kernels import KERNEL_SLOPES, kernel_function

FloatArray = NDArray[np.float64]


def interpolation_matrix(R2: FloatArray, P: FloatArray, kernel: str, smoothing: float
                         ) -> FloatArray:
    """The symmetric interpolation matrix ``[[K + smoothing I, P], [P^T, 0]]`` for the
    squared scaled distances ``R2`` (n, n) and the polynomial tail ``P`` (n, q)."""
    n, q = P.shape
    A = np.zeros((n + q, n + q))
    A[:n, :n] = kernel_function(kernel)(R2)
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
    from scipy.spatial.distance import cdist  # on use: evaluating a metamodel needs none

    R2 = cdist(Z, Z, "sqeuclidean")
    return loo_from_distances(R2, P, Y, kernel, smoothing)[0]


def loo_from_distances(R2: FloatArray, P: FloatArray, Y: FloatArray, kernel: str, smoothing: float
                       ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Rippa's LOO residuals ``e`` plus ``B = A^{-1}``, coefficients ``w`` and ``diag(B)``."""
    n = R2.shape[0]
    B = scipy.linalg.inv(interpolation_matrix(R2, P, kernel, smoothing), check_finite=False)
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
    from scipy.spatial.distance import cdist  # on use: evaluating a metamodel needs none

    R2 = cdist(U * np.sqrt(s2), U * np.sqrt(s2), "sqeuclidean")
    e, Bn, w, g = loo_from_distances(R2, P, Y, kernel, smoothing)
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
