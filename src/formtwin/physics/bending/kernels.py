"""Numba kernels of the bending model: material point, corotational beam, band LU.

Units are mm, N, s, MPa; all forces are per mm of width (2D plane strain).

Material point
    The through-thickness layers are in uniaxial plane-strain bending (sigma_yy = 0,
    eps_zz = 0). With the plane-strain modulus ``E' = E / (1 - nu^2)`` and an incompressible
    plastic flow, von Mises gives ``sigma_xx = (2/sqrt 3) sigma_flow`` at yield and an
    equivalent plastic strain rate ``(2/sqrt 3) |epsdot_p,xx|``; the return map is therefore
    one-dimensional in ``sigma_xx``. The flow stress is
    ``(1 + (epsdot/epsdot0)^q) sigma_y h(eps_bar)`` (Cowper-Symonds, paper eq. 11) with the
    tabulated hardening ratio ``h`` and the equivalent strain rate of the layer from the
    previous converged increment (lagged one increment, so the tangent stays consistent).

Beam
    Two-node corotational Euler-Bernoulli element (Crisfield; Battini): local axial
    stretch ``u_l = l - l0`` and local end rotations ``theta_i - (beta - beta0)``;
    cubic Hermite bending, ``n_g`` Gauss points along, layers through the thickness.

Through-thickness stress
    The contact pressure on a face is not zero through the thickness: each layer carries a
    through-thickness stress ``sigma_yy``, linear from ``-p_lower`` on the lower face to
    ``-p_upper`` on the upper face, with the pressures of the last converged increment
    (lagged, so the tangent stays exact for the increment) spread along the sheet over
    about a thickness (:func:`.contact.face_pressure`). In plane strain with incompressible flow the
    yield condition becomes ``|sigma_xx - sigma_yy| = (2/sqrt 3) sigma_flow``: a sheet pressed
    onto a tool yields at a shifted axial stress, which a plain beam misses.

Transverse shear stress (2.3)
    An Euler-Bernoulli beam carries any shear force ``V = dM/ds``, but a layer cannot: where
    the punch pinches the flap against the die radius over a span of about one thickness
    (near bottom dead centre), the mean shear stress ``V/t`` of the sheet reaches the shear
    yield stress ``k = sigma_flow/sqrt 3``, and the continuum shears plastically there. Each
    element's mean shear stress ``tau = V/t`` of the last converged increment (lagged, as
    the pressure; :func:`element_shear`) enters each of its layers' plane-strain von Mises
    condition ``(sigma_xx - sigma_yy)^2/4 + tau^2 = k^2``, i.e.
    ``|sigma_xx - sigma_yy| = (2/sqrt 3) sigma_flow sqrt(1 - (tau/k)^2)``: the axial
    capacity, and with it the moment, drops where the shear force is high. The uniform
    ``tau`` is the fully plastic shear distribution; the shear strain itself is not modelled.

Shear under a pinching punch (2.4)
    Where the punch presses the flap at or above a fraction of the plane-strain yield stress,
    an element takes the largest ``|V/t|`` within one thickness (``pinch_reach``) of its
    centre: in the continuum the core shear of the span next to the pinched contact runs on
    into the contact patch, so the section at the punch edge yields under the reverse moment
    of the flap's tip (:func:`element_shear`).

Contact: :mod:`.contact`.
"""

from __future__ import annotations

import math

from numba import njit

from formtwin.physics.bending.material import HARD_EPS, HARD_RATIO, HARD_SLOPE

SQ = 2.0 / math.sqrt(3.0)  # plane-strain factor between sigma_xx and the von Mises stress
#: smallest fraction of a layer's axial yield stress left by the shear stress (a lagged
#: ``tau`` may exceed ``k`` for an increment)
SHEAR_FLOOR = 0.2
BW = 5  # semi-bandwidth of the stiffness of a chain of 3-dof nodes
#: fast-math flags of all kernels (also :mod:`.contact`): they keep NaN/inf semantics
#: (failed runs must still be detected) and leave out ``reassoc`` and ``contract``. With
#: those two, LLVM re-optimises a callee linked into its caller differently from the
#: callee compiled alone; a fresh process calls the latter, a process that loads the
#: caller from Numba's on-disk cache the former, and the outputs differed by up to 0.3 N
#: (0.1.0.dev12, docs/notes/physics-determinism.md)
FASTMATH = {"nsz", "arcp", "afn"}

