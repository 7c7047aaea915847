"""Contact of the sheet's faces with rigid tools (Numba kernels).

Contact points
    Penalty contact acts at points on the sheet's faces: at the nodes and at
    ``n_sub - 1`` points inside each element (``contact_points`` of the discretisation).
    A point at ``xi`` in element ``e`` (nodes ``a = e``, ``b = e + 1``) lies ``s t/2``
    along the normal ``n = (-sin, cos)`` of the direction ``(1 - xi) phi_a + xi phi_b``
    from the cubic Hermite mid-surface ``H1 x_a + H2 L0 t(phi_a) + H3 x_b + H4 L0 t(phi_b)``
    (:func:`.faces.hermite_face`), where ``phi_i`` is the node's direction, ``t = (cos, sin)``,
    ``s = +-1`` the face and ``L0`` the element's reference length. Points at the nodes (``xi = 0``)
    are the node's face point, as in a node-to-surface scheme; the inner points let a tool
    corner (a nose of a few element lengths) slide along the sheet without the force
    jumping from node to node, which made the final angle saw-toothed in the stage-2
    setting with a period of one element. Each point's penalty is the penalty per length
    times its share of the sheet (trapezoidal).

Each point's force ``F`` acts on its element's six dofs as ``B^T F`` with
``B = dy/d(u_a, v_a, theta_a, u_b, v_b, theta_b)``; the tangent is ``B^T J B`` plus
``F . d^2 y / d theta_i d theta_j`` on the rotations (``J = dF/dy`` of :func:`contact_node`).
Node-to-rigid-surface penalty contact with Coulomb friction by an elastic-predictor /
slip-corrector return map on the tangential force, consistent tangent (including the
rotation of the normal on arcs).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from formtwin.physics.bending.faces import element_lengths, node_point_trig, point_face_trig
from formtwin.physics.bending.kernels import BW, FASTMATH

#: margin (mm) by which a primitive's lower bound of the distance must exceed the best
#: distance for :func:`closest_point` to skip it: far above the roundoff of the bounds
#: (~1e-15 mm at the tools' coordinates), so a skipped primitive could never have won
SKIP_MARGIN = 1e-9


@njit(cache=True, error_model="numpy", fastmath=FASTMATH)
def primitive_frames(ptype, pdata):  # type: ignore[no-untyped-def]
    """Per primitive ``(n_p, 4)``: a segment's unit tangent and length ``(tx, ty, L, 0)``, an
    arc's end directions ``(cos a0, sin a0, cos a1, sin a1)`` (for :func:`closest_point`)."""
    pre = np.zeros((ptype.shape[0], 4))
    for j in range(ptype.shape[0]):
        if ptype[j] == 0:
            tx, ty = pdata[j, 2] - pdata[j, 0], pdata[j, 3] - pdata[j, 1]
            L = math.sqrt(tx * tx + ty * ty)
            pre[j, 0], pre[j, 1], pre[j, 2] = tx / L, ty / L, L
        else:
            pre[j, 0], pre[j, 1] = math.cos(pdata[j, 3]), math.sin(pdata[j, 3])
            pre[j, 2], pre[j, 3] = math.cos(pdata[j, 4]), math.sin(pdata[j, 4])
    return pre


