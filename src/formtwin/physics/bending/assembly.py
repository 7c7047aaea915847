"""Assembly of the bending model's equations (Numba): residual, band tangent, punch row.

Unknowns: the nodal ``(u_x, u_y, theta)`` of the sheet (a chain of beam elements) and,
when the press is compliant, the punch position ``p`` (the translation of the tools owned
by the punch). The crank prescribes the ram position ``c(t)``; the press frame is a spring
``k`` between ram and punch, so the punch equilibrium reads

    G = k (p - c) - F_v - s mu_tt |F_lat| = 0,

with ``F_v, F_lat`` the vertical and lateral forces of the sheet on the punch and
``s = -tanh(c'(t) / v_eps)`` the direction of the guide friction (+1 moving down). The
sensor measures the spring force ``k (p - c)``. With ``k <= 0`` the punch follows the
crank exactly. :mod:`.solver` solves the bordered system (banded sheet block + one punch
row and column) by block elimination.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from formtwin.physics.bending.contact import contact_forces_work, contact_work
from formtwin.physics.bending.kernels import BW, beam_element

# indices into the ``press`` array
K_SPRING, MU_TT, V_EPS, CR_R, CR_L, CR_W, G0 = range(7)


@njit(cache=True)
def crank(t, press):  # type: ignore[no-untyped-def]
    """Ram height above bottom dead centre ``c(t)`` (mm) and its speed (mm/s)."""
    R, L, w = press[CR_R], press[CR_L], press[CR_W]
    a = w * t
    sa, ca = math.sin(a), math.cos(a)
    root = math.sqrt(L * L - R * R * sa * sa)
    return R * (1.0 - ca) + L - root, R * w * sa + R * R * w * sa * ca / root


@njit(cache=True)
def assemble(t, u, p, mesh, sig, epb, eps, rate, trial,  # type: ignore[no-untyped-def]
             tools, contact, ct_trial, press, fext, Kb, R, col, row, out):
    """:func:`assemble_work` with a work space of its own (:func:`assembly_work`)."""
    assemble_work(t, u, p, mesh, sig, epb, eps, rate, trial, tools, contact, ct_trial, press,
                  fext, Kb, R, col, row, out, assembly_work(mesh, tools))


@njit(cache=True)
def assembly_work(mesh, tools):  # type: ignore[no-untyped-def]
    """Work space of :func:`assemble_work`: an element's force, tangent and ``B`` matrix,
    the punch row's ``dF/du`` per node, and :func:`.contact.contact_work`."""
    X, thick = mesh[0], mesh[2]
    return (np.zeros(6), np.zeros((6, 6)), np.zeros((3, 6)), np.zeros((X.shape[0], 2, 3)),
            contact_work(X, thick, tools[6].shape[0], tools[0], tools[1], tools[3].shape[0]))


@njit(cache=True)
def assemble_work(t, u, p, mesh, sig, epb, eps, rate, trial,  # type: ignore[no-untyped-def]
                  tools, contact, ct_trial, press, fext, Kb, R, col, row, out, work):
    """Residual ``R = f_int - f_contact - f_ext`` and band tangent ``Kb``.

    ``mesh = (X, phi0, thick, ylay, wlay, xg, wg, mat)``, ``trial = (sig_t, epb_t, eps_t)``
    (written), ``tools = (ptype, pdata, tstart, towner, tface, tmu, el, xi, pen, Xp)``: the
    tools and the contact points (element, ``xi``, penalties, reference positions;
    :mod:`.contact`), ``contact = (ct_t, ct_rel, ct_act, pface, tshear, scales)``
    (per point and tool, committed; ``pface`` the face pressures at the nodes, MPa;
    ``tshear`` the elements' mean shear stresses, MPa; ``scales`` the layers' yield factors
    of the committed state, :func:`.kernels.layer_scales_all`),
    ``ct_trial = (ct_t_t, ct_act_t, ct_n_t)`` (written; ``ct_n_t`` normal forces, N/mm).
    Contact acts at points on the sheet's faces (:func:`.contact.contact_forces`), so the
    normal and friction forces also load the nodes' rotations.
    ``col = dR/dp``, ``row = dG/du``; ``out = [G, dG/dp, F_v, F_lat, spring/measured force]``;
    ``work`` from :func:`assembly_work` (made once per solve).
    """
    X, phi0, thick, ylay, wlay, xg, wg, mat = mesh
    sig_t, epb_t, eps_t = trial
    ptype, pdata, tstart, towner, tface, tmu, el, xi, pen = tools[:9]
    pface, tshear, scales = contact[3], contact[4], contact[5]
    n_dof = u.shape[0]
    n_el = X.shape[0] - 1
    Kb[:, :] = 0.0
    col[:] = 0.0
    row[:] = 0.0
    for i in range(n_dof):
        R[i] = -fext[i]
    fe, Ke, Bw, Jp = work[:4]
    for e in range(n_el):
        beam_element(e, X, u, thick, ylay, wlay, xg, wg, mat,
                     sig, epb, eps, rate, sig_t, epb_t, eps_t, fe, Ke, Bw, pface, tshear,
                     scales)
        i0 = 3 * e
        for a in range(6):
            R[i0 + a] += fe[a]
            for b in range(6):
                Kb[i0 + a, b - a + BW] += Ke[a, b]
    n_nodes = X.shape[0]
    Jp[:, :, :] = 0.0
    fv, flat = contact_forces_work(p, u, X, phi0, thick, (el, xi, pen),
                                   (ptype, pdata, tstart, towner, tface, tmu), contact[:3],
                                   ct_trial, press[G0], Kb, R, col, Jp, work[4])
    c, v = crank(t, press)
    sdir = -math.tanh(v / press[V_EPS])
    mtt = sdir * press[MU_TT] * (1.0 if flat >= 0.0 else -1.0)
    dgdp = press[K_SPRING]
    for nd in range(n_nodes):
        for b in range(3):
            row[3 * nd + b] = Jp[nd, 1, b] + mtt * Jp[nd, 0, b]
        dgdp -= Jp[nd, 1, 1] + mtt * Jp[nd, 0, 1]
    meas = fv + sdir * press[MU_TT] * abs(flat)
    out[0] = press[K_SPRING] * (p - c) - meas
    out[1] = dgdp
    out[2] = fv
    out[3] = flat
    out[4] = press[K_SPRING] * (p - c) if press[K_SPRING] > 0.0 else meas
