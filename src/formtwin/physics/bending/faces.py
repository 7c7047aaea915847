"""Contact points on the sheet's faces and their current positions (Numba kernels).

A contact point at ``xi`` in element ``e`` (nodes ``a = e``, ``b = e + 1``) lies ``s t/2``
along the normal ``n = (-sin, cos)`` of the direction ``(1 - xi) phi_a + xi phi_b`` from the
cubic Hermite mid-surface ``H1 x_a + H2 L0 t(phi_a) + H3 x_b + H4 L0 t(phi_b)``
(:func:`hermite_face`; see :mod:`.contact` for how the points carry the contact forces).

The hot paths (every assembly in :func:`.contact.contact_forces`, every converged increment
in :func:`.solver.run_history`) evaluate the same points for each of the tools. They take the
cosines and sines of the nodes' and the points' directions once (:func:`face_trig`) and pass
them to :func:`hermite_face_dir`, which does the arithmetic of :func:`hermite_face` on them:
the numbers are those of :func:`hermite_face` bit for bit (the same operations on the same
operands), only the repeated ``cos``/``sin``/``hypot`` calls are gone.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from formtwin.physics.bending.kernels import FASTMATH


@njit(cache=True, error_model="numpy", fastmath=FASTMATH, inline="always")
def hermite_face(xa, ya, pa, xb, yb, pb, s, h, L0, xi, d):  # type: ignore[no-untyped-def]
    """Face point ``y`` (returned as ``(yx, yy)``) of a contact point, and its derivatives.

    Nodes ``a, b`` at ``(x, y)`` with directions ``p`` (rad); face ``s`` (+-1) at ``h`` (mm)
    from the mid-surface; element reference length ``L0``; ``xi`` in [0, 1]. The mid-surface
    point is the cubic Hermite ``H1 x_a + H2 L0 t(p_a) + H3 x_b + H4 L0 t(p_b)``, the face
    point lies ``s h`` along the normal of the interpolated direction ``(1 - xi) p_a + xi
    p_b`` (on a circular arc both are exact to O(L0^4)). Writes ``d (5, 2)``: ``dy/dp_a``,
    ``dy/dp_b``, ``d2y/dp_a2``, ``d2y/dp_b2``, ``d2y/dp_a dp_b``; ``dy/dx_a = H1``,
    ``dy/dx_b = H3`` (times the identity).
    """
    ca, sa, cb, sb = math.cos(pa), math.sin(pa), math.cos(pb), math.sin(pb)
    cp, sp = face_dir(pa, ca, sa, pb, xi)
    return hermite_face_dir(xa, ya, ca, sa, xb, yb, cb, sb, cp, sp, s, h, L0, xi, d)


@njit(cache=True, error_model="numpy", fastmath=FASTMATH, inline="always")
def face_dir(pa, ca, sa, pb, xi):  # type: ignore[no-untyped-def]
    """``cos, sin`` of a point's direction ``(1 - xi) p_a + xi p_b`` (``ca, sa`` at ``xi = 0``)."""
    if xi == 0.0:
        return ca, sa
    ang = (1.0 - xi) * pa + xi * pb
    return math.cos(ang), math.sin(ang)


@njit(cache=True, error_model="numpy", fastmath=FASTMATH, inline="always")
def hermite_face_dir(xa, ya, ca, sa, xb, yb, cb, sb, cp, sp,  # type: ignore[no-untyped-def]
                     s, h, L0, xi, d):
    """:func:`hermite_face` with the nodes' and the point's direction cosines and sines
    given (``cp, sp`` from :func:`face_dir`)."""
    x2 = xi * xi
    x3 = x2 * xi
    H1, H2, H3, H4 = 1.0 - 3.0 * x2 + 2.0 * x3, xi - 2.0 * x2 + x3, 3.0 * x2 - 2.0 * x3, x3 - x2
    sh = s * h
    wa, wb = 1.0 - xi, xi
    d[0, 0] = -H2 * L0 * sa - sh * cp * wa
    d[0, 1] = H2 * L0 * ca - sh * sp * wa
    d[1, 0] = -H4 * L0 * sb - sh * cp * wb
    d[1, 1] = H4 * L0 * cb - sh * sp * wb
    d[2, 0] = -H2 * L0 * ca + sh * sp * wa * wa
    d[2, 1] = -H2 * L0 * sa - sh * cp * wa * wa
    d[3, 0] = -H4 * L0 * cb + sh * sp * wb * wb
    d[3, 1] = -H4 * L0 * sb - sh * cp * wb * wb
    d[4, 0] = sh * sp * wa * wb
    d[4, 1] = -sh * cp * wa * wb
    return (H1 * xa + H2 * L0 * ca + H3 * xb + H4 * L0 * cb - sh * sp,
            H1 * ya + H2 * L0 * sa + H3 * yb + H4 * L0 * sb + sh * cp)


@njit(cache=True, error_model="numpy", fastmath=FASTMATH)
def face_trig(X, phi0, u, el, xi, trig):  # type: ignore[no-untyped-def]
    """Direction cosines and sines of the nodes and the points, and the elements' lengths.

    Writes ``trig (n_nodes + n_points, 2)``: rows ``i < n_nodes`` ``cos, sin`` of node ``i``'s
    direction ``phi0[i] + u[3 i + 2]``, rows ``n_nodes + q`` those of point ``q``
    (:func:`face_dir`); returns the elements' reference lengths ``(n_el,)`` (mm,
    :func:`element_lengths`).
    """
    node_point_trig(X, phi0, u, el, xi, trig)
    return element_lengths(X)


