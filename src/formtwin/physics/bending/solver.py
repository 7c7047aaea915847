"""Incremental-iterative solver of the bending model (Numba).

The equations (the sheet's residual and band tangent, the punch row and column when the
press is compliant) are :mod:`.assembly`'s. The bordered system (banded sheet block + one
punch row and column) is solved by block elimination.

Time stepping: the history is a list of target times; between targets the step is
halved on failure (down to ``dt_min``) and doubled after a few easy steps (up to
``dt_max``). The Newton predictor extrapolates the last increment.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from formtwin.physics.bending.assembly import (
    K_SPRING,
    assemble_work,
    assembly_work,
    crank,
)
from formtwin.physics.bending.assembly import assemble as assemble
from formtwin.physics.bending.contact import face_pressure, friction_shear
from formtwin.physics.bending.faces import face_points
from formtwin.physics.bending.kernels import (
    BW,
    SQ,
    band_lu,
    band_solve,
    element_shear,
    layer_scales_all,
)

# indices into the ``opts`` array
(DT_MAX, DT_MIN, MAX_IT, TOL_R, TOL_U, CAP_U, PREDICT, LS_MAX, LS_TOL, EASY_IT, EASY_N,
 RATE_TAU, SPREAD, SHEAR, LS_ENERGY, PINCH_REACH, PINCH_P0, PINCH_P1, RATE_SPEED,
 FRICTION_SHEAR) = range(20)
# status codes
OK, FAIL_STEP = 0, 1


@njit(cache=True)
def _fix(R, Kb, col, row, free):  # type: ignore[no-untyped-def]
    """Eliminate prescribed dofs (identity rows/columns); returns the residual 2-norm."""
    n = R.shape[0]
    acc = 0.0
    for i in range(n):
        if free[i] == 0:
            R[i] = 0.0
            col[i] = 0.0
            row[i] = 0.0
            for j in range(2 * BW + 1):
                Kb[i, j] = 0.0
            for j in range(max(0, i - BW), min(n, i + BW + 1)):
                Kb[j, i - j + BW] = 0.0
            Kb[i, BW] = 1.0
        else:
            acc += R[i] * R[i]
    return math.sqrt(acc)


@njit(cache=True)
def _work(x, dp, R, g, spring):  # type: ignore[no-untyped-def]
    """``x . R + dp g``: the residual's work along the Newton direction ``(x, dp)``."""
    acc = dp * g if spring else 0.0
    for i in range(x.shape[0]):
        acc += x[i] * R[i]
    return acc


@njit(cache=True)
def newton(t, u, pa, mesh, sig, epb, eps, rate, trial,  # type: ignore[no-untyped-def]
           tools, contact, ct_trial, press, fext, free, opts, Kb, R, col, row, out, counters,
           reac, work):
    """Newton iterations with a backtracking line search at time ``t``.

    The line search halves the step until, with ``opts[LS_ENERGY]``, the work of the residual
    along the Newton direction ``|x . R(u + alpha x)|`` (the directional derivative of the
    energy) is at most ``opts[LS_TOL]`` times its value at ``alpha = 0``, or else the
    residual norm is below ``opts[LS_TOL]`` times the last one.

    Starts from the predictor in ``u, pa[0]``; ``free[i] = 0`` marks a prescribed dof
    (its value is already set in ``u``). The groups are those of :func:`.assembly.assemble`.
    ``reac (n,)`` receives the residual of the last assembly with the prescribed dofs
    kept (their reactions); ``out`` is that assembly's. ``work = (assembly, x1, x2, u0)``:
    :func:`assembly_work` and three ``(n,)`` vectors.
    Returns the number of iterations, or -1 if not converged within ``opts[MAX_IT]``.
    """
    n = u.shape[0]
    spring = press[K_SPRING] > 0.0
    aw, x1, x2, u0 = work
    assemble_work(t, u, pa[0], mesh, sig, epb, eps, rate, trial, tools, contact, ct_trial,
                  press, fext, Kb, R, col, row, out, aw)
    reac[:] = R
    norm = _fix(R, Kb, col, row, free)
    if spring:
        norm = math.sqrt(norm * norm + out[0] * out[0])
    for it in range(int(opts[MAX_IT])):
        rmax = abs(out[0]) if spring else 0.0
        for i in range(n):
            rmax = max(rmax, abs(R[i]))
        if not math.isfinite(rmax):
            return -1
        if rmax < opts[TOL_R] and it > 0:
            return it
        if not band_lu(Kb):
            return -1
        for i in range(n):
            x1[i] = -R[i]
        band_solve(Kb, x1)
        dp = 0.0
        if spring:
            for i in range(n):
                x2[i] = col[i]
            band_solve(Kb, x2)
            den = out[1]
            num = -out[0]
            for i in range(n):
                den -= row[i] * x2[i]
                num -= row[i] * x1[i]
            dp = num / den
            for i in range(n):
                x1[i] -= x2[i] * dp
        dmax = abs(dp)
        for i in range(n):
            if i % 3 != 2 and abs(x1[i]) > dmax:
                dmax = abs(x1[i])
        scale = 1.0
        if dmax > opts[CAP_U]:
            scale = opts[CAP_U] / dmax
        for i in range(n):
            u0[i] = u[i]
        p0 = pa[0]
        norm0 = norm
        energy = opts[LS_ENERGY] > 0.0
        work0 = _work(x1, dp, R, out[0], spring) if energy else 0.0
        alpha = scale
        n_ls = int(opts[LS_MAX])
        for ls in range(n_ls + 1):
            for i in range(n):
                u[i] = u0[i] + alpha * x1[i]
            pa[0] = p0 + alpha * dp
            assemble_work(t, u, pa[0], mesh, sig, epb, eps, rate, trial, tools, contact,
                          ct_trial, press, fext, Kb, R, col, row, out, aw)
            counters[3] += 1
            reac[:] = R
            norm = _fix(R, Kb, col, row, free)
            if spring:
                norm = math.sqrt(norm * norm + out[0] * out[0])
            if energy:
                accept = abs(_work(x1, dp, R, out[0], spring)) <= opts[LS_TOL] * abs(work0)
            else:
                accept = norm < opts[LS_TOL] * norm0
            if accept or ls == n_ls:
                break
            alpha *= 0.5
        if dmax * alpha < opts[TOL_U] and norm < 1e3 * opts[TOL_R]:
            return it + 1
    return -1