@njit(cache=True, error_model="numpy", fastmath=FASTMATH, inline="always")
def closest_point(px, py, p0, p1, ptype, pdata, pre):  # type: ignore[no-untyped-def]
    """Closest point of a tool (primitives ``p0:p1``) to ``(px, py)`` (tool frame).

    Returns ``(distance, signed_distance, nx, ny, rho)`` with the outward normal at the
    closest point and ``rho`` the distance to the arc centre (0 for a straight face).
    Segments have the tool on their right; arcs are convex corners (tool inside, spanning
    less than 180 deg). ``pre`` from :func:`primitive_frames`.

    A primitive whose cheap lower bound of the distance (the distance to a segment's line or
    beyond its ends; to an arc's circle, from the squared radius) exceeds the best distance
    so far by :data:`SKIP_MARGIN` cannot be the closest and is not evaluated further: the
    same result as evaluating it (its distance would not be below the best), fewer
    ``hypot`` calls. The bound it must beat is the smaller of the best so far and a cheap
    upper bound of the distance taken first (:func:`distance_above`), so that the
    primitives before the nearest one are skipped too.
    """
    best = 1e300
    sd = 0.0
    bnx = 0.0
    bny = 0.0
    brho = 0.0
    above = distance_above(px, py, p0, p1, ptype, pdata, pre)
    for j in range(p0, p1):
        lim = min(best, above)
        if ptype[j] == 0:
            x0, y0 = pdata[j, 0], pdata[j, 1]
            tx, ty, L = pre[j, 0], pre[j, 1], pre[j, 2]
            nx, ny = -ty, tx
            sp = (px - x0) * tx + (py - y0) * ty
            sgn = (px - x0) * nx + (py - y0) * ny
            if max(abs(sgn), -sp, sp - L) > lim + SKIP_MARGIN:
                continue
            spc = min(max(sp, 0.0), L)
            qx, qy = x0 + spc * tx, y0 + spc * ty
            dist = math.hypot(px - qx, py - qy)
            rho = 0.0
        else:
            cx, cy, R = pdata[j, 0], pdata[j, 1], pdata[j, 2]
            c0, s0, c1, s1 = pre[j, 0], pre[j, 1], pre[j, 2], pre[j, 3]
            rx, ry = px - cx, py - cy
            r2 = rx * rx + ry * ry  # |rho - R| <= dist: skip if rho > R + best or < R - best
            outer = R + lim + SKIP_MARGIN
            inner = R - lim - SKIP_MARGIN
            if r2 > outer * outer or (inner > 0.0 and r2 < inner * inner):
                continue
            rho = math.hypot(rx, ry)
            if c0 * ry - s0 * rx >= 0.0 and rx * s1 - ry * c1 >= 0.0 and rho > 0.0:
                nx, ny = rx / rho, ry / rho
                sgn = rho - R
                dist = abs(sgn)
            else:  # the nearer end (in angle)
                if rx * c0 + ry * s0 > rx * c1 + ry * s1:
                    nx, ny = c0, s0
                else:
                    nx, ny = c1, s1
                qx, qy = cx + R * nx, cy + R * ny
                dist = math.hypot(px - qx, py - qy)
                sgn = (px - qx) * nx + (py - qy) * ny
                rho = 0.0
        if dist < best:
            best = dist
            sd = sgn
            bnx, bny, brho = nx, ny, rho
    return best, sd, bnx, bny, brho


@njit(cache=True, error_model="numpy", fastmath=FASTMATH, inline="always")
def distance_above(px, py, p0, p1, ptype, pdata, pre):  # type: ignore[no-untyped-def]
    """An upper bound (mm) of the distance of ``(px, py)`` to a tool (primitives ``p0:p1``,
    tool frame) without a square root: the least over its primitives of a segment's
    ``|normal offset| + distance beyond its ends along it`` and an arc's first end point's
    distance ``|dx| + |dy|`` (both at least the distance, above it by far more than
    :data:`SKIP_MARGIN` where not equal). ``pre`` from :func:`primitive_frames`.
    """
    above = 1e300
    for j in range(p0, p1):
        if ptype[j] == 0:
            x0, y0 = pdata[j, 0], pdata[j, 1]
            tx, ty, L = pre[j, 0], pre[j, 1], pre[j, 2]
            sp = (px - x0) * tx + (py - y0) * ty
            b = abs((py - y0) * tx - (px - x0) * ty) + max(0.0, -sp, sp - L)
        else:
            R = pdata[j, 2]
            b = abs(px - pdata[j, 0] - R * pre[j, 0]) + abs(py - pdata[j, 1] - R * pre[j, 1])
        above = min(above, b)
    return above


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