# ---------------------------------------------------------------------------- material


@njit(cache=True, error_model="numpy", fastmath=FASTMATH)
def hardening(eb, hard):  # type: ignore[no-untyped-def]
    """Hardening ratio ``h(eb)`` and slope ``dh/deb`` from :data:`.material.HARD_RATIO`.

    Piecewise linear, linearly extrapolated; ``hard = 0`` gives perfect plasticity.
    """
    n = HARD_EPS.shape[0]
    i = 0
    while i < n - 2 and eb > HARD_EPS[i + 1]:
        i += 1
    slope = HARD_SLOPE[i]
    r = HARD_RATIO[i] + slope * (eb - HARD_EPS[i])
    return 1.0 + hard * (r - 1.0), hard * slope


@njit(cache=True, error_model="numpy", fastmath=FASTMATH)
def layer_update(de, sig_n, epb_n, rate_n, E, sy, e0, q, hard,  # type: ignore[no-untyped-def]
                 syy=0.0, tau=0.0):
    """Return map of one layer point.

    ``E`` plane-strain modulus, ``sy`` yield stress (MPa), ``e0, q`` Cowper-Symonds
    constants, ``hard`` hardening switch (1 tabulated, 0 perfectly plastic); ``de`` the
    axial strain increment, ``rate_n`` the lagged equivalent strain rate (1/s); ``syy``
    the through-thickness stress (MPa, <= 0 under contact pressure), which shifts the
    yield condition to ``|sigma - syy| = (2/sqrt 3) sigma_flow``; ``tau`` the transverse
    shear stress (MPa), which scales it by ``sqrt(1 - (tau/k)^2)``, ``k = sigma_flow/sqrt 3``
    at the committed hardening and rate (at least :data:`SHEAR_FLOOR`).
    Returns ``(sigma, eps_bar, E_tangent)``.
    """
    r, fac = layer_yield(epb_n, sy, hard, tau)
    return layer_return(de, sig_n, epb_n, E, sy, hard, syy, r, fac, math.nan, rate_n, e0, q,
                        tau)[:3]


@njit(cache=True, error_model="numpy", fastmath=FASTMATH)
def layer_yield(epb_n, sy, hard, tau):  # type: ignore[no-untyped-def]
    """The factors of :func:`layer_update`'s rate-free yield surface, which depend on the
    committed state alone: hardening ratio ``r`` at ``epb_n`` and the shear factor ``fac``.

    They are constant over a time increment's Newton iterations (:func:`layer_scales_all`
    computes them once per increment); :func:`layer_return` takes them.
    """
    r = 1.0
    if epb_n > 0.0:
        r, h = hardening(epb_n, hard)
    fac = 1.0
    if tau != 0.0:  # von Mises with the shear stress: (s_xx - s_yy)^2/4 + tau^2 = k^2
        fac = math.sqrt(max(1.0 - 3.0 * (tau / (sy * r)) ** 2, SHEAR_FLOOR ** 2))
    return r, fac


@njit(cache=True, error_model="numpy", fastmath=FASTMATH)
def layer_s0(rate_n, sy, e0, q, tau, r, fac):  # type: ignore[no-untyped-def]
    """The rate-dependent axial yield stress ``s0`` (MPa, times ``r`` at yield) of
    :func:`layer_update` from :func:`layer_yield`'s ``r, fac`` (committed state alone)."""
    rf = 1.0
    if rate_n > 0.0:
        rf = 1.0 + (rate_n / e0) ** q
    if tau != 0.0:
        fac = math.sqrt(max(1.0 - 3.0 * (tau / (rf * sy * r)) ** 2, SHEAR_FLOOR ** 2))
    return SQ * rf * sy * fac