@njit(cache=True)
def run_history(targets, lam, lam_fix, t_start, mesh, state,  # type: ignore[no-untyped-def]
                tools, contact, loads, opts, record):
    """Advance the state and the contact state in place through ``targets``.

    Grouped arguments: ``mesh = (X, phi0, thick, ylay, wlay, xg, wg, mat)``, ``state =
    (u, pa, sig, epb, eps, rate)``, ``tools = (ptype, pdata, tstart, towner, tface, tmu, el,
    xi, pen, Xp)`` (:func:`.assembly.assemble`), ``contact = (ct_t, ct_rel, ct_act, pface, tshear,
    scales)`` (``scales`` work space, kept in step with the committed state),
    ``loads = (press, fref, fix_idx, fix_ref)``, ``record = (rec_u, rec_f, rec_r, counters)``.

    Loads are ``lam(t) * fref``, prescribed dofs ``u[fix_idx] = lam_fix(t) * fix_ref``
    (both piecewise linear through their values at ``targets``). At each
    target it records ``u`` in ``rec_u``; ``[measured force, F_v, F_lat, p, c, steps,
    iterations, cuts]`` in ``rec_f``; the residual with prescribed dofs kept (reactions) in
    ``rec_r``. ``counters = [steps, iterations, cuts, assemblies]``. Returns a status code
    (0 = converged).
    """
    X, phi0, thick = mesh[0], mesh[1], mesh[2]
    u, pa, sig, epb, eps, rate = state
    towner, tface, el, xi, Xp = tools[3], tools[4], tools[6], tools[7], tools[9]
    ct_t, ct_rel, ct_act, pface, tshear, scales = contact
    layer_scales_all(epb, tshear, mesh[7], scales)
    press, fref, fix_idx, fix_ref = loads
    rec_u, rec_f, rec_r, counters = record
    n = u.shape[0]
    n_el = X.shape[0] - 1
    n_tools = towner.shape[0]
    n_p = el.shape[0]
    sig_t = np.empty_like(sig)
    epb_t = np.empty_like(epb)
    eps_t = np.empty_like(eps)
    trial = (sig_t, epb_t, eps_t)
    ct_t_t = np.zeros((n_p, n_tools))
    ct_act_t = np.zeros((n_p, n_tools), dtype=np.int64)
    ct_trial = (ct_t_t, ct_act_t, np.zeros((n_p, n_tools)))
    Kb = np.zeros((n, 2 * BW + 1))
    R = np.zeros(n)
    col = np.zeros(n)
    row = np.zeros(n)
    out = np.zeros(5)
    reac = np.zeros(n)
    fresh = False  # whether out and reac are those of the committed state
    fext = np.zeros(n)
    free = np.ones(n, dtype=np.int64)
    for i in fix_idx:
        free[i] = 0
    u_trial = np.empty(n)
    pt = np.empty(1)
    work = (assembly_work(mesh, tools), np.zeros(n), np.zeros(n), np.zeros(n))
    tadd = np.zeros(n_el)  # the face friction's distributed moment as V/t (friction_shear)
    du_prev = np.zeros(n)
    dp_prev = 0.0
    dt_prev = 0.0
    spring = press[K_SPRING] > 0.0
    t = t_start
    dt = opts[DT_MAX]
    easy = 0
    for j in range(targets.shape[0]):
        while t < targets[j] - 1e-12:
            h = min(dt, targets[j] - t)
            tn = t + h
            lf = np.interp(tn, targets, lam)  # load factors: piecewise linear
            for i in range(n):
                fext[i] = lf * fref[i]
                u_trial[i] = u[i]
                if dt_prev > 0.0:
                    u_trial[i] += opts[PREDICT] * du_prev[i] * h / dt_prev
            lff = np.interp(tn, targets, lam_fix)
            for m in range(fix_idx.shape[0]):
                u_trial[fix_idx[m]] = lff * fix_ref[m]
            c_new, _ = crank(tn, press)
            if spring:
                if dt_prev > 0.0 and opts[PREDICT] > 0.0:
                    pt[0] = pa[0] + dp_prev * h / dt_prev
                else:
                    c_old, _ = crank(t, press)
                    pt[0] = pa[0] + (c_new - c_old)
            else:
                pt[0] = c_new
            its = newton(tn, u_trial, pt, mesh, sig, epb, eps, rate, trial, tools, contact,
                         ct_trial, press, fext, free, opts, Kb, R, col, row, out, counters,
                         reac, work)
            fresh = its >= 0
            if its < 0:
                counters[2] += 1
                dt = 0.5 * h
                easy = 0
                dt_prev = 0.0  # restart without extrapolation
                if dt < opts[DT_MIN]:
                    return FAIL_STEP
                continue
            counters[0] += 1
            counters[1] += its
            # commit
            # equivalent strain rate of each layer point: the increment's rate, smoothed
            # over the time constant opts[RATE_TAU] (0: the last increment's rate)
            # (opts[RATE_SPEED] > 0: the uniform rate of the ram speed, CalculiX's rate law)
            wr = h / (h + opts[RATE_TAU])
            r_ram = opts[RATE_SPEED] * abs(crank(tn, press)[1])
            for e in range(n_el):
                for g in range(sig.shape[1]):
                    for k in range(sig.shape[2]):
                        r_new = r_ram
                        if opts[RATE_SPEED] <= 0.0:
                            r_new = 2.0 / math.sqrt(3.0) * abs(eps_t[e, g, k] - eps[e, g, k]) / h
                        rate[e, g, k] += wr * (r_new - rate[e, g, k])
                        sig[e, g, k] = sig_t[e, g, k]
                        epb[e, g, k] = epb_t[e, g, k]
                        eps[e, g, k] = eps_t[e, g, k]
            if opts[SPREAD] > 0.0:  # face pressures for the next increment
                face_pressure(X, Xp, ct_trial[2], tface, opts[SPREAD] * thick, pface, towner)
            if opts[SHEAR] > 0.0:  # the elements' shear stresses for the next increment
                ys = SQ * mesh[7][1]  # plane-strain yield stress
                if opts[FRICTION_SHEAR] > 0.0:
                    friction_shear(X, el, xi, ct_trial[0], tadd)
                element_shear(X, sig, thick, mesh[3], mesh[4], mesh[5], tshear, pface,
                              opts[PINCH_REACH] * thick, opts[PINCH_P0] * ys,
                              opts[PINCH_P1] * ys, tadd)
            # the layers' yield factors of the committed state, for the next increment
            layer_scales_all(epb, tshear, mesh[7], scales)
            for q in range(el.shape[0]):
                for k in range(n_tools):
                    ct_act[q, k] = ct_act_t[q, k]
                    ct_t[q, k] = ct_t_t[q, k]
            # the points' face positions in the tools' frames
            face_points(X, phi0, u_trial, el, xi, tface, towner, 0.5 * thick, pt[0], ct_rel)
            for i in range(n):
                du_prev[i] = u_trial[i] - u[i]
                u[i] = u_trial[i]
            dp_prev = pt[0] - pa[0]
            pa[0] = pt[0]
            dt_prev = h
            t = tn
            easy = easy + 1 if its <= opts[EASY_IT] else 0
            if easy >= opts[EASY_N]:
                dt = min(2.0 * dt, opts[DT_MAX])
                easy = 0
        # record the forces and reactions of the converged state: those of the last Newton
        # assembly (assemble only if no step was taken since the last record)
        if not fresh:
            assemble_work(t, u, pa[0], mesh, sig, epb, eps, rate, trial, tools, contact,
                          ct_trial, press, fext, Kb, R, col, row, out, work[0])
            reac[:] = R
            fresh = True
        for i in range(n):
            rec_u[j, i] = u[i]
            rec_r[j, i] = reac[i]
        c_now, _ = crank(t, press)
        rec_f[j, 0] = out[4]
        rec_f[j, 1] = out[2]
        rec_f[j, 2] = out[3]
        rec_f[j, 3] = pa[0]
        rec_f[j, 4] = c_now
        for m in range(3):
            rec_f[j, 5 + m] = counters[m]
    return OK