@njit(cache=True, error_model="numpy", fastmath=FASTMATH)
def face_pressure(X, Xp, fn, tface, a, pface, towner=None):  # type: ignore[no-untyped-def]
    """Contact pressure (MPa) on the lower and upper face at each node, ``pface (n, 2)``.

    The normal contact forces of the contact points ``fn (n_points, n_tools)`` (N/mm, per
    mm width) at the reference positions ``Xp (n_points, 2)``, on the faces ``tface
    (n_tools,)`` (+1 upper, -1 lower), spread along the sheet by a hat of half-width ``a``
    (mm; a load on a face spreads through the thickness over about the thickness), so the
    pressure at the nodes ``X (n_nodes, 2)`` is independent of the point spacing.
    With ``pface (n, 3)`` and ``towner (n_tools,)`` the third column takes the pressure of
    the tools that move with the punch (``towner == 1``) alone (MPa, either face).
    A node farther than ``a`` along either axis is passed over without its distance (by a
    relative margin of 1e-12, far above the distance's roundoff: it would add nothing).
    """
    n = X.shape[0]
    pface[:, :] = 0.0
    far = a * (1.0 + 1e-12)
    for j in range(Xp.shape[0]):
        for k in range(tface.shape[0]):
            if fn[j, k] == 0.0:
                continue
            side = 1 if tface[k] > 0.0 else 0
            for i in range(n):
                dx = X[i, 0] - Xp[j, 0]
                dy = X[i, 1] - Xp[j, 1]
                if max(abs(dx), abs(dy)) > far:
                    continue
                d = math.hypot(dx, dy)
                if d < a:
                    pface[i, side] += fn[j, k] * (1.0 - d / a) / a
                    if towner is not None and pface.shape[1] > 2 and towner[k] == 1:
                        pface[i, 2] += fn[j, k] * (1.0 - d / a) / a


@njit(cache=True, error_model="numpy", fastmath=FASTMATH)
def friction_shear(X, el, xi, tt, tadd):  # type: ignore[no-untyped-def]
    """Correction (MPa) of each element's ``dM/ds / t`` for the face friction, ``tadd (n_el,)``.

    A tangential contact force ``F_t`` on a face (+-t/2) is an axial force plus a moment
    ``m = -(t/2) tt`` (counter-clockwise) about the mid-surface, whatever the face, with ``tt``
    the committed tangential force along the tool's ``tau = (-n_y, n_x)`` (:func:`contact_node`;
    ``tt (n_points, n_tools)``, N/mm). A beam's moment balance is ``dM/ds = -V - m`` (``m`` per
    length): the section's transverse shear force ``V`` is ``-(dM/ds + m)``, so the elements'
    ``dM/ds / t`` (:func:`.kernels.element_shear`, which stands for ``-V/t``) takes
    ``m/t = -sum(tt) / (2 L)`` over the element's points (a point at a node half to each of its
    elements). A strip dragged over a die has ``dM/ds = 0`` but a mean shear stress of half the
    friction traction, as in a continuum (``tau_xy`` = traction on the face, 0 on the other).
    """
    n_el = X.shape[0] - 1
    tadd[:] = 0.0
    for q in range(el.shape[0]):
        s = 0.0
        for k in range(tt.shape[1]):
            s += tt[q, k]
        if s == 0.0:
            continue
        e = el[q]
        if xi[q] == 0.0 and e > 0:  # a node's point: half to each element
            tadd[e - 1] += 0.5 * s
            tadd[e] += 0.5 * s
        else:
            tadd[min(e, n_el - 1)] += s
    for e in range(n_el):
        tadd[e] *= -0.5 / math.hypot(X[e + 1, 0] - X[e, 0], X[e + 1, 1] - X[e, 1])