@njit(cache=True, error_model="numpy", fastmath=FASTMATH)
def layer_scales_all(epb, tshear, mat, out):  # type: ignore[no-untyped-def]
    """:func:`layer_yield` of every layer point ``(n_el, n_g, n_layers)`` into ``out[..., :2]``
    (``out (n_el, n_g, n_layers, 3)``) with element ``e``'s shear stress ``tshear[e]`` (MPa);
    ``out[..., 2] = NaN``: :func:`layer_s0` not computed yet (:func:`beam_element` computes
    it where a point first yields in the increment and keeps it)."""
    sy, hard = mat[1], mat[4]
    for e in range(epb.shape[0]):
        for g in range(epb.shape[1]):
            for k in range(epb.shape[2]):
                r, fac = layer_yield(epb[e, g, k], sy, hard, tshear[e])
                out[e, g, k, 0] = r
                out[e, g, k, 1] = fac
                out[e, g, k, 2] = math.nan


@njit(cache=True, error_model="numpy", fastmath=FASTMATH, inline="always")
def layer_return(de, sig_n, epb_n, E, sy, hard, syy, r, fac,  # type: ignore[no-untyped-def]
                 s0, rate_n, e0, q, tau):
    """:func:`layer_update` with the factors of :func:`layer_yield` given and ``s0`` of
    :func:`layer_s0` (NaN: computed here if the point yields); returns ``(sigma, eps_bar,
    E_tangent, s0)``.

    Inlined into its callers, so that a point inside the rate-free yield surface (most of
    a sheet's layer points) costs no call; :func:`layer_plastic` takes the others.
    """
    sig_tr = sig_n + E * de - syy  # the stress difference that yields
    if abs(sig_tr) <= SQ * sy * r * fac:  # inside the rate-free (smallest) yield surface
        return sig_tr + syy, epb_n, E, s0
    return layer_plastic(sig_tr, epb_n, E, sy, hard, syy, r, fac, s0, rate_n, e0, q, tau)


@njit(cache=True, error_model="numpy", fastmath=FASTMATH)
def layer_plastic(sig_tr, epb_n, E, sy, hard, syy, r, fac,  # type: ignore[no-untyped-def]
                  s0, rate_n, e0, q, tau):
    """:func:`layer_return` of a point outside the rate-free yield surface, from its trial
    stress difference ``sig_tr`` (MPa)."""
    a = abs(sig_tr)
    if math.isnan(s0):
        s0 = layer_s0(rate_n, sy, e0, q, tau, r, fac)
    if a - s0 * r <= 0.0:
        return sig_tr + syy, epb_n, E, s0
    dg = 0.0
    for _ in range(40):
        r, h = hardening(epb_n + SQ * dg, hard)
        res = a - E * dg - s0 * r
        step = res / (E + s0 * SQ * h)
        dg += step
        if abs(step) <= 1e-15 + 1e-13 * dg:
            break
    r, h = hardening(epb_n + SQ * dg, hard)
    H = s0 * SQ * h
    sig = math.copysign(a - E * dg, sig_tr) + syy
    return sig, epb_n + SQ * dg, E * H / (E + H), s0


# -------------------------------------------------------------------------------- beam


