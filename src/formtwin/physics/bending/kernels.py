"""Numba kernels of the bending model: material point, corotational beam, contact, band LU.

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
    about a thickness (:func:`face_pressure`). In plane strain with incompressible flow the
    yield condition becomes ``|sigma_xx - sigma_yy| = (2/sqrt 3) sigma_flow``: a sheet pressed
    onto a tool yields at a shifted axial stress, which a plain beam misses.

Contact
    Node-to-rigid-surface penalty contact with the sheet surface offset ``t/2`` from the
    mid-surface node, Coulomb friction by an elastic-predictor / slip-corrector return map
    on the tangential force, consistent tangent (including the rotation of the normal on
    arcs).
"""

from __future__ import annotations

import math

from numba import njit

from formtwin.physics.bending.material import HARD_EPS, HARD_RATIO

SQ = 2.0 / math.sqrt(3.0)  # plane-strain factor between sigma_xx and the von Mises stress
BW = 5  # semi-bandwidth of the stiffness of a chain of 3-dof nodes
#: fast-math flags that keep NaN/inf semantics (failed runs must still be detected)
FASTMATH = {"nsz", "arcp", "contract", "afn", "reassoc"}

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
    slope = (HARD_RATIO[i + 1] - HARD_RATIO[i]) / (HARD_EPS[i + 1] - HARD_EPS[i])
    r = HARD_RATIO[i] + slope * (eb - HARD_EPS[i])
    return 1.0 + hard * (r - 1.0), hard * slope


@njit(cache=True, error_model="numpy", fastmath=FASTMATH)
def layer_update(de, sig_n, epb_n, rate_n, E, sy, e0, q, hard,  # type: ignore[no-untyped-def]
                 syy=0.0):
    """Return map of one layer point.

    ``E`` plane-strain modulus, ``sy`` yield stress (MPa), ``e0, q`` Cowper-Symonds
    constants, ``hard`` hardening switch (1 tabulated, 0 perfectly plastic); ``de`` the
    axial strain increment, ``rate_n`` the lagged equivalent strain rate (1/s); ``syy``
    the through-thickness stress (MPa, <= 0 under contact pressure), which shifts the
    yield condition to ``|sigma - syy| = (2/sqrt 3) sigma_flow``.
    Returns ``(sigma, eps_bar, E_tangent)``.
    """
    sig_tr = sig_n + E * de - syy  # the stress difference that yields
    a = abs(sig_tr)
    r = 1.0
    if epb_n > 0.0:
        r, h = hardening(epb_n, hard)
    if a <= SQ * sy * r:  # inside the rate-free (smallest) yield surface
        return sig_tr + syy, epb_n, E
    rf = 1.0
    if rate_n > 0.0:
        rf = 1.0 + (rate_n / e0) ** q
    s0 = SQ * rf * sy
    if a - s0 * r <= 0.0:
        return sig_tr + syy, epb_n, E
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
    return sig, epb_n + SQ * dg, E * H / (E + H)


# -------------------------------------------------------------------------------- beam


