"""Deviation model ``z = g(z~, theta_d)`` between modelled and real force curve, and its inverse.

``theta_d = [a_1..a_k, b_1..b_k]`` holds the force scaling ``a`` and the speed scaling ``b``
at ``k`` evenly spaced knots on the curve window (paper: k = 4 on [-80, 20] ms, values in
[-0.2, 0.2]); both are piecewise linear in time between the knots and constant beyond them.
The real curve is

    z(t) = (1 + a(t)) z~(tau(t)),    tau(t) = int_0^t (1 + b(s)) ds,

so a faster punch (b > 0) runs through model time quicker; tau is anchored at t = 0, where
the punch is lowest, and is strictly increasing because b > -1. ``tau`` is a piecewise
quadratic and is integrated and inverted exactly, segment by segment. A curve is read
between its samples by linear interpolation and, outside its window, by its edge value
(the force is flat there: before contact and after release).

Everything is vectorised: one curve against ``N`` parameter sets gives ``(N, n_t)`` at once.

>>> import numpy as np
>>> t = np.linspace(-0.08, 0.02, 101)
>>> g = DeviationModel(t, np.linspace(-0.08, 0.02, 4))
>>> z = np.exp(-((t + 0.01) / 0.02) ** 2)
>>> theta_d = np.array([0.1, 0.1, 0.1, 0.1, 0.0, 0.0, 0.0, 0.0])
>>> bool(np.allclose(g.apply(z, theta_d), 1.1 * z))
True
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import Any

import numpy as np
from numba import njit
from numpy.typing import NDArray

from formtwin.spec import ProcessSpec

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class DeviationModel:
    """``g`` on a uniform grid ``time`` (n_t,) (s, or mm of stroke) with knots ``knots``
    (k,) in the same unit. ``kinds`` (the spec's ``[deviation] kinds``) are the parts of
    ``theta_d``, in the order force scaling, speed scaling; a kind left out is held at 0
    (no kinds: ``g`` is the identity and ``theta_d`` has no columns)."""

    time: FloatArray
    knots: FloatArray
    kinds: tuple[str, ...] = ("force_scaling", "speed_scaling")

    @classmethod
    def from_spec(cls, spec: ProcessSpec) -> DeviationModel:
        """The deviation model of ``spec``: its kinds and knots on the spec's curve grid."""
        return cls(spec.time, spec.deviation.knots, spec.deviation.kinds)

    @property
    def n_params(self) -> int:
        """Length of ``theta_d``: ``k`` per kind (``2 k`` with force and speed scaling)."""
        return len(self.kinds) * int(self.knots.size)

    def _split(self, theta_d: FloatArray) -> tuple[FloatArray, FloatArray]:
        theta_d = np.atleast_2d(np.asarray(theta_d, dtype=np.float64))
        k, n = self.knots.size, self.n_params
        if theta_d.shape[-1] != n:
            raise ValueError(f"theta_d has {theta_d.shape[-1]} columns, expected {n}")
        zero = np.zeros((theta_d.shape[0], k))
        a = theta_d[:, :k] if "force_scaling" in self.kinds else zero
        b = theta_d[:, n - k:] if "speed_scaling" in self.kinds else zero
        if np.any(b <= -1.0):
            raise ValueError("theta_d speed scaling must be above -1 (time must run forward)")
        return a, b

    def _knot_weights(self, t: FloatArray) -> tuple[NDArray[np.intp], FloatArray]:
        """Knot interval ``idx`` (n,) of times ``t`` (n,) and the weight ``w`` (n,) of its
        right knot (clipped to [0, 1]: flat outside the knots)."""
        kn = self.knots
        idx = np.clip(np.searchsorted(kn, t, side="right") - 1, 0, kn.size - 2)
        w = np.clip((t - kn[idx]) / (kn[idx + 1] - kn[idx]), 0.0, 1.0)
        return idx, w

    def _pwl(self, t: FloatArray, values: FloatArray) -> FloatArray:
        """Piecewise-linear ``values`` (N, k) at times ``t`` (n,) -> (N, n), flat outside."""
        idx, w = self._knot_weights(t)
        out: FloatArray = values[:, idx] * (1.0 - w) + values[:, idx + 1] * w
        return out

    @cached_property
    def _grid(self) -> tuple[Any, ...]:
        """Per grid time (n_t,): the knot interval and weight of :meth:`_pwl`, the segment of
        :meth:`_segments` (0 = left tail) and the offset from its base time; then the grid's
        start and step (s). Computed once per model."""
        t, kn = self.time, self.knots
        idx, w = self._knot_weights(t)
        seg = np.searchsorted(kn, t, side="right")
        u = t - np.concatenate([kn[:1], kn])[seg]
        return idx, w, seg, u, float(t[0]), float(t[1] - t[0])

    def force_scaling(self, theta_d: FloatArray) -> FloatArray:
        """``a(t)`` on the grid, ``(N, n_t)``."""
        a, _ = self._split(theta_d)
        return self._pwl(self.time, a)

    def _segments(self, b: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        """Segments of ``tau`` (left tail, k-1 interior, right tail): base time (k+1,) and,
        per row, tau at the base, slope ``1 + b`` and curvature ``db/dt``, each (N, k+1)."""
        kn, n = self.knots, b.shape[0]
        h = np.diff(kn)
        cum = np.concatenate([np.zeros((n, 1)),
                              np.cumsum(0.5 * (b[:, :-1] + b[:, 1:]) * h, axis=1)], axis=1)
        base = np.concatenate([kn[:1], kn])
        b_int = np.concatenate([cum[:, :1], cum], axis=1)  # int_{k_0}^{base} b ds
        slope = 1.0 + np.concatenate([b[:, :1], b], axis=1)
        curv = np.concatenate([np.zeros((n, 1)), np.diff(b, axis=1) / h, np.zeros((n, 1))],
                              axis=1)
        # tau(t) = t + B(t) - B(0); evaluate t + B at t = 0 to anchor it
        seg0 = int(np.searchsorted(kn, 0.0, side="right"))
        u0 = 0.0 - base[seg0]
        f0 = b_int[:, seg0] + (slope[:, seg0] - 1.0) * u0 + 0.5 * curv[:, seg0] * u0**2
        return base, base + b_int - f0[:, None], slope, curv

    def model_time(self, theta_d: FloatArray) -> FloatArray:
        """``tau(t)`` on the grid, ``(N, n_t)`` s."""
        _, b = self._split(theta_d)
        _, tau_base, slope, curv = self._segments(b)
        seg, u = self._grid[2:4]
        out: FloatArray = tau_base[:, seg] + slope[:, seg] * u + 0.5 * curv[:, seg] * u**2
        return out

    def _inverse(self, theta_d: FloatArray) -> tuple[FloatArray, FloatArray]:
        """``t(tau)`` at the grid's model times and ``a`` there, both ``(N, n_t)``."""
        a, b = self._split(theta_d)
        base, tau_base, slope, curv = self._segments(b)
        n_rows, n_t = b.shape[0], self.time.size
        # a is piecewise linear on the same segments: its value and slope at each base
        zero = np.zeros((n_rows, 1))
        a_base = np.concatenate([a[:, :1], a], axis=1)
        a_slope = np.concatenate([zero, np.diff(a, axis=1) / np.diff(self.knots), zero], axis=1)
        # segment of each model time: how many knots' tau lie at or below it. tau is
        # increasing, so per row the segments are runs of consecutive grid times: the run
        # of segment j starts at the first time >= tau at knot j, and a segment's numbers
        # are repeated over its run (the same values as gathering them point by point)
        starts = np.searchsorted(self.time, tau_base[:, 1:], side="left")  # (N, k)
        edges = np.concatenate([np.zeros((n_rows, 1), np.intp), starts,
                                np.full((n_rows, 1), n_t, np.intp)], axis=1)
        runs = np.diff(edges, axis=1).ravel()  # (N (k+1),) lengths, summing to n_t per row
        per_seg = np.stack([tau_base, slope, curv, a_base, a_slope,
                            np.broadcast_to(base, tau_base.shape)])  # (6, N, k+1)
        tau0, s1, s2, a0, da, t0 = np.repeat(per_seg.reshape(6, -1), runs, axis=1).reshape(
            6, n_rows, n_t)
        # u solves tau0 + s1 u + s2 u^2 / 2 = time, in the cancellation-free form
        c = self.time[None, :] - tau0
        root = s1**2
        q = 2.0 * s2
        q *= c
        root += q
        np.maximum(root, 0.0, out=root)
        np.sqrt(root, out=root)
        root += s1
        u = 2.0 * c
        u /= root
        da *= u
        a0 += da
        t0 += u
        return t0, a0

    def real_time(self, theta_d: FloatArray) -> FloatArray:
        """``t(tau)``, the inverse of ``tau``, at the grid's model times, ``(N, n_t)`` s."""
        return self._inverse(theta_d)[0]

    def _interp_rows(self, curves: FloatArray, tq: FloatArray) -> FloatArray:
        """Row-wise linear interpolation of curves (n_t,) or (N, n_t) at times tq (N, n_t)."""
        t0, dt, n = self.time[0], self.time[1] - self.time[0], self.time.size
        pos = tq - t0
        pos /= dt
        np.clip(pos, 0.0, n - 1.0, out=pos)
        i = np.minimum(pos.astype(np.intp), n - 2)
        w = pos - i
        if curves.ndim == 1:  # one curve for all rows: plain indexing
            step = np.diff(curves)  # curves[i + 1] - curves[i]
            w *= step[i]
            w += curves[i]
            out1: FloatArray = w
            return out1
        curves = np.broadcast_to(curves, tq.shape)
        # row r's sample j is entry r n + j of the flat array: one take per end of the
        # interval (as take_along_axis, ~2x faster), then lo + w (hi - lo) as before
        i += np.arange(0, curves.size, n)[:, None]
        flat = np.ascontiguousarray(curves).reshape(-1)
        lo = flat.take(i)
        i += 1
        out: FloatArray = flat.take(i)
        out -= lo
        out *= w
        out += lo
        return out

    def _identity(self, z: FloatArray, td: FloatArray) -> FloatArray:
        """Curves (N, n_t) unchanged: a copy of ``z`` (n_t,) or (N, n_t), N rows of ``td``."""
        if td.shape[-1] != 0:
            raise ValueError(f"theta_d has {td.shape[-1]} columns, expected 0 (no deviation "
                             "kinds)")
        out: FloatArray = np.array(np.broadcast_to(z, (td.shape[0], self.time.size)))
        return out

    def apply(self, z_model: FloatArray, theta_d: FloatArray) -> FloatArray:
        """``g(z~, theta_d)``: modelled curve(s) (n_t,) or (N, n_t) -> real curves (N, n_t).

        Curves (N, n_t) with finite ``theta_d`` (N, 2k) (the tracker's particles) take one
        Numba pass (:func:`_apply_rows`) with the same float operations as the NumPy steps
        below, bit for bit (``tests/test_deviation.py``).
        """
        z = np.asarray(z_model, dtype=np.float64)
        td = np.atleast_2d(np.asarray(theta_d, dtype=np.float64))
        if not self.kinds:  # no deviation model: g is the identity
            return self._identity(z, td)
        if z.ndim == 2 and z.shape == (td.shape[0], self.time.size) and np.isfinite(td).all():
            a, b = self._split(td)
            _, tau_base, slope, curv = self._segments(b)
            out: FloatArray = _apply_rows(np.ascontiguousarray(z), np.ascontiguousarray(a),
                                          tau_base, slope, curv, *self._grid)
            return out
        a = self.force_scaling(theta_d)
        return (1.0 + a) * self._interp_rows(z, self.model_time(theta_d))

    def invert(self, z: FloatArray, theta_d: FloatArray) -> FloatArray:
        """``g^-1(z, theta_d)``: real curve(s) (n_t,) or (N, n_t) -> model-time curves (N, n_t)."""
        if not self.kinds:
            return self._identity(np.asarray(z, dtype=np.float64),
                                  np.atleast_2d(np.asarray(theta_d, dtype=np.float64)))
        t_real, a = self._inverse(theta_d)
        out: FloatArray = self._interp_rows(np.asarray(z, dtype=np.float64), t_real) / (1.0 + a)
        return out


@njit(cache=True)
def _apply_rows(z, a, tau_base, slope, curv, idx, w, seg, u, t0, dt):  # type: ignore[no-untyped-def]
    """``g`` row by row in one pass (Numba): the operations of ``_pwl``, ``model_time``,
    ``_interp_rows`` and ``(1 + a) *`` in their order, per entry."""
    n_rows, n_t = z.shape
    out = np.empty((n_rows, n_t))
    for r in range(n_rows):
        for j in range(n_t):
            i = idx[j]
            aj = a[r, i] * (1.0 - w[j]) + a[r, i + 1] * w[j]
            sj = seg[j]
            tau = tau_base[r, sj] + slope[r, sj] * u[j] + 0.5 * curv[r, sj] * (u[j] * u[j])
            pos = (tau - t0) / dt
            if pos < 0.0:  # np.clip(pos, 0, n - 1)
                pos = 0.0
            if pos > n_t - 1.0:
                pos = n_t - 1.0
            k = min(int(pos), n_t - 2)
            lo = z[r, k]
            out[r, j] = (1.0 + aj) * ((z[r, k + 1] - lo) * (pos - k) + lo)
    return out