@njit(cache=True, error_model="numpy", fastmath=FASTMATH)
def beam_element(e, X, u, thick, ylay, wlay, xg, wg, mat,  # type: ignore[no-untyped-def]
                 sig, epb, eps, rate, sig_t, epb_t, eps_t, f, K, B, pface, tshear,
                 scales):
    """Internal force ``f (6,)`` and tangent ``K (6, 6)`` of element ``e`` (nodes e, e+1).

    Reads the committed layer state ``sig, epb, eps, rate [e]`` and writes the trial state
    into ``sig_t, epb_t, eps_t [e]``; ``B (3, 6)`` is work space; ``pface (n_nodes, 2)``
    the contact pressures (MPa) on the lower and upper face, interpolated linearly along
    the element, give each layer its through-thickness stress; ``tshear (n_el,)`` the
    elements' mean transverse shear stresses (MPa, :func:`element_shear`); ``scales (n_el,
    n_g, n_layers, 3)`` the layers' yield factors of the committed state
    (:func:`layer_scales_all`; ``s0`` filled in where a point first yields).
    """
    X1, Y1, X2, Y2 = X[e, 0], X[e, 1], X[e + 1, 0], X[e + 1, 1]
    dX, dY = X2 - X1, Y2 - Y1
    l0 = math.sqrt(dX * dX + dY * dY)
    c0, s0 = dX / l0, dY / l0
    i0 = 3 * e
    dx = dX + u[i0 + 3] - u[i0]
    dy = dY + u[i0 + 4] - u[i0 + 1]
    ln = math.sqrt(dx * dx + dy * dy)
    c, s = dx / ln, dy / ln
    alpha = math.atan2(c0 * s - s0 * c, c0 * c + s0 * s)
    th1 = u[i0 + 2] - alpha
    th2 = u[i0 + 5] - alpha
    ul = (ln * ln - l0 * l0) / (ln + l0)
    E, sy, e0, q, hard = mat[0], mat[1], mat[2], mat[3], mat[4]
    f0 = f1 = f2 = 0.0
    k00 = k01 = k02 = k11 = k12 = k22 = 0.0
    for g in range(xg.shape[0]):
        b2 = (6.0 * xg[g] - 4.0) / l0
        b3 = (6.0 * xg[g] - 2.0) / l0
        kap = b2 * th1 + b3 * th2
        wgl = wg[g] * l0 * thick
        p_lo = (1.0 - xg[g]) * pface[e, 0] + xg[g] * pface[e + 1, 0]
        p_up = (1.0 - xg[g]) * pface[e, 1] + xg[g] * pface[e + 1, 1]
        for k in range(ylay.shape[0]):
            y = thick * ylay[k]
            ek = ul / l0 - y * kap
            syy = -(p_lo * (0.5 - ylay[k]) + p_up * (0.5 + ylay[k]))
            sg, eb, et, s0k = layer_return(ek - eps[e, g, k], sig[e, g, k], epb[e, g, k], E,
                                           sy, hard, syy, scales[e, g, k, 0],
                                           scales[e, g, k, 1], scales[e, g, k, 2],
                                           rate[e, g, k], e0, q, tshear[e])
            scales[e, g, k, 2] = s0k  # kept for the increment's next assemblies
            sig_t[e, g, k] = sg
            epb_t[e, g, k] = eb
            eps_t[e, g, k] = ek
            w = wgl * wlay[k]
            d0 = 1.0 / l0
            d1 = -y * b2
            d2 = -y * b3
            ws = w * sg
            f0 += ws * d0
            f1 += ws * d1
            f2 += ws * d2
            we = w * et
            k00 += we * d0 * d0
            k01 += we * d0 * d1
            k02 += we * d0 * d2
            k11 += we * d1 * d1
            k12 += we * d1 * d2
            k22 += we * d2 * d2
    r = (-c, -s, 0.0, c, s, 0.0)
    z = (s, -c, 0.0, -s, c, 0.0)
    for j in range(6):
        B[0, j] = r[j]
        B[1, j] = -z[j] / ln
        B[2, j] = -z[j] / ln
    B[1, 2] += 1.0
    B[2, 5] += 1.0
    msum = (f1 + f2) / (ln * ln)
    for i in range(6):
        b0, b1, b2_ = B[0, i], B[1, i], B[2, i]
        f[i] = b0 * f0 + b1 * f1 + b2_ * f2
        g0 = b0 * k00 + b1 * k01 + b2_ * k02
        g1 = b0 * k01 + b1 * k11 + b2_ * k12
        g2 = b0 * k02 + b1 * k12 + b2_ * k22
        for j in range(6):
            K[i, j] = (g0 * B[0, j] + g1 * B[1, j] + g2 * B[2, j] + z[i] * z[j] * f0 / ln
                       + (r[i] * z[j] + z[i] * r[j]) * msum)


