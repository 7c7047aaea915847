"""Verification of the bending model's beam, material and contact against known answers."""

from __future__ import annotations

import math

import numpy as np
import pytest

pytest.importorskip("numba")

from formtwin.physics.bending.geometry import make_toolset  # noqa: E402
from formtwin.physics.bending.material import Material  # noqa: E402
from formtwin.physics.bending.model import Discretisation, Sheet, solve  # noqa: E402
from formtwin.physics.bending.solver import crank  # noqa: E402

T = 0.3  # mm
ELASTIC = Material(yield_stress=1e9, rate=False)
EPP = Material(yield_stress=300.0, hardening=False, rate=False)  # elastic-perfectly plastic
DISC = Discretisation(dt_min=1e-9, max_iter=40)


def strip(length: float, n_el: int, n_layers: int = 15) -> Sheet:
    return Sheet.straight(0.0, length, 0.0, n_el, T, n_layers, 2)


def ramp(n: int = 11) -> np.ndarray:
    return np.linspace(0.0, 1.0, n)


def bending_stiffness(m: Material) -> float:
    return m.plane_strain_modulus * T**3 / 12.0


def tip_load(length: float, n_el: int, p: float, steps: int = 11,
             material: Material = ELASTIC) -> tuple[Sheet, np.ndarray]:
    sheet = strip(length, n_el)
    fref = np.zeros(sheet.u.size)
    fref[-2] = p  # dead vertical load at the tip
    t = ramp(steps)
    h = solve(sheet, material, None, t, DISC, dt_max=1.0 / (steps - 1), lam=t, fref=fref)
    assert h.status == 0
    return sheet, h.u[-1]


def test_cantilever_tip_load_small_deflection() -> None:
    length, ei = 10.0, bending_stiffness(ELASTIC)
    p = 1e-4 * 3 * ei / length**2  # deflection / L = 1e-4: linear range
    _, u = tip_load(length, 20, p, steps=2)
    expected = p * length**3 / (3 * ei)
    assert u[-2] == pytest.approx(expected, rel=5e-3)
    assert u[-1] == pytest.approx(p * length**2 / (2 * ei), rel=5e-3)


@pytest.mark.parametrize(("load", "x_over_l", "y_over_l"), [
    (1.0, 0.9436, 0.3017), (2.0, 0.8394, 0.4935), (5.0, 0.6124, 0.7138), (10.0, 0.4450, 0.8106)])
def test_elastica_dead_tip_load(load: float, x_over_l: float, y_over_l: float) -> None:
    length = 10.0
    p = load * bending_stiffness(ELASTIC) / length**2
    sheet, u = tip_load(length, 20, p, steps=21)
    tip = sheet.X[-1] + u[-3:-1]
    assert tip[0] / length == pytest.approx(x_over_l, rel=5e-3)
    assert tip[1] / length == pytest.approx(y_over_l, rel=5e-3)


def test_pure_moment_quarter_circle() -> None:
    length, ei = 10.0, bending_stiffness(ELASTIC)
    sheet = strip(length, 20)
    fref = np.zeros(sheet.u.size)
    fref[-1] = ei * (math.pi / 2) / length  # M L / EI = pi/2
    t = ramp(11)
    h = solve(sheet, ELASTIC, None, t, DISC, dt_max=0.1, lam=t, fref=fref)
    assert h.status == 0
    radius = 2 * length / math.pi
    tip = sheet.positions[-1]
    assert tip[0] == pytest.approx(radius, rel=2e-3)
    assert tip[1] == pytest.approx(radius, rel=2e-3)
    assert sheet.u[-1] == pytest.approx(math.pi / 2, rel=1e-6)


def curvature_controlled(material: Material, kappa: float, length: float = 1.0,
                         n_el: int = 4) -> tuple[Sheet, float]:
    """Bend a strip to a uniform curvature by its end rotation; return the root moment."""
    sheet = strip(length, n_el)
    n = sheet.u.size
    fix = np.array([0, 1, 2, n - 1])
    t = ramp(21)
    h = solve(sheet, material, None, t, DISC, dt_max=0.05, fix=fix,
              fix_ref=np.array([0.0, 0.0, 0.0, kappa * length]), lam=t)
    assert h.status == 0
    return sheet, float(h.reactions[-1, 2])


def test_fully_plastic_moment_plane_strain() -> None:
    sy = EPP.yield_stress
    kappa_y = 2 * (2 * sy / math.sqrt(3)) / (EPP.plane_strain_modulus * T)
    _, moment = curvature_controlled(EPP, 50 * kappa_y)
    mp = sy * T**2 / (2 * math.sqrt(3))
    assert abs(moment) == pytest.approx(mp * (1 - 1 / (3 * 50**2)), rel=1e-2)