@njit(cache=True, error_model="numpy", fastmath=FASTMATH)
def contact_forces(p, u, X, phi0, thick, points, tools, contact,  # type: ignore[no-untyped-def]
                   ct_trial, g0, Kb, R, col, Jp):
    """Add the contact forces of all points to ``R`` (as ``-B^T F``) and their tangent to the
    band ``Kb``; ``col += dR/dp`` and ``Jp (n_nodes, 2, 3) += dF/du`` of the punch's tools.

    ``points = (el, xi, pen (n_p, 2))``, ``tools = (ptype, pdata, tstart, towner, tface, tmu)``,
    ``contact = (ct_t, ct_rel, ct_act)`` committed, ``ct_trial = (ct_t_t, ct_act_t, ct_n_t)``
    written. Returns the punch's ``(F_v, F_lat)``. :func:`contact_forces_work` with a work
    space of its own (:func:`contact_work`).
    """
    work = contact_work(X, thick, points[0].shape[0], tools[0], tools[1], tools[3].shape[0])
    return contact_forces_work(p, u, X, phi0, thick, points, tools, contact, ct_trial, g0, Kb,
                               R, col, Jp, work)


@njit(cache=True, error_model="numpy", fastmath=FASTMATH)
def contact_work(X, thick, n_p, ptype, pdata, n_tools):  # type: ignore[no-untyped-def]
    """Work space of :func:`contact_forces_work` for a sheet ``X (n_nodes, 2)`` of thickness
    ``thick`` with ``n_p`` contact points and a tool set of ``n_tools`` tools.

    ``(pre, L0s, near, trig, dnode, dref, qref, J, d, B, JB)``: the primitives' frames
    (:func:`primitive_frames`), the elements' reference lengths, each node's least and
    largest threshold ``2 L0 + 1.5 t`` of its elements ``near (n_nodes, 2)``, the cosines
    and sines of :func:`.faces.face_trig`, the nodes' distances to a tool, the last
    computed distance of each node to each tool and the node's position in the tool's
    frame then (``dref = NaN``: none yet), and the small matrices.
    """
    n_nodes = X.shape[0]
    L0s = element_lengths(X)
    near = np.empty((n_nodes, 2))
    near[:, 0] = np.inf
    near[:, 1] = -np.inf
    for e in range(n_nodes - 1):
        lim = 2.0 * L0s[e] + 1.5 * thick
        for i in (e, e + 1):
            near[i, 0] = min(near[i, 0], lim)
            near[i, 1] = max(near[i, 1], lim)
    dref = np.full((n_nodes, n_tools), np.nan)
    return (primitive_frames(ptype, pdata), L0s, near, np.empty((n_nodes + n_p, 2)),
            np.empty(n_nodes), dref, np.zeros((n_nodes, n_tools, 2)), np.zeros((2, 2)),
            np.zeros((5, 2)), np.zeros((2, 6)), np.zeros((2, 6)))


