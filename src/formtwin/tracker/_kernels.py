"""Numba kernels of the tracker's own per-product terms (the hot path beside the model).

Each replaces a handful of NumPy calls on arrays of 8 to 500 rows, whose fixed cost per
call (~2-5 us) was most of their time, with one pass:

* :func:`drift`: the transition ``a + b x + s v`` (:meth:`formtwin.tracker.BendingSSM.
  sample_transition`), the same float steps as NumPy's, so the same particles;
* :func:`select_heaviest`: the particles whose angles are predicted
  (:func:`formtwin.tracker.core.heaviest`): the same selection, exactly (a stable sort
  and sequential prefix sums, as NumPy's);
* :func:`shifted_columns`, :func:`row_sums`: the share's evidence
  (:meth:`~formtwin.tracker.hyper.GridPosteriors.update_share`): the same operations in
  their order around NumPy's ``exp`` and ``log``, so the same numbers bit for bit;
* :func:`centred_spread`: the goodness of fit's mean residual and the rows of the cloud's
  spread (:func:`formtwin.tracker.fit.assess`);
* :func:`cloud_moments`, :func:`angle_moments`: the estimate's std (eq. 14) and the
  cloud's covariance for the intervals in one pass; the predicted angles' moments;
* :func:`information`, :func:`mu_gain_step`, :func:`term_variances`: the assumed mu's
  interval term (:class:`formtwin.tracker.sandwich.Sandwich`): ``J^T S^-1 J``, the
  recursion's solve (Gaussian elimination with partial pivoting, as LAPACK's ``dgesv``)
  and the variances it adds.

The last three groups sum in another order than BLAS and solve without LAPACK: their
numbers agree with the NumPy formulas to rounding (``tests/test_tracker_kernels.py``
holds them to tolerances from ``eps`` and the solve's condition number), and they are
deterministic, so a tracker restored from its state continues bit for bit. No fast-math.
``scripts/compile_kernels.py`` compiles them into Numba's cache with the tracker's steps.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def select_heaviest(w, mass):  # type: ignore[no-untyped-def]
    """Indices (ascending) of the weights ``w`` (N,) left after dropping the lightest ones
    whose sum is at most ``mass``; ``w`` itself when none is dropped (see
    :func:`formtwin.tracker.core.heaviest`)."""
    n = w.size
    light = np.empty(n, dtype=np.intp)
    n_light = 0
    for k in range(n):
        if w[k] <= mass:
            light[n_light] = k
            n_light += 1
    light = light[:n_light]
    order = light[np.argsort(w[light], kind="mergesort")]  # stable, as NumPy's
    total = 0.0
    n_drop = 0
    for k in range(n_light):  # searchsorted(cumsum, mass, "right"): the sums <= mass
        total += w[order[k]]
        if total > mass:
            break
        n_drop += 1
    keep = np.ones(n, dtype=np.bool_)
    for k in range(n_drop):
        keep[order[k]] = False
    return np.flatnonzero(keep)


@njit(cache=True)
def shifted_columns(a, grid):  # type: ignore[no-untyped-def]
    """``t = (a[:, None] + grid).T - top`` (n_k, N) and ``top`` (n_k,), the columns' finite
    maxima of ``a[:, None] + grid`` (0 where a column has none): the steps of
    :func:`formtwin.filters.sir.logsumexp` over the rows of ``a[:, None] + grid``
    before its ``exp``."""
    n, n_k = grid.shape
    t = np.empty((n_k, n))
    top = np.empty(n_k)
    for j in range(n_k):
        hi = -np.inf
        nan = False
        for k in range(n):
            v = a[k] + grid[k, j]
            t[j, k] = v
            if v != v:
                nan = True
            elif v > hi:
                hi = v
        top[j] = hi if np.isfinite(hi) and not nan else 0.0  # np.max: NaN wins
        for k in range(n):
            t[j, k] = t[j, k] - top[j]
    return t, top


@njit(cache=True)
def row_sums(t):  # type: ignore[no-untyped-def]
    """Sums (n_k,) of the rows of ``t`` (n_k, N), each in order (as ``cumsum``'s last)."""
    out = np.zeros(t.shape[0])
    for j in range(t.shape[0]):
        s = 0.0
        for k in range(t.shape[1]):
            s += t[j, k]
        out[j] = s
    return out


@njit(cache=True)
def centred_spread(r, v, stride):  # type: ignore[no-untyped-def]
    """For residuals ``r`` (N, n_t) with weights ``v`` (N,), normalised here to ``w``:
    ``r_bar = sum_k w_k r_k`` (n_t,); whether every weight is positive and ``r_bar``
    finite (then no row has a NaN or inf); and the rows ``s = 0, stride, ...`` centred
    and scaled, ``(r_s - r_bar) sqrt(w_s / sum w_s)`` (ceil(N / stride), n_t)."""
    n_rows, n_t = r.shape
    total = 0.0
    positive = True
    for k in range(n_rows):
        total += v[k]
        if not v[k] > 0.0:
            positive = False
    w = v / total
    r_bar = np.zeros(n_t)
    for k in range(n_rows):
        wk = w[k]
        for j in range(n_t):
            r_bar[j] += wk * r[k, j]
    ok = positive
    for j in range(n_t):
        if not np.isfinite(r_bar[j]):
            ok = False
    n_s = (n_rows + stride - 1) // stride
    total = 0.0
    for s in range(n_s):
        total += w[s * stride]
    out = np.empty((n_s, n_t))
    for s in range(n_s):
        k = s * stride
        f = np.sqrt(w[k] / total)
        for j in range(n_t):
            out[s, j] = (r[k, j] - r_bar[j]) * f
    return r_bar, ok, out


@njit(cache=True)
def cloud_moments(x, w, mean, m):  # type: ignore[no-untyped-def]
    """In one pass over the particles ``x`` (N, d) with weights ``w`` (N,) and weighted
    mean ``mean`` (d,): the weighted variance of every column (d,) and the covariance ``P =
    sum_k w_k (x_k - mean)(x_k - mean)^T`` (m, m) of the first ``m`` columns."""
    n, n_col = x.shape
    var = np.zeros(n_col)
    P = np.zeros((m, m))
    d = np.empty(n_col)
    for k in range(n):
        wk = w[k]
        for i in range(n_col):
            d[i] = x[k, i] - mean[i]
            var[i] += wk * (d[i] * d[i])
        for i in range(m):
            a = wk * d[i]
            for j in range(m):
                P[i, j] += a * d[j]
    return var, P


@njit(cache=True)
def angle_moments(angles, w, extra):  # type: ignore[no-untyped-def]
    """Weighted mean and std (n_out,) of the angles (M, n_out) with weights ``w`` (M,),
    rows with a NaN or inf left out and the rest renormalised, the variances ``extra``
    (n_out,) added to the std's square; NaN when no row is left."""
    n, n_out = angles.shape
    ok = np.empty(n, dtype=np.bool_)
    total = 0.0
    for i in range(n):
        ok[i] = True
        for j in range(n_out):
            if not np.isfinite(angles[i, j]):
                ok[i] = False
        if ok[i]:
            total += w[i]
    mean = np.full(n_out, np.nan)
    std = np.full(n_out, np.nan)
    if not total > 0.0:
        return mean, std
    mean[:] = 0.0
    for i in range(n):
        if ok[i]:
            wi = w[i] / total
            for j in range(n_out):
                mean[j] += wi * angles[i, j]
    var = np.zeros(n_out)
    for i in range(n):
        if ok[i]:
            wi = w[i] / total
            for j in range(n_out):
                e = angles[i, j] - mean[j]
                var[j] += wi * (e * e)
    for j in range(n_out):
        std[j] = np.sqrt(max(var[j], 0.0) + extra[j])
    return mean, std


@njit(cache=True)
def information(TJ, v):  # type: ignore[no-untyped-def]
    """``(TJ)^T diag(1 / v) TJ`` (m, m) of ``TJ`` (n_t, m) and ``v`` (n_t,): ``J^T S^-1 J``
    in the likelihood's whitened coordinates."""
    n_t, m = TJ.shape
    out = np.zeros((m, m))
    scaled = np.empty(m)
    for t in range(n_t):
        for j in range(m):
            scaled[j] = TJ[t, j] / v[t]
        for i in range(m):
            a = TJ[t, i]
            for j in range(m):
                out[i, j] += a * scaled[j]
    return out


@njit(cache=True)
def mu_gain_step(P_prev, info, F, Q, G_mu, drive):  # type: ignore[no-untyped-def]
    """The next ``G_mu = A^-1 (F G_mu + drive)`` (m, n_x) with ``A = I + P_pred J^T S^-1
    J``, ``P_pred = F P_prev F + diag(Q)`` (:func:`formtwin.tracker.sandwich.mu_step`:
    ``A^-1 = P_lin P_pred^-1``), by Gaussian elimination with partial pivoting; and
    False (with the input ``G_mu``) when ``A`` is singular in floating point."""
    m, nx = G_mu.shape
    P_pred = np.empty((m, m))
    for i in range(m):
        for j in range(m):
            P_pred[i, j] = F[i] * P_prev[i, j] * F[j]
        P_pred[i, i] += Q[i]
    A = np.zeros((m, m))  # I + P_pred info, in loops (no BLAS call for 18 x 18)
    for i in range(m):
        for k in range(m):
            a = P_pred[i, k]
            for j in range(m):
                A[i, j] += a * info[k, j]
        A[i, i] += 1.0
    B = np.empty((m, nx))
    for i in range(m):
        for j in range(nx):
            B[i, j] = F[i] * G_mu[i, j] + drive[i, j]
    for c in range(m):
        p, big = c, abs(A[c, c])
        for r in range(c + 1, m):
            if abs(A[r, c]) > big:
                p, big = r, abs(A[r, c])
        if big == 0.0:
            return G_mu, False
        if p != c:
            for j in range(m):
                A[c, j], A[p, j] = A[p, j], A[c, j]
            for j in range(nx):
                B[c, j], B[p, j] = B[p, j], B[c, j]
        for r in range(c + 1, m):
            f = A[r, c] / A[c, c]
            for j in range(c + 1, m):
                A[r, j] -= f * A[c, j]
            for j in range(nx):
                B[r, j] -= f * B[c, j]
    for c in range(m - 1, -1, -1):
        for j in range(nx):
            s = B[c, j]
            for k in range(c + 1, m):
                s -= A[c, k] * B[k, j]
            B[c, j] = s / A[c, c]
    return B, True


@njit(cache=True)
def term_variances(G, half, Ja, n_in):  # type: ignore[no-untyped-def]
    """The variances that ``G half half^T G^T`` adds: its diagonal (m,) and, through the
    angles' gradient ``Ja`` (n_out, n_in), that of ``Ja H H^T Ja^T`` (n_out,) with
    ``H = G half`` ((m, r) of ``G`` (m, q) and ``half`` (q, r))."""
    m, r = G.shape[0], half.shape[1]
    H = np.zeros((m, r))
    for i in range(m):
        for k in range(G.shape[1]):
            a = G[i, k]
            for j in range(r):
                H[i, j] += a * half[k, j]
    var = np.zeros(m)
    for i in range(m):
        for j in range(r):
            var[i] += H[i, j] * H[i, j]
    avar = np.zeros(Ja.shape[0])
    for o in range(Ja.shape[0]):
        for j in range(r):
            s = 0.0
            for i in range(n_in):
                s += Ja[o, i] * H[i, j]
            avar[o] += s * s
    return var, avar


@njit(cache=True)
def drift(x, a, b, s, z, lo, hi, out):  # type: ignore[no-untyped-def]
    """The transition ``out[:, :q] = a + b x + s z`` of the first ``q`` columns of the
    particles ``x`` (N, d) with the normal draws ``z`` (N, q) and the columns' ``a, b, s``
    (q,), as NumPy's ``x * b``, ``+= a``, ``+= z * s`` (the same float steps); returns
    the rows (N,) that left the box ``[lo, hi]`` in one of those columns (to be
    reflected: :func:`formtwin.evolution.into_box`)."""
    n, q = z.shape
    rows = np.zeros(n, dtype=np.bool_)
    for k in range(n):
        for j in range(q):
            v = x[k, j] * b[j]
            v = v + a[j]
            v = v + z[k, j] * s[j]
            out[k, j] = v
            if v < lo[j] or v > hi[j]:
                rows[k] = True
    return rows
