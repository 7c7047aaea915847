"""Fused evaluation of the cubic RBF kernel from a Gram matrix (Numba, the hot path).

:meth:`formtwin.metamodel.rbf.RBF.predict` forms the squared scaled distances of ``N``
inputs to ``m`` centres as ``|z|^2 - 2 z.c + |c|^2`` from the Gram matrix ``z.c`` (BLAS)
and applies the kernel: with NumPy that is five passes over an ``(N, m)`` array (~2 MB at
N = 500, m = 1000 in float32). :func:`cubic_from_gram` does them in one pass, with the
same operations in the same order and the array's own precision (no fast-math), so the
result is bit for bit NumPy's (``tests/test_metamodel.py``) at about half the time.
"""

from __future__ import annotations

import numpy as np
from numba import njit
from numpy.typing import NDArray


@njit(cache=True)
def _cubic(g, zz, cc, minus_two, zero):  # type: ignore[no-untyped-def]
    for i in range(g.shape[0]):
        a = zz[i]
        for j in range(g.shape[1]):
            v = g[i, j] * minus_two  # the same float32 (or float64) steps as NumPy's
            v = v + a
            v = v + cc[j]
            if v < zero:  # np.maximum(v, 0): NaN stays NaN, -0.0 stays
                v = zero
            g[i, j] = np.sqrt(v) * v
    return g


def cubic_from_gram(g: NDArray[np.floating], zz: NDArray[np.floating],
                    cc: NDArray[np.floating]) -> NDArray[np.floating]:
    """The cubic kernel ``r^3`` of ``r^2 = max(zz_i - 2 g_ij + cc_j, 0)``, in place in ``g``.

    ``g (N, m)`` the Gram matrix of the scaled inputs and centres, ``zz (N,)`` and ``cc (m,)``
    their squared norms, all of one float dtype; returns ``g``, equal bit for bit to
    ``r2 = g; r2 *= -2; r2 += zz[:, None]; r2 += cc; np.maximum(r2, 0, out=r2);
    np.sqrt(r2) * r2``.
    """
    t = g.dtype.type
    out: NDArray[np.floating] = _cubic(g, zz.astype(g.dtype, copy=False),
                                       cc.astype(g.dtype, copy=False), t(-2.0), t(0.0))
    return out


@njit(cache=True)
def cubic_value_slope(Z, C):  # type: ignore[no-untyped-def]
    """For scaled inputs ``Z`` (N, d) and scaled centres ``C`` (m, d), float64: the cubic
    kernel ``phi = r^3`` (N, m) of ``r^2 = |z - c|^2`` and its gradient's factors ``S``
    (N, d, m), ``S[n, i, j] = 2 phi'(r^2) (z_ni - c_ji)`` with ``phi'(r^2) = 1.5 r``
    (:meth:`formtwin.metamodel.RBF.value_and_gradient`: ``S @ weights`` is the gradient
    in ``Z``); one pass instead of NumPy's six over (N, m, d) temporaries."""
    n, d = Z.shape
    m = C.shape[0]
    phi = np.empty((n, m))
    S = np.empty((n, d, m))
    diff = np.empty(d)
    for p in range(n):
        for j in range(m):
            r2 = 0.0
            for i in range(d):
                diff[i] = Z[p, i] - C[j, i]
                r2 += diff[i] * diff[i]
            r = np.sqrt(r2)
            phi[p, j] = r2 * r
            f = 2.0 * (1.5 * r)
            for i in range(d):
                S[p, i, j] = diff[i] * f
    return phi, S