@njit(cache=True, error_model="numpy", fastmath=FASTMATH)
def contact_forces_work(p, u, X, phi0, thick, points, tools,  # type: ignore[no-untyped-def]
                        contact, ct_trial, g0, Kb, R, col, Jp, work):
    """:func:`contact_forces` with the work space ``work`` of :func:`contact_work` (made once
    per solve: the tools' frames and the elements' lengths are those of the run).

    The nodes' distances to a tool only decide which elements cannot hold a contact point
    (both nodes farther than the element's threshold). The distance being 1-Lipschitz in
    the node's position, a node whose last computed distance ``dref``, less how far it
    moved since (``m = |dx| + |dy|`` in the tool's frame), still exceeds the largest
    threshold of its elements by :data:`SKIP_MARGIN` is farther than them now too; one
    whose ``dref + m`` is below their least threshold by that margin is nearer. Neither's
    distance is computed again: each element is skipped or not as with every distance
    computed (the margin is far above the distances' roundoff).
    """
    el, xi, pen = points
    ptype, pdata, tstart, towner, tface, tmu = tools
    ct_t, ct_rel, ct_act = contact
    ct_t_t, ct_act_t, ct_n_t = ct_trial
    pre, L0s, near, trig, dnode, dref, qref, J, d, B, JB = work
    fv = 0.0
    flat = 0.0
    half = 0.5 * thick
    n_nodes = X.shape[0]
    # cos, sin of the nodes' and the points' directions: once, not once per tool
    node_point_trig(X, phi0, u, el, xi, trig)
    for k in range(towner.shape[0]):
        ty = p if towner[k] == 1 else 0.0
        s = tface[k]
        for i in range(n_nodes):  # the nodes' distances to the tool, to skip far elements
            qx = X[i, 0] + u[3 * i]
            qy = X[i, 1] + u[3 * i + 1] - ty
            moved = abs(qx - qref[i, k, 0]) + abs(qy - qref[i, k, 1])
            if dref[i, k] - moved > near[i, 1] + SKIP_MARGIN:
                dnode[i] = dref[i, k] - moved  # above both thresholds
                continue
            if dref[i, k] + moved < near[i, 0] - SKIP_MARGIN:
                dnode[i] = dref[i, k] + moved  # below both
                continue
            dnode[i] = closest_point(qx, qy, tstart[k], tstart[k + 1], ptype, pdata, pre)[0]
            dref[i, k] = dnode[i]
            qref[i, k, 0] = qx
            qref[i, k, 1] = qy
        for q in range(el.shape[0]):
            ct_act_t[q, k] = 0
            ct_t_t[q, k] = 0.0
            ct_n_t[q, k] = 0.0
            e = el[q]
            i0 = 3 * e
            L0 = L0s[e]
            # a point lies within 1.5 L0 + t/2 of its element's nodes (Hermite weights
            # |H2|, |H4| <= 4/27; stretch allowed for), and a contact needs |gap| <= t: the
            # tool's distance being 1-Lipschitz, an element whose nodes are both farther
            # than 2 L0 + 1.5 t from it has no contact point on it
            if min(dnode[e], dnode[e + 1]) > 2.0 * L0 + 1.5 * thick:
                continue
            px, py = point_face_trig(X, u, el, xi, q, s, half, L0s, trig, d)
            py -= ty
            dist, gap, nx, ny, rho = closest_point(px, py, tstart[k], tstart[k + 1], ptype,
                                                   pdata, pre)
            if gap >= 0.0 or gap < -thick:
                continue
            tt_n = ct_t[q, k] if ct_act[q, k] == 1 else 0.0
            fx, fy, tt, slip = contact_node(gap, g0, nx, ny, rho, pen[q, 0], pen[q, 1],
                                            tmu[k], tt_n, px - ct_rel[q, k, 0],
                                            py - ct_rel[q, k, 1], J)
            ct_act_t[q, k] = 1
            ct_t_t[q, k] = tt
            ct_n_t[q, k] = fx * nx + fy * ny
            H3 = 3.0 * xi[q] * xi[q] - 2.0 * xi[q] ** 3
            B[:, :] = 0.0
            B[0, 0] = B[1, 1] = 1.0 - H3
            B[0, 3] = B[1, 4] = H3
            B[0, 2], B[1, 2] = d[0, 0], d[0, 1]
            B[0, 5], B[1, 5] = d[1, 0], d[1, 1]
            for a in range(2):
                for b in range(6):
                    JB[a, b] = J[a, 0] * B[0, b] + J[a, 1] * B[1, b]
            for a in range(6):
                R[i0 + a] -= B[0, a] * fx + B[1, a] * fy
                for b in range(6):
                    Kb[i0 + a, b - a + BW] -= B[0, a] * JB[0, b] + B[1, a] * JB[1, b]
            Kb[i0 + 2, BW] -= fx * d[2, 0] + fy * d[2, 1]
            Kb[i0 + 5, BW] -= fx * d[3, 0] + fy * d[3, 1]
            Kb[i0 + 2, 3 + BW] -= fx * d[4, 0] + fy * d[4, 1]
            Kb[i0 + 5, -3 + BW] -= fx * d[4, 0] + fy * d[4, 1]
            if towner[k] == 1:
                fv -= fy
                flat -= fx
                for a in range(6):
                    col[i0 + a] += B[0, a] * J[0, 1] + B[1, a] * J[1, 1]
                for a in range(2):
                    for b in range(3):
                        Jp[e, a, b] += JB[a, b]
                        Jp[e + 1, a, b] += JB[a, 3 + b]
    return fv, flat