@njit(cache=True, error_model="numpy", fastmath=FASTMATH)
def element_lengths(X):  # type: ignore[no-untyped-def]
    """The elements' reference lengths ``(n_el,)`` (mm) of the nodes ``X (n_nodes, 2)``."""
    L0 = np.empty(X.shape[0] - 1)
    for e in range(X.shape[0] - 1):
        L0[e] = math.hypot(X[e + 1, 0] - X[e, 0], X[e + 1, 1] - X[e, 1])
    return L0


@njit(cache=True, error_model="numpy", fastmath=FASTMATH)
def node_point_trig(X, phi0, u, el, xi, trig):  # type: ignore[no-untyped-def]
    """The ``trig`` of :func:`face_trig` alone (the solver takes the elements' lengths
    once per run, :func:`element_lengths`)."""
    n_nodes = X.shape[0]
    for i in range(n_nodes):
        trig[i, 0] = math.cos(phi0[i] + u[3 * i + 2])
        trig[i, 1] = math.sin(phi0[i] + u[3 * i + 2])
    for q in range(el.shape[0]):
        e = el[q]
        cp, sp = face_dir(phi0[e] + u[3 * e + 2], trig[e, 0], trig[e, 1],
                          phi0[e + 1] + u[3 * e + 5], xi[q])
        trig[n_nodes + q, 0] = cp
        trig[n_nodes + q, 1] = sp


@njit(cache=True, error_model="numpy", fastmath=FASTMATH, inline="always")
def point_face_trig(X, u, el, xi, q, s, h, L0, trig, d):  # type: ignore[no-untyped-def]
    """:func:`point_face` of point ``q`` from :func:`face_trig`'s ``trig`` and ``L0``."""
    e = el[q]
    n_nodes = X.shape[0]
    return hermite_face_dir(X[e, 0] + u[3 * e], X[e, 1] + u[3 * e + 1], trig[e, 0], trig[e, 1],
                            X[e + 1, 0] + u[3 * e + 3], X[e + 1, 1] + u[3 * e + 4],
                            trig[e + 1, 0], trig[e + 1, 1], trig[n_nodes + q, 0],
                            trig[n_nodes + q, 1], s, h, L0[e], xi[q], d)


@njit(cache=True, error_model="numpy", fastmath=FASTMATH)
def face_points(X, phi0, u, el, xi, tface, towner, h, p, rel):  # type: ignore[no-untyped-def]
    """Every point's face position in every tool's frame, ``rel (n_points, n_tools, 2)``:
    :func:`point_face` on face ``tface[k]`` (offset ``h``), minus the punch position ``p``
    in ``y`` for the tools it owns (``towner == 1``)."""
    trig = np.empty((X.shape[0] + el.shape[0], 2))
    L0 = face_trig(X, phi0, u, el, xi, trig)
    d = np.empty((5, 2))
    for q in range(el.shape[0]):
        for k in range(tface.shape[0]):
            fx, fy = point_face_trig(X, u, el, xi, q, tface[k], h, L0, trig, d)
            rel[q, k, 0] = fx
            rel[q, k, 1] = fy - (p if towner[k] == 1 else 0.0)


@njit(cache=True, error_model="numpy", fastmath=FASTMATH)
def contact_points(X, phi0, n_sub):  # type: ignore[no-untyped-def]
    """Contact points of a sheet ``X (n_nodes, 2)``: element ``(n_p,)``, ``xi (n_p,)``,
    reference position ``(n_p, 2)`` and share of the sheet's length ``(n_p,)`` (mm)."""
    n_el = X.shape[0] - 1
    n_p = n_el * n_sub + 1
    el = np.zeros(n_p, dtype=np.int64)
    xi = np.zeros(n_p)
    Xp = np.zeros((n_p, 2))
    w = np.zeros(n_p)
    for e in range(n_el):
        L0 = math.hypot(X[e + 1, 0] - X[e, 0], X[e + 1, 1] - X[e, 1])
        for m in range(n_sub + 1 if e == n_el - 1 else n_sub):
            p = e * n_sub + m
            el[p] = e
            xi[p] = m / n_sub
            Xp[p, 0] = X[e, 0] + xi[p] * (X[e + 1, 0] - X[e, 0])
            Xp[p, 1] = X[e, 1] + xi[p] * (X[e + 1, 1] - X[e, 1])
        for m in range(n_sub):
            w[e * n_sub + m] += 0.5 * L0 / n_sub
            w[e * n_sub + m + 1] += 0.5 * L0 / n_sub
    return el, xi, Xp, w


@njit(cache=True, error_model="numpy", fastmath=FASTMATH)
def point_face(X, phi0, u, el, xi, p, s, h):  # type: ignore[no-untyped-def]
    """Current face point ``(x, y)`` of contact point ``p`` (face ``s``, offset ``h``), by the
    solver's own path (:func:`face_trig`, :func:`point_face_trig`)."""
    trig = np.empty((X.shape[0] + el.shape[0], 2))
    L0 = face_trig(X, phi0, u, el, xi, trig)
    return point_face_trig(X, u, el, xi, p, s, h, L0, trig, np.zeros((5, 2)))