@njit(cache=True, error_model="numpy", fastmath=FASTMATH)
def element_shear(X, sig, thick, ylay, wlay, xg, tshear,  # type: ignore[no-untyped-def]
                  pface=None, reach=0.0, p0=0.0, p1=1.0, tadd=None):
    """Mean transverse shear stress ``V / t`` (MPa) of each element into ``tshear (n_el,)``.

    ``V = dM/ds`` from the bending moments ``M = -int sigma y dy`` (N mm/mm) of the layer
    stresses ``sig (n_el, n_g, n_layers)`` at the first and last Gauss point ``xg`` (moment
    linear along the element, as its curvature). ``tadd (n_el,)`` (MPa) is added to each
    element's value first (:func:`.contact.friction_shear`: the face friction's distributed
    moment, which ``dM/ds`` counts as shear force).

    With ``reach > 0`` (mm) and the punch's face pressure ``pface[:, 2]`` (MPa,
    :func:`.contact.face_pressure`): an element under the punch takes the largest ``|tau|``
    of the elements within ``reach`` of its centre, in full where the punch presses it by
    ``p1`` (MPa) or more, not at all below ``p0``, linearly in between. Where the punch
    pinches the flap, the continuum's core shear of the span next to the contact runs on
    into the contact patch (CalculiX at punch end distance 310 um: 165 MPa in the core at the
    punch edge where ``V/t`` is 47 MPa), and the section there yields under the reverse
    moment of the flap's tip.
    """
    n_g = xg.shape[0]
    for e in range(sig.shape[0]):
        m0 = 0.0
        m1 = 0.0
        for k in range(ylay.shape[0]):
            wy = thick * thick * wlay[k] * ylay[k]
            m0 -= wy * sig[e, 0, k]
            m1 -= wy * sig[e, n_g - 1, k]
        l0 = math.hypot(X[e + 1, 0] - X[e, 0], X[e + 1, 1] - X[e, 1])
        tshear[e] = (m1 - m0) / (l0 * (xg[n_g - 1] - xg[0]) * thick)
        if tadd is not None:
            tshear[e] += tadd[e]
    if pface is None or reach <= 0.0:
        return
    tau0 = tshear.copy()
    for e in range(sig.shape[0]):
        w = (max(pface[e, 2], pface[e + 1, 2]) - p0) / (p1 - p0)
        if w <= 0.0:
            continue
        xc = 0.5 * (X[e, 0] + X[e + 1, 0])
        best = tau0[e]
        for f in range(sig.shape[0]):
            if abs(0.5 * (X[f, 0] + X[f + 1, 0]) - xc) <= reach and abs(tau0[f]) > abs(best):
                best = tau0[f]
        tshear[e] = tau0[e] + min(w, 1.0) * (best - tau0[e])


# ------------------------------------------------------------------------------ band LU


@njit(cache=True, error_model="numpy", fastmath=FASTMATH)
def band_lu(A):  # type: ignore[no-untyped-def]
    """In-place LU (no pivoting) of a band matrix ``A[i, j - i + BW]``; False if singular."""
    n = A.shape[0]
    for k in range(n):
        piv = A[k, BW]
        if abs(piv) < 1e-300 or not math.isfinite(piv):
            return False
        for i in range(k + 1, min(n, k + BW + 1)):
            lik = A[i, k - i + BW] / piv
            if lik != 0.0:
                A[i, k - i + BW] = lik
                for j in range(k + 1, min(n, k + BW + 1)):
                    A[i, j - i + BW] -= lik * A[k, j - k + BW]
    return True


@njit(cache=True, error_model="numpy", fastmath=FASTMATH)
def band_solve(A, b):  # type: ignore[no-untyped-def]
    """Solve in place with the factors of :func:`band_lu`."""
    n = A.shape[0]
    for i in range(n):
        for k in range(max(0, i - BW), i):
            b[i] -= A[i, k - i + BW] * b[k]
    for i in range(n - 1, -1, -1):
        for j in range(i + 1, min(n, i + BW + 1)):
            b[i] -= A[i, j - i + BW] * b[j]
        b[i] /= A[i, BW]
