"""A monitor's per-product arithmetic in one pass over arrays (Numba kernels).

:class:`~formtwin.monitoring.Monitor` keeps every chart's state in arrays over its
quantities, and a charted product costs three kernel calls and two calls of SciPy's
``ndtri`` on the whole vector, instead of ~60 small Python objects (named tuples,
dataclasses) per product:

1. :func:`reference_probabilities`: each health statistic's in-control probability of a
   value at least as good (:meth:`~formtwin.monitoring.incontrol.Reference.normal_score`
   before its ``ndtri``);
2. :func:`residual_probabilities`: each AR model's one-step residual ``e / sigma`` and its
   probability under the in-control quantiles
   (:meth:`~formtwin.monitoring.incontrol.InControl.score` before its ``ndtri``), or the
   score itself where no ``ndtri`` is needed (tails, no quantiles, non-finite);
3. :func:`chart_step`: the EWMA, GLR, CUSUM and Shewhart charts of every quantity, the
   mismatch CUSUM of every health statistic, the AR histories and the health levels that
   follow the line (:class:`~formtwin.monitoring.charts.Ewma`,
   :class:`~formtwin.monitoring.charts.Cusum`, :class:`~formtwin.monitoring.glr.Glr`,
   ``Monitor._remember``, ``Monitor._follow``).

Every statistic is the same float operations in the same order as the scalar forms
(Python's ``max(0.0, x)`` is ``x if x > 0.0 else 0.0``, the EWMA limit a table of
:func:`~formtwin.monitoring.charts.ewma_limit` itself, the GLR the same
``_add_and_max``), so the alarms and the saved state are the scalar forms' bit for bit
(``tests/test_monitoring_bank.py`` charts streams both ways). No fast-math.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
from numba import njit
from numpy.typing import NDArray

from formtwin.monitoring.charts import ewma_limit
from formtwin.monitoring.glr import _add_and_max

FloatArray = NDArray[np.float64]

#: the charts of a quantity, the columns of :func:`chart_step`'s outputs
QUANTITY_CHARTS = ("ewma", "glr", "cusum", "shewhart")
#: ``alarmed_at`` of a health statistic whose chart has not signalled
NEVER = -(10**9)


def ewma_limits(lam: float, L: float) -> FloatArray:
    """:func:`~formtwin.monitoring.charts.ewma_limit` for ``i`` = 1, 2, ... (index
    ``i - 1``) up to the first ``i`` whose limit no later one differs from (``1 - (1 -
    lam)^(2 i)`` is 1.0 in floating point from there on): the same numbers, looked up."""
    out = [ewma_limit(1, lam, L)]
    i = 1
    while 1.0 - (1.0 - lam) ** (2 * i) != 1.0:
        i += 1
        out.append(ewma_limit(i, lam, L))
    return np.array(out)


def padded(rows: list[tuple[float, ...]], width: int | None = None
           ) -> tuple[FloatArray, NDArray[np.int64]]:
    """Rows of different lengths as one (n, width) array (NaN-padded) and their lengths."""
    w = max([len(r) for r in rows] + [1]) if width is None else width
    out = np.full((len(rows), w), np.nan)
    for j, r in enumerate(rows):
        out[j, :len(r)] = r
    return out, np.array([len(r) for r in rows], dtype=np.int64)


def split(buffer: NDArray[Any], shapes: Sequence[tuple[int, ...]]) -> list[NDArray[Any]]:
    """Consecutive views of ``buffer`` with ``shapes``."""
    out, at = [], 0
    for shape in shapes:
        size = math.prod(shape)
        out.append(buffer[at:at + size].reshape(shape))
        at += size
    return out


@njit(cache=True)
def _count_below(q, n, v, right):  # type: ignore[no-untyped-def]
    """``bisect_right(q[:n], v)`` (``right``) or ``bisect_left``: how many of the sorted
    ``q[:n]`` are ``<= v`` (``< v``)."""
    lo, hi = 0, n
    while lo < hi:
        mid = (lo + hi) // 2
        if (v < q[mid]) if right else (q[mid] >= v):
            hi = mid
        else:
            lo = mid + 1
    return lo


@njit(cache=True)
def reference_probabilities(v, start, sample, length, bad_low, out):  # type: ignore[no-untyped-def]
    """``out[r]`` = the probability whose ``ndtri`` is the normal score of health value
    ``v[start + r]`` against its sorted in-control ``sample[r, :length[r]]`` (mid-rank;
    ``bad_low``: low values are worse; NaN and the infinity on the bad side count as
    worst), clipped to ``[0.5 / n, 1 - 0.5 / n]``."""
    for r in range(out.size):
        n = length[r]
        x = v[start + r]
        if not np.isfinite(x):
            u = 0.0 if ((x > 0) == bad_low[r]) and not np.isnan(x) else 1.0
        else:
            below = (_count_below(sample[r], n, x, False)
                     + _count_below(sample[r], n, x, True))
            f = float(below) / (2.0 * n)
            u = 1.0 - f if bad_low[r] else f
        lo = 0.5 / n
        hi = 1.0 - 0.5 / n
        u = lo if lo > u else u  # min(max(u, lo), hi) as Python's
        out[r] = hi if hi < u else u


@njit(cache=True)
def residual_probabilities(v, scores, ref_of_model, hist, hlen, order, phi, mean,  # type: ignore[no-untyped-def]
                           has_mean, sigma, quant, qlen, zmax, y, use, f, direct, need):
    """Each AR model ``j``'s value ``y[j]``: ``v[j]`` for a quantity (the first
    ``v.size - scores.size``), the normal score ``scores[ref_of_model[j - nq]]`` for a
    health model; ``use[j]``: it has its ``order[j]`` earlier values, its mean and (a
    quantity) a finite value. For those, its standardised residual given its history
    ``hist[j, :hlen[j]]`` (oldest first) and ``mean[j]``; with quantiles ``quant[j,
    :qlen[j]]`` the probability ``f[j]`` whose ``ndtri`` is its normal score
    (``need[j]``), else the score itself in ``direct[j]``."""
    nq = v.size - scores.size
    for j in range(y.size):
        y[j] = v[j] if j < nq else scores[ref_of_model[j - nq]]
        f[j] = 0.5
        need[j] = False
        use[j] = hlen[j] >= order[j] and has_mean[j] != 0 and (j >= nq or np.isfinite(y[j]))
        if not use[j]:
            continue
        m = mean[j]
        s = 0.0
        p = order[j]
        h = hlen[j]
        for lag in range(p):  # sum(phi_l (h_{-l} - m)) from 0, as Python's sum
            s = s + phi[j, lag] * (hist[j, h - 1 - lag] - m)
        e = (y[j] - (m + s)) / sigma[j]
        n = qlen[j]
        if n == 0:
            direct[j] = e
            continue
        lo = quant[j, 0]
        hi = quant[j, n - 1]
        if not np.isfinite(e):
            direct[j] = np.nan if np.isnan(e) else (np.inf if e > 0 else -np.inf)
        elif e <= lo:
            direct[j] = -zmax[j] - (lo - e)
        elif e >= hi:
            direct[j] = zmax[j] + (e - hi)
        else:
            k = _count_below(quant[j], n, e, True) - 1  # q[k] <= e < q[k + 1]
            span = quant[j, k + 1] - quant[j, k]
            frac = (e - quant[j, k]) / span if span > 0 else 0.5
            f[j] = (k + 0.5 + frac) / n
            need[j] = True


@njit(cache=True)
def chart_step(zf, direct, need, use, scores, y, hist, hlen, order, mean, has_mean,  # type: ignore[no-untyped-def]
               e_lam, e_z, e_i, e_lim, e_len,
               has_c, c_k, c_h, c_hi_on, c_lo_on, c_hi, c_lo, shew,
               has_g, g_s, g_d2, g_win, g_h, g_clip, g_sums, g_len, g_i,
               h_model, h_k, h_h, h_hi, h_lo, alarmed_at, n_seen, follow, hold,
               stat, lim, side, h_stat, h_side, h_charted):
    """One charted product. Each AR model's score is ``zf[j]`` (``ndtri`` of
    :func:`residual_probabilities`' ``f``) where ``need[j]``, else ``direct[j]``.
    Quantities ``q < nq`` (their models' scores where ``use[q]``): EWMA, GLR
    (``has_g``), CUSUM (``has_c``) and Shewhart (``shew`` not NaN, with the CUSUM) into
    ``stat``, ``lim``, ``side`` (nq, 4) (side 1 high, -1 low, 0 none; columns
    :data:`QUANTITY_CHARTS`), each chart restarted after a signal. Health
    statistics ``r``: the one-sided mismatch CUSUM of its AR model ``h_model[r]``'s score
    (``h_charted[r]``: that model had the history and mean to score it), or of its normal
    score ``scores[r]`` (``h_model[r]`` = -1), signals recorded in ``alarmed_at[r] =
    n_seen``. Then every AR model's history takes its finite ``y[j]``, and with ``follow``
    > 0 each health model's mean moves by ``follow`` times its score's clipped deviation,
    unless within ``hold`` products of its chart's last signal."""
    nq = e_z.size
    for q in range(nq):
        for c in range(4):
            side[q, c] = 0
            stat[q, c] = np.nan
            lim[q, c] = np.nan
        if not use[q]:
            continue
        x = zf[q] if need[q] else direct[q]
        lam = e_lam[q]
        zz = lam * x + (1.0 - lam) * e_z[q]
        i = e_i[q] + 1
        li = e_lim[q, min(i, e_len[q]) - 1]
        sd = 1 if zz > li else (-1 if zz < -li else 0)
        stat[q, 0], lim[q, 0], side[q, 0] = zz, li, sd
        if sd:
            e_z[q], e_i[q] = 0.0, 0
        else:
            e_z[q], e_i[q] = zz, i
        if has_g[q]:
            xg = x
            cl = g_clip[q]
            if not np.isnan(cl):  # min(max(z, -clip), clip) as Python's
                xg = -cl if -cl > xg else xg
                xg = cl if cl < xg else xg
            w = g_win[q]
            m = min(g_i[q] + 1, w)
            row = g_sums[q]
            for a in range(m - 1, 0, -1):
                row[a] = row[a - 1]
            row[0] = 0.0
            k, g = _add_and_max(row, g_s[q], g_d2[q], xg, m)
            sg = 0 if g <= g_h[q] else (1 if row[k] > 0 else -1)
            stat[q, 1], lim[q, 1], side[q, 1] = g, g_h[q], sg
            if sg:
                g_len[q], g_i[q] = 0, 0
            else:
                g_len[q], g_i[q] = m, g_i[q] + 1
        if not has_c[q]:
            continue
        hi = 0.0
        if c_hi_on:
            t = x - c_k[q] + c_hi[q]
            hi = t if t > 0.0 else 0.0
        lo = 0.0
        if c_lo_on:
            t = -x - c_k[q] + c_lo[q]
            lo = t if t > 0.0 else 0.0
        lim[q, 2] = c_h[q]
        if hi > c_h[q]:
            stat[q, 2], side[q, 2] = hi, 1
            c_hi[q], c_lo[q] = 0.0, 0.0
        elif lo > c_h[q]:
            stat[q, 2], side[q, 2] = lo, -1
            c_hi[q], c_lo[q] = 0.0, 0.0
        else:
            stat[q, 2] = lo if lo > hi else hi
            c_hi[q], c_lo[q] = hi, lo
        if not np.isnan(shew[q]):
            stat[q, 3], lim[q, 3] = x, shew[q]
            if abs(x) > shew[q]:
                side[q, 3] = 1 if x > 0 else -1
    for r in range(h_k.size):
        h_side[r] = 0
        j = h_model[r]
        h_charted[r] = j < 0 or use[j]
        if not h_charted[r]:
            continue
        x = scores[r] if j < 0 else (zf[j] if need[j] else direct[j])
        t = x - h_k[r] + h_hi[r]
        hi = t if t > 0.0 else 0.0
        h_stat[r] = hi
        if hi > h_h[r]:
            h_side[r] = 1
            h_hi[r], h_lo[r] = 0.0, 0.0
            alarmed_at[r] = n_seen
        else:
            h_stat[r] = 0.0 if 0.0 > hi else hi  # max(hi, lo) with lo = 0
            h_hi[r], h_lo[r] = hi, 0.0
    for j in range(y.size):  # the AR histories: the last order[j] finite values
        p = order[j]
        if p == 0 or not np.isfinite(y[j]):
            continue
        if hlen[j] < p:
            hist[j, hlen[j]] = y[j]
            hlen[j] += 1
        else:
            for a in range(p - 1):
                hist[j, a] = hist[j, a + 1]
            hist[j, p - 1] = y[j]
    if follow > 0.0:
        for r in range(h_k.size):
            j = h_model[r]
            if j < 0 or n_seen - alarmed_at[r] < hold:
                continue
            m = mean[j]
            v = y[j]
            if has_mean[j] != 0 and np.isfinite(v):
                d = v - m
                d = -3.0 if -3.0 > d else d
                d = 3.0 if 3.0 < d else d
                mean[j] = m + follow * d


def load_kernels(monitor: Any) -> None:
    """Load the kernels of ``monitor``'s charted products now (from Numba's cache, ~10 ms;
    compiled, seconds), not at its first charted product: a copy of it charts one product
    of zeros (``monitor`` is untouched). A service calls it at its start, so that product's
    latency is like the others'."""
    probe = monitor.copy()
    probe._chart(dict.fromkeys(probe._inputs, 0.0), 0)


__all__ = ["NEVER", "QUANTITY_CHARTS", "chart_step", "ewma_limits", "load_kernels", "padded",
           "reference_probabilities", "residual_probabilities", "split"]