@pytest.mark.parametrize("rho", [0.1, 0.3])
def test_springback_elastic_perfectly_plastic(rho: float) -> None:
    sbar = 2 * EPP.yield_stress / math.sqrt(3)
    r_i = rho * EPP.plane_strain_modulus * T / sbar
    length = 5.0
    sheet, _ = curvature_controlled(EPP, 1.0 / r_i, length=length, n_el=8)
    # release the end rotation: no load, only the root clamped
    t = np.array([1.0, 1.1])
    h = solve(sheet, EPP, None, t, DISC, dt_max=0.1, t_start=1.0)
    assert h.status == 0
    r_f = length / sheet.u[-1]
    assert r_i / r_f == pytest.approx(1 - 3 * rho + 4 * rho**3, rel=2e-2)


def friction_history(mu: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A stiff strip on a flat die, pressed by 1 N/mm per node, dragged +d, then back to -d.

    The nodes' rotations are held: friction acts on the strip's lower face, ``t/2`` below
    the nodes, and its moment would otherwise rock the strip on the (soft at first)
    contact. Returns ``(lam_fix, reaction, moments)`` at the recorded instants: the
    reaction at the dragged dof and the sum of the reactions at the held rotations.
    """
    stiff = Material(yield_stress=1e12, E=1e9, rate=False)
    # the lower face 1e-9 mm into the die: at a gap of exactly 0 the first step's contact
    # (and with it a stiffness against the strip's rigid vertical motion) hung on the last
    # bit of the face position (it failed without the fast-math flag `contract`)
    sheet = Sheet.straight(0.0, 1.0, 0.5 * T - 1e-9, 4, T, 15, 2)
    die = make_toolset([("die", 0, -1, [(np.array([[-5.0, 0.0], [5.0, 0.0]]), np.zeros(0))])])
    fref = np.zeros(sheet.u.size)
    fref[1::3] = -1.0
    t = np.r_[0.0, 0.5, 1.0, 1.01, 2.0, 2.005, 2.5, 3.0]
    lam = np.minimum(t, 1.0)
    lam_fix = np.interp(t, [0.0, 1.0, 2.0, 3.0], [0.0, 0.0, 1.0, -1.0])
    rot = np.arange(2, sheet.u.size, 3)
    h = solve(sheet, stiff, die, t, DISC, dt_max=0.01, mu=np.array([mu]), lam=lam,
              lam_fix=lam_fix, fix=np.r_[0, rot], fix_ref=np.r_[1e-4, np.zeros(rot.size)],
              fref=fref)
    assert h.status == 0
    return lam_fix, h.reactions[:, 0], h.reactions[:, rot].sum(axis=1)


def test_friction_stick_slip_and_reversal() -> None:
    mu, penalty = 0.2, 5.0e5
    lam_fix, reaction, moments = friction_history(mu)
    # stick: 1e-6 mm of drag, every node sticks: reaction = penalty * length * drag (the
    # strip's axial compliance, E = 1e9 MPa, takes 5e-4 of it)
    assert lam_fix[3] == pytest.approx(0.01)
    assert reaction[3] == pytest.approx(penalty * 1.0 * 1e-6, rel=1e-3)
    # full slip: Coulomb, mu times the total normal force (5 nodes x 1 N/mm)
    assert reaction[4] == pytest.approx(mu * 5.0, rel=1e-6)
    # slip reversal: first 1e-6 mm back sticks again (elastic unloading of the tangential force)
    assert reaction[5] == pytest.approx(mu * 5.0 - penalty * 1e-6, rel=1e-3)
    # then slips the other way
    assert reaction[6] == pytest.approx(-mu * 5.0, rel=1e-6)
    assert reaction[7] == pytest.approx(-mu * 5.0, rel=1e-6)
    # the friction force on the lower face has the lever arm t/2 about the nodes
    assert moments[4] == pytest.approx(0.5 * T * mu * 5.0, rel=1e-6)
    assert moments[7] == pytest.approx(-0.5 * T * mu * 5.0, rel=1e-6)


def test_frictionless_drag_needs_no_force() -> None:
    _, reaction, moments = friction_history(0.0)
    assert np.abs(reaction[3:]).max() < 1e-7
    assert np.abs(moments[3:]).max() < 1e-7


def wrapped_strip(radius: float, t: float, h: float, mirror: bool) -> Sheet:
    """A stress-free strip (mm) lying on a convex radius: 1 mm straight on top, a quarter
    circle of the mid-surface radius ``radius + t/2`` about ``(0, -radius)``, 1 mm straight
    down; ``mirror``: reflected in ``y`` (it wraps up under a tool above, upper face on it)."""
    rm = radius + 0.5 * t
    xs = np.linspace(-1.0, 0.0, int(round(1.0 / h)) + 1)
    ang = np.linspace(0.5 * math.pi, 0.0, int(round(rm * 0.5 * math.pi / h)) + 1)[1:]
    ys = np.linspace(-radius, -radius - 1.0, int(round(1.0 / h)) + 1)[1:]
    X = np.vstack([np.c_[xs, np.full_like(xs, 0.5 * t)],
                   np.c_[rm * np.cos(ang), -radius + rm * np.sin(ang)],
                   np.c_[np.full_like(ys, rm), ys]])
    if mirror:
        X[:, 1] *= -1.0
    yl, wl = np.polynomial.legendre.leggauss(7)
    xg, wg = np.polynomial.legendre.leggauss(2)
    return Sheet(X, t, 0.5 * yl, 0.5 * wl, 0.5 * (xg + 1), 0.5 * wg)


@pytest.mark.parametrize("mu", [0.0, 0.1, 0.3])
@pytest.mark.parametrize("face", [-1, +1])
def test_capstan_on_a_tool_radius(mu: float, face: int) -> None:
    """An elastic strip (t/R = 0.01) wrapped 90 deg over a tool radius, its root clamped, pulled
    at the other end: sliding everywhere, the tension falls along the wrap as ``exp(-mu phi)``
    (capstan), so the root holds ``P exp(-mu pi/2)``; on the lower face over a die and on the
    upper face under a tool above (friction on arcs: the normal's rotation, the face's lever
    arm)."""
    radius, t, p = 2.0, 0.02, 1.0
    sheet = wrapped_strip(radius, t, 0.05, mirror=face > 0)
    pts = np.array([[-5.0, 0.0], [radius, 0.0], [radius, -6.0]])
    if face > 0:  # the mirrored tool, traversed so that it stays on the right
        pts = pts[::-1] * np.array([1.0, -1.0])
    tool = make_toolset([("tool", 0, face, [(pts, np.array([radius]))])])
    fref = np.zeros(sheet.u.size)
    fref[-2] = p * face  # pulled along the straight end, away from the wrap
    t_grid = ramp()
    h = solve(sheet, ELASTIC, tool, t_grid, DISC, dt_max=0.1, mu=np.array([mu]), lam=t_grid,
              fref=fref)
    assert h.status == 0
    assert -h.reactions[-1, 0] / p == pytest.approx(math.exp(-mu * 0.5 * math.pi), rel=4e-3)


def test_friction_of_a_moving_tool_acts_in_its_frame() -> None:
    """A vertical strip pressed (1 N/mm per node) against a vertical wall that moves up with the
    crank (a tool that moves with the punch): the wall drags the strip up, the support at its
    root holds it with ``-mu N``; without friction it holds nothing."""
    sheet = Sheet(np.c_[np.full(5, 1e-4), np.linspace(0.0, -1.0, 5)], T,
                  *(0.5 * a for a in np.polynomial.legendre.leggauss(15)),
                  np.array([0.5 - 0.5 / math.sqrt(3), 0.5 + 0.5 / math.sqrt(3)]),
                  np.array([0.5, 0.5]))
    wall = make_toolset([("wall", 1, +1, [(np.array([[0.5 * T, -5.0], [0.5 * T, 5.0]]),
                                          np.zeros(0))])])
    fref = np.zeros(sheet.u.size)
    fref[0::3] = 1.0
    t = np.r_[0.0, 0.2, 0.4, 0.8, 1.2]
    rot = np.arange(2, sheet.u.size, 3)
    stiff = Material(yield_stress=1e12, E=1e9, rate=False)
    for mu in (0.0, 0.2):
        h = solve(sheet, stiff, wall, t, DISC, dt_max=0.01, mu=np.array([mu]),
                  lam=np.minimum(t / 0.2, 1.0), fix=np.r_[1, rot],
                  fix_ref=np.zeros(1 + rot.size), fref=fref)
        assert h.status == 0
        assert np.all(np.diff(h.force[:, 3]) > 0)  # the wall rises
        np.testing.assert_allclose(h.reactions[2:, 1], -mu * 5.0, atol=1e-6)
        sheet.u[:] = 0.0


def test_face_friction_is_not_shear_force() -> None:
    """A flat, unbent strip under a uniform friction traction ``q`` on one face: ``dM/ds = 0``,
    but its mean shear stress is ``q/2`` (a continuum's ``tau_xy`` is ``q`` on that face, 0 on
    the other): the moment ``(t/2) q`` of the traction about the mid-surface balances the shear
    force. :func:`friction_shear` (``Discretisation.friction_shear``) adds it to the
    elements' ``dM/ds / t``; bending-2.4 (without it) has 0."""
    from formtwin.physics.bending.contact import friction_shear
    from formtwin.physics.bending.faces import contact_points
    from formtwin.physics.bending.kernels import element_shear

    sheet = Sheet.straight(0.0, 1.0, 0.5 * T, 4, T, 15, 2)
    el, xi, _, share = contact_points(sheet.X, sheet.phi0, 4)
    q = 30.0  # MPa: N/mm of tangential force per mm of sheet, per mm of width
    zero = np.zeros_like(share)
    for tool_tt in (np.c_[q * share, zero], np.c_[zero, -q * share]):  # either face/tool
        tadd = np.zeros(4)
        friction_shear(sheet.X, el, xi, tool_tt, tadd)
        tau = np.zeros(4)
        element_shear(sheet.X, sheet.sig, T, sheet.ylay, sheet.wlay, sheet.xg, tau, tadd=tadd)
        np.testing.assert_allclose(np.abs(tau), 0.5 * q, rtol=1e-12)
        old = np.ones(4)
        element_shear(sheet.X, sheet.sig, T, sheet.ylay, sheet.wlay, sheet.xg, old)
        np.testing.assert_allclose(old, 0.0, atol=1e-12)


@pytest.mark.parametrize(("rate", "window", "strain"), [
    (1.0, 0.0, 0.02), (100.0, 0.0, 0.02), (1.0, 5e-3, 0.1)])
def test_cowper_symonds_bar(rate: float, window: float, strain: float) -> None:
    """Plastic bar stretched at a constant strain rate: N = t sbar (1 + (epsdot/epsdot0)^q).

    With the model's rate smoothing (time constant ``window``) the rate settles on the
    constant rate after a few time constants (here 20).
    """
    m = Material(yield_stress=300.0, hardening=False, log_rate=2.0, rate_exponent=0.5)
    sheet = strip(1.0, 1)
    t = np.linspace(0.0, strain / rate, 101)
    h = solve(sheet, m, None, t, DISC, dt_max=t[1], fix=np.array([0, 1, 2, 3, 4, 5]),
              fix_ref=np.array([0, 0, 0, strain, 0, 0]), lam=t / t[-1], rate_tau=window)
    assert h.status == 0
    eq_rate = 2 / math.sqrt(3) * rate
    sbar = 2 / math.sqrt(3) * m.yield_stress * (1 + (eq_rate / 10**m.log_rate) ** m.rate_exponent)
    assert h.reactions[-1, 3] == pytest.approx(T * sbar, rel=1e-3)


@pytest.mark.parametrize("rate_per_speed", [0.1, 1.0])
def test_uniform_rate_of_the_ram_speed(rate_per_speed: float) -> None:
    """``Discretisation.rate_per_speed`` (CalculiX's rate law): every layer takes the rate
    ``rate_per_speed * |c'(t)|`` of the crank, not its own. A plastic bar stretched at
    1/s near the crank's top speed (~94 mm/s) carries ``N = t sbar (1 + (r/epsdot0)^q)``
    with that ``r`` (of the last committed increment: the rate is lagged one step)."""
    m = Material(yield_stress=300.0, hardening=False, log_rate=2.0, rate_exponent=0.5)
    press = np.array([0.0, 0.0, 1.0, 10.0, 100.0, 3 * math.pi])  # prescribed punch, crank
    disc = Discretisation(dt_min=1e-9, max_iter=40, rate_per_speed=rate_per_speed)
    t = np.linspace(0.15, 0.17, 101)  # crank angle 81-92 deg
    h = solve(strip(1.0, 1), m, None, t, disc, dt_max=t[1] - t[0], press=press,
              fix=np.array([0, 1, 2, 3, 4, 5]), fix_ref=np.array([0, 0, 0, 0.02, 0, 0]),
              lam=(t - t[0]) / (t[-1] - t[0]))
    assert h.status == 0
    speed = abs(crank(t[-2], np.r_[press, 5e-4])[1])
    assert 90.0 < speed < 100.0
    rate = rate_per_speed * speed
    sbar = 2 / math.sqrt(3) * m.yield_stress * (1 + (rate / 10**m.log_rate) ** m.rate_exponent)
    assert h.reactions[-1, 3] == pytest.approx(T * sbar, rel=1e-6)
    # the bar's own rate (2/sqrt 3 /s) would give a force 15-45 % lower
    own = 2 / math.sqrt(3) * m.yield_stress * (1 + (2 / math.sqrt(3) / 10**m.log_rate) ** 0.5)
    assert T * own < 0.9 * h.reactions[-1, 3]


@pytest.mark.parametrize("kappa_rate", [0.5, 50.0])
def test_cowper_symonds_plastic_bending(kappa_rate: float) -> None:
    """Fully plastic bending at a constant curvature rate (1/(mm s)).

    With ``epsdot(y) = (2/sqrt 3) |y| kappa_dot`` through the thickness,
    ``M = M_p (1 + 2/(2+q) ((2/sqrt 3) kappa_dot t/2 / epsdot0)^q)``.
    """
    m = Material(yield_stress=300.0, hardening=False, log_rate=2.0, rate_exponent=0.5)
    sheet = strip(1.0, 1, n_layers=31)
    kappa = 0.5  # 1/mm: 46 times the first-yield curvature
    t = np.linspace(0.0, kappa / kappa_rate, 41)
    # one element, all dofs prescribed: end rotations -+ kappa L / 2 at a fixed chord give a
    # uniform curvature kappa with no stretch of the mid-surface
    h = solve(sheet, m, None, t, DISC, dt_max=t[1], fix=np.arange(6),
              fix_ref=np.array([0.0, 0.0, -kappa / 2, 0.0, 0.0, kappa / 2]), lam=t / t[-1])
    assert h.status == 0
    mp = m.yield_stress * T**2 / (2 * math.sqrt(3))
    edge_rate = 2 / math.sqrt(3) * kappa_rate * T / 2
    q = m.rate_exponent
    elastic_core = 1 - (2 * (2 / math.sqrt(3)) * m.yield_stress / (m.plane_strain_modulus * T)
                        / kappa) ** 2 / 3
    expected = mp * (elastic_core + 2 / (2 + q) * (edge_rate / 10**m.log_rate) ** q)
    assert abs(h.reactions[-1, 5]) == pytest.approx(expected, rel=1e-2)


@pytest.mark.parametrize("slip", [False, True])
@pytest.mark.parametrize("n_sub", [1, 3])
def test_face_contact_tangent_is_the_derivative_of_the_residual(slip: bool, n_sub: int) -> None:
    """Contact on the sheet's faces (at the nodes' face points ``x + f t/2 n(theta)``, and
    with ``n_sub`` > 1 at Hermite-interpolated points inside the elements too): the
    assembled band tangent and the punch column ``dR/dp`` are the finite-difference
    derivatives of the residual, in stick and in slip, on a nose (arc) and on a flat die,
    with rotated nodes."""
    from formtwin.physics.bending.faces import contact_points
    from formtwin.physics.bending.kernels import layer_scales_all
    from formtwin.physics.bending.solver import BW, assemble

    sheet = Sheet.straight(0.0, 0.6, 0.5 * T, 3, T, 15, 2)
    n = sheet.u.size
    rng = np.random.default_rng(3)
    u = 1e-3 * rng.standard_normal(n)
    u[2::3] = [0.02, -0.01, 0.03, 0.015]  # rotations, rad
    u[1::3] -= 2e-4  # into the die
    tools = make_toolset([
        ("die", 0, -1, [(np.array([[-5.0, 0.0], [5.0, 0.0]]), np.zeros(0))]),
        ("nose", 1, +1, [(np.array([[0.8, 2.0], [0.8, 0.3], [-1.0, 0.3]]), np.array([0.3]))])])
    p = T - 0.3 - 2e-4 - 0.01  # the punch's nose pressed into the sheet's upper face
    mesh = (sheet.X, sheet.phi0, T, sheet.ylay, sheet.wlay, sheet.xg, sheet.wg, ELASTIC.array)
    zeros = np.zeros_like(sheet.sig)
    el, xi, Xp, _ = contact_points(sheet.X, sheet.phi0, n_sub)
    n_p = el.size
    pen = np.full((n_p, 2), 5.0e4 / n_sub)
    mu = np.full(2, 0.3)
    # the committed face points: a slip far beyond mu N / penalty, or a tiny stick offset
    ct_rel = np.zeros((n_p, 2, 2))
    ct_rel[:, :, 0] = Xp[:, [0]] + (5e-3 if slip else 1e-7)
    ct_rel[:, :, 1] = 0.0
    ct_rel[:, 1, 1] = T - p
    tshear = np.zeros(sheet.X.shape[0] - 1)
    scales = np.empty((*zeros.shape, 3))
    layer_scales_all(zeros, tshear, ELASTIC.array, scales)
    contact = (np.zeros((n_p, 2)), ct_rel, np.zeros((n_p, 2), np.int64),
               np.zeros((sheet.X.shape[0], 2)), tshear, scales)
    press = np.array([0.0, 0.0, 1.0, 1.0, 10.0, 1.0, 5e-4])
    toolarr = (tools.ptype, tools.pdata, tools.tstart, tools.owner, tools.face, mu, el, xi,
               pen, Xp)

    def residual(uu: np.ndarray, pp: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        Kb, R = np.zeros((n, 2 * BW + 1)), np.zeros(n)
        col, row, out = np.zeros(n), np.zeros(n), np.zeros(5)
        trial = (np.zeros_like(zeros), np.zeros_like(zeros), np.zeros_like(zeros))
        ct_trial = (np.zeros((n_p, 2)), np.zeros((n_p, 2), np.int64), np.zeros((n_p, 2)))
        assemble(0.0, uu, pp, mesh, zeros, zeros, zeros, zeros, trial, toolarr, contact,
                 ct_trial, press, np.zeros(n), Kb, R, col, row, out)
        assert ct_trial[1].sum() >= 4  # several contacts active
        return R, Kb, col

    R0, Kb, col = residual(u, p)
    h = 1e-9
    for j in range(n):
        du = np.zeros(n)
        du[j] = h
        fd = (residual(u + du, p)[0] - residual(u - du, p)[0]) / (2 * h)
        band = np.array([Kb[i, j - i + BW] if abs(i - j) <= BW else 0.0 for i in range(n)])
        np.testing.assert_allclose(band, fd, rtol=1e-4, atol=1e-4 * np.abs(fd).max())
    fd = (residual(u, p + h)[0] - residual(u, p - h)[0]) / (2 * h)
    np.testing.assert_allclose(col, fd, rtol=1e-4, atol=1e-4 * np.abs(fd).max())


@pytest.mark.parametrize("p", [0.0, 100.0, 250.0])
def test_yield_under_through_thickness_pressure(p: float) -> None:
    """Plane strain with incompressible flow under a through-thickness stress -p: the layer
    yields where ``|sigma_xx + p| = (2/sqrt 3) sigma_y`` (perfect plasticity), in tension
    and in compression; elastic below it."""
    from formtwin.physics.bending.kernels import SQ, layer_update

    mat = Material(yield_stress=300.0, rate=False, hardening=False).array
    E = mat[0]
    for sign in (+1.0, -1.0):
        sig, _, et = layer_update(sign * 0.05, 0.0, 0.0, 0.0, E, 300.0, np.inf, 1.0, 0.0, -p)
        assert sig == pytest.approx(-p + sign * SQ * 300.0, rel=1e-12)
        assert et == pytest.approx(0.0, abs=1e-9)  # perfectly plastic
    small = 0.5 * SQ * 300.0 / E  # half the yield strain without pressure
    sig, epb, et = layer_update(small, 0.0, 0.0, 0.0, E, 300.0, np.inf, 1.0, 0.0,
                                -min(p, 0.4 * SQ * 300.0))
    assert sig == pytest.approx(E * small) and epb == 0.0 and et == E


@pytest.mark.parametrize("ratio", [0.0, 0.6, 0.9])
def test_yield_under_transverse_shear(ratio: float) -> None:
    """Plane-strain von Mises with a shear stress ``tau = ratio k``, ``k = sigma_y/sqrt 3``:
    ``(sigma_xx - sigma_yy)^2/4 + tau^2 = k^2``, so the layer yields at ``|sigma_xx -
    sigma_yy| = (2/sqrt 3) sigma_y sqrt(1 - ratio^2)`` (perfect plasticity), with and
    without a through-thickness pressure; elastic below it."""
    from formtwin.physics.bending.kernels import SQ, layer_update

    sy = 300.0
    mat = Material(yield_stress=sy, rate=False, hardening=False).array
    E = mat[0]
    tau = ratio * sy / math.sqrt(3.0)
    for p in (0.0, 100.0):
        for sign in (+1.0, -1.0):
            sig, _, et = layer_update(sign * 0.05, 0.0, 0.0, 0.0, E, sy, np.inf, 1.0, 0.0, -p,
                                      tau)
            assert sig == pytest.approx(-p + sign * SQ * sy * math.sqrt(1 - ratio**2),
                                        rel=1e-12)
            assert et == pytest.approx(0.0, abs=1e-9)
    small = 0.9 * SQ * sy * math.sqrt(1 - ratio**2) / E
    sig, epb, et = layer_update(small, 0.0, 0.0, 0.0, E, sy, np.inf, 1.0, 0.0, 0.0, tau)
    assert sig == pytest.approx(E * small) and epb == 0.0 and et == E


def test_element_shear_of_a_cantilever_is_the_tip_load() -> None:
    """An elastic cantilever with a tip load ``P``: the shear force is ``P`` all along, so
    every element's mean shear stress (from the moments at its Gauss points) is ``P / t``."""
    from formtwin.physics.bending.kernels import element_shear

    p = 1e-3
    sheet, _ = tip_load(1.0, 10, p)
    tshear = np.zeros(10)
    element_shear(sheet.X, sheet.sig, T, sheet.ylay, sheet.wlay, sheet.xg, tshear)
    np.testing.assert_allclose(np.abs(tshear), p / T, rtol=1e-6)


def test_element_shear_under_a_pinching_punch_takes_the_spans_shear() -> None:
    """With the punch's pressure in ``pface[:, 2]``: elements pressed by ``p1`` or more take
    the signed largest ``|tau|`` of the elements within ``reach`` of their centre, elements
    below ``p0`` keep their own, and in between the blend is linear in the pressure (a
    reference implementation of the rule on random layer stresses)."""
    from formtwin.physics.bending.kernels import element_shear

    rng = np.random.default_rng(3)
    sheet, _ = tip_load(1.0, 12, 1e-3)
    sheet.sig[:] = rng.normal(0.0, 100.0, sheet.sig.shape)
    tau0 = np.zeros(12)
    element_shear(sheet.X, sheet.sig, T, sheet.ylay, sheet.wlay, sheet.xg, tau0)
    n = sheet.X.shape[0]
    pface = np.zeros((n, 3))
    pface[3:6, 2] = 200.0  # elements 2..5 touch a node pressed in full
    pface[9, 2] = 75.0  # elements 8 and 9: a quarter of the way from p0 = 50 to p1 = 150
    reach = 0.2
    tau = np.zeros(12)
    element_shear(sheet.X, sheet.sig, T, sheet.ylay, sheet.wlay, sheet.xg, tau, pface, reach,
                  50.0, 150.0)
    xc = 0.5 * (sheet.X[1:, 0] + sheet.X[:-1, 0])
    for e in range(12):
        near = tau0[np.abs(xc - xc[e]) <= reach]
        best = near[np.argmax(np.abs(near))]
        w = np.clip((max(pface[e, 2], pface[e + 1, 2]) - 50.0) / 100.0, 0.0, 1.0)
        assert tau[e] == pytest.approx(tau0[e] + w * (best - tau0[e]), rel=1e-12, abs=1e-12)
    assert np.any(tau != tau0) and tau[0] == tau0[0]


def test_face_pressure_spreads_forces_without_changing_their_sum() -> None:
    """Uniform normal forces ``f`` per node at spacing ``h``, spread by a hat of half-width
    ``3 h``: the pressure away from the ends is ``f / h`` (exactly: the hat's weights sum
    to 1/h); a single force keeps its total ``sum p h``; the faces are kept apart."""
    from formtwin.physics.bending.contact import face_pressure

    h, n = 0.05, 41
    X = np.column_stack([h * np.arange(n), np.zeros(n)])
    fn = np.zeros((n, 2))
    fn[:, 0] = 2.0  # a lower-face tool (face -1) pressing every node with 2 N/mm
    p = np.zeros((n, 2))
    face_pressure(X, X, fn, np.array([-1.0, 1.0]), 3 * h, p)
    np.testing.assert_allclose(p[5:-5, 0], 2.0 / h, rtol=1e-12)
    assert np.all(p[:, 1] == 0.0)
    fn[:] = 0.0
    fn[20, 1] = 3.0  # one force on the upper face
    face_pressure(X, X, fn, np.array([-1.0, 1.0]), 3 * h, p)
    assert np.sum(p[:, 1]) * h == pytest.approx(3.0, rel=1e-12)
    assert np.count_nonzero(p[:, 1] > 1e-9 * p[:, 1].max()) == 5 and np.all(p[:, 0] == 0.0)
    p3 = np.zeros((n, 3))  # the punch's own pressure: the tools that move with it
    fn[20, 0] = 1.0
    face_pressure(X, X, fn, np.array([-1.0, 1.0]), 3 * h, p3, np.array([0, 1]))
    np.testing.assert_allclose(p3[:, 2], p3[:, 1], rtol=1e-12, atol=1e-12)
    assert np.sum(p3[:, 0]) * h == pytest.approx(1.0, rel=1e-12)


def test_contact_points_lie_on_the_face_of_a_bent_sheet() -> None:
    """Nodes on a circle of radius ``r`` with their directions along it: the Hermite face
    points inside the elements lie on the offset circle ``r -+ t/2`` to the interpolation's
    O(h^4) (exactly on a straight sheet), their derivatives by the nodes' rotations match
    finite differences, and the points' shares of the length sum to the sheet's length."""
    from formtwin.physics.bending.faces import contact_points, hermite_face, point_face

    r, errors = 1.0, []
    for n_el in (8, 16):
        a = np.linspace(0.0, 0.5 * math.pi, n_el + 1)  # quarter circle about (0, r) from (0, 0)
        X = np.column_stack([r * np.sin(a), r - r * np.cos(a)])
        phi0 = a.copy()  # the circle's direction at each node
        el, xi, Xp, share = contact_points(X, phi0, 4)
        assert el.size == 4 * n_el + 1 and share.sum() == pytest.approx(
            np.linalg.norm(np.diff(X, axis=0), axis=1).sum(), rel=1e-14)
        np.testing.assert_allclose(xi[:5], [0.0, 0.25, 0.5, 0.75, 0.0])
        u = np.zeros(3 * (n_el + 1))
        for s in (+1.0, -1.0):  # upper face: inside the bend, radius r - t/2
            radii = [np.hypot(*(np.array(point_face(X, phi0, u, el, xi, q, s, T / 2))
                                - [0.0, r])) for q in range(el.size)]
            errors.append(np.max(np.abs(np.array(radii) - (r - s * T / 2))))
    assert max(errors[:2]) < 2e-5 * r and max(errors[2:]) < max(errors[:2]) / 12  # O(h^4)
    flat = np.column_stack([np.linspace(0.0, 1.0, 5), np.zeros(5)])
    el, xi, _, _ = contact_points(flat, np.zeros(5), 3)
    pts = np.array([point_face(flat, np.zeros(5), np.zeros(15), el, xi, q, 1.0, T / 2)
                    for q in range(el.size)])
    np.testing.assert_allclose(pts, np.column_stack([np.linspace(0.0, 1.0, 13),
                                                     np.full(13, T / 2)]), atol=1e-15)
    d = np.zeros((5, 2))
    args = (0.1, 0.2, 0.3, 0.4, 0.25, -0.2, -1.0, T / 2, 0.3, 0.35)
    hermite_face(*args, d)
    h = 1e-6

    def shifted(i: int, step: float) -> tuple[np.ndarray, np.ndarray]:
        a = list(args)
        a[i] += step
        dd = np.zeros((5, 2))
        return np.array(hermite_face(*a, dd)), dd

    for i, first, second in ((2, 0, 2), (5, 1, 3)):  # the rotations of node a and node b
        (yp, dp), (yn, dn) = shifted(i, h), shifted(i, -h)
        np.testing.assert_allclose((yp - yn) / (2 * h), d[first], rtol=1e-7, atol=1e-9)
        np.testing.assert_allclose((dp[first] - dn[first]) / (2 * h), d[second], rtol=1e-6,
                                   atol=1e-8)
    (_, dp), (_, dn) = shifted(5, h), shifted(5, -h)
    np.testing.assert_allclose((dp[0] - dn[0]) / (2 * h), d[4], rtol=1e-6, atol=1e-8)


def test_closest_point_matches_a_sampled_tool_outline() -> None:
    """The closest point of each stage-1 and stage-2 tool to random points (inside and
    outside, near corners): its distance is the distance to the densely sampled outline,
    and away from the chains' open ends the signed distance is the distance with its sign
    and the normal points from the closest point to the query point."""
    from formtwin.physics.bending.contact import closest_point, primitive_frames
    from formtwin.physics.bending.geometry import FlapGeometry, make_toolset, tool_outline

    g = FlapGeometry()
    ts = make_toolset([("die1", 0, -1, g.die1()), ("holder", 0, +1, g.holder(T)),
                       ("punch1", 1, +1, g.punch1(0.36, 0.0, 0.0)),
                       ("die2", 0, -1, g.die2()), ("punch2", 1, +1, g.punch2(0.0))])
    pre = primitive_frames(ts.ptype, ts.pdata)
    rng = np.random.default_rng(3)
    for k in range(ts.owner.size):
        # the outline's arcs finely sampled; its straight parts are exact as segments
        outline = tool_outline(ts, k, n_arc=4000)
        corners = outline[::200]
        for _ in range(60):
            q = corners[rng.integers(len(corners))] + rng.normal(0.0, 0.3, 2)
            dist, sd, nx, ny, _ = closest_point(q[0], q[1], ts.tstart[k], ts.tstart[k + 1],
                                                ts.ptype, ts.pdata, pre)
            gap, interior = _polyline_distance(outline, q)
            assert dist == pytest.approx(gap, abs=2e-3)
            if interior and dist > 1e-2:
                foot = q - sd * np.array([nx, ny])  # on the outline
                assert _polyline_distance(outline, foot)[0] < 2e-3
                assert abs(abs(sd) - dist) < 2e-3


def _polyline_distance(points: np.ndarray, q: np.ndarray) -> tuple[float, bool]:
    """Distance from ``q`` (2,) to the polyline through ``points`` (n, 2), by brute force
    over its segments (each exact: the foot of the perpendicular clipped to the segment),
    and whether the nearest point is away from the polyline's two ends."""
    a, ab = points[:-1], np.diff(points, axis=0)
    len2 = np.einsum("ij,ij->i", ab, ab)
    t = np.clip(np.einsum("ij,ij->i", q - a, ab) / np.where(len2 > 0, len2, 1.0), 0.0, 1.0)
    gaps = np.hypot(*(a + t[:, None] * ab - q).T)
    i = int(np.argmin(gaps))
    ends = (i == 0 and t[i] <= 0.0) or (i == len(gaps) - 1 and t[i] >= 1.0)
    return float(gaps[i]), not ends