@njit(cache=True, error_model="numpy", fastmath=FASTMATH)
def beam_element(e, X, u, thick, ylay, wlay, xg, wg, mat,  # type: ignore[no-untyped-def]
                 sig, epb, eps, rate, sig_t, epb_t, eps_t, f, K, B, pface):
    """Internal force ``f (6,)`` and tangent ``K (6, 6)`` of element ``e`` (nodes e, e+1).

    Reads the committed layer state ``sig, epb, eps, rate [e]`` and writes the trial state
    into ``sig_t, epb_t, eps_t [e]``; ``B (3, 6)`` is work space; ``pface (n_nodes, 2)``
    the contact pressures (MPa) on the lower and upper face, interpolated linearly along
    the element, give each layer its through-thickness stress.
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
            sg, eb, et = layer_update(ek - eps[e, g, k], sig[e, g, k], epb[e, g, k],
                                      rate[e, g, k], E, sy, e0, q, hard, syy)
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
def face_pressure(X, fn, tface, a, pface):  # type: ignore[no-untyped-def]
    """Contact pressure (MPa) on the lower and upper face at each node, ``pface (n, 2)``.

    The normal contact forces of the nodes ``fn (n_nodes, n_tools)`` (N/mm, per mm width)
    on the faces ``tface (n_tools,)`` (+1 upper, -1 lower), spread along the sheet by a
    hat of half-width ``a`` (mm; a load on a face spreads through the thickness over about
    the thickness), so the pressure is independent of the node spacing ``X (n_nodes, 2)``.
    """
    n = X.shape[0]
    pface[:, :] = 0.0
    for j in range(n):
        for k in range(tface.shape[0]):
            if fn[j, k] == 0.0:
                continue
            side = 1 if tface[k] > 0.0 else 0
            for i in range(n):
                d = math.hypot(X[i, 0] - X[j, 0], X[i, 1] - X[j, 1])
                if d < a:
                    pface[i, side] += fn[j, k] * (1.0 - d / a) / a


# ----------------------------------------------------------------------------- contact


@njit(cache=True, error_model="numpy", fastmath=FASTMATH, inline="always")
def closest_point(px, py, p0, p1, ptype, pdata):  # type: ignore[no-untyped-def]
    """Closest point of a tool (primitives ``p0:p1``) to ``(px, py)`` (tool frame).

    Returns ``(distance, signed_distance, nx, ny, rho)`` with the outward normal at the
    closest point and ``rho`` the distance to the arc centre (0 for a straight face).
    Segments have the tool on their right; arcs are convex corners (tool inside).
    """
    best = 1e300
    sd = 0.0
    bnx = 0.0
    bny = 0.0
    brho = 0.0
    for j in range(p0, p1):
        if ptype[j] == 0:
            x0, y0, x1, y1 = pdata[j, 0], pdata[j, 1], pdata[j, 2], pdata[j, 3]
            tx, ty = x1 - x0, y1 - y0
            L = math.sqrt(tx * tx + ty * ty)
            tx /= L
            ty /= L
            nx, ny = -ty, tx
            sp = (px - x0) * tx + (py - y0) * ty
            spc = min(max(sp, 0.0), L)
            qx, qy = x0 + spc * tx, y0 + spc * ty
            dist = math.hypot(px - qx, py - qy)
            sgn = (px - x0) * nx + (py - y0) * ny
            rho = 0.0
        else:
            cx, cy, R, a0, a1 = pdata[j, 0], pdata[j, 1], pdata[j, 2], pdata[j, 3], pdata[j, 4]
            rx, ry = px - cx, py - cy
            rho = math.hypot(rx, ry)
            ang = (math.atan2(ry, rx) - a0) % (2.0 * math.pi)
            if ang <= a1 - a0 and rho > 0.0:
                nx, ny = rx / rho, ry / rho
                sgn = rho - R
                dist = abs(sgn)
            else:
                aa = a0 if ang > 0.5 * (a1 - a0) + math.pi else a1
                qx, qy = cx + R * math.cos(aa), cy + R * math.sin(aa)
                nx, ny = math.cos(aa), math.sin(aa)
                dist = math.hypot(px - qx, py - qy)
                sgn = (px - qx) * nx + (py - qy) * ny
                rho = 0.0
        if dist < best:
            best = dist
            sd = sgn
            bnx, bny, brho = nx, ny, rho
    return best, sd, bnx, bny, brho


@njit(cache=True, error_model="numpy", fastmath=FASTMATH, inline="always")
def contact_node(gap, g0, nx, ny, rho, epn, ept, mu, tt_n, drx, dry, J):  # type: ignore[no-untyped-def]
    """Penalty contact force on a node and its derivative ``J = df/d(x_node - x_tool)``.

    ``gap < 0`` is the penetration; the normal force is ``epn (-gap - g0/2)`` beyond
    ``g0`` and quadratic ``epn gap^2 / (2 g0)`` within it (continuous stiffness at first
    touch). ``(drx, dry)`` is the relative displacement of the node against the tool since
    the last converged state, ``tt_n`` the committed tangential force along
    ``tau = (-ny, nx)``. Returns ``(fx, fy, tt, slip)``.
    """
    if gap < -g0:
        lam = -epn * (gap + 0.5 * g0)
        kn = epn
    else:
        lam = epn * gap * gap / (2.0 * g0)
        kn = -epn * gap / g0
    tx, ty = -ny, nx
    ds = tx * drx + ty * dry
    tt = tt_n - ept * ds
    cap = mu * lam
    slip = abs(tt) > cap
    if slip:
        tt = math.copysign(cap, tt)
    nn = (nx, ny)
    ta = (tx, ty)
    for a in range(2):
        for b in range(2):
            v = -kn * nn[a] * nn[b]
            if rho > 0.0:
                v += (lam * ta[a] * ta[b] - tt * nn[a] * ta[b]) / rho
            if slip:
                v -= mu * math.copysign(1.0, tt) * kn * ta[a] * nn[b]
            else:
                v -= ept * ta[a] * ta[b]
            J[a, b] = v
    return lam * nx + tt * tx, lam * ny + tt * ty, tt, slip


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
