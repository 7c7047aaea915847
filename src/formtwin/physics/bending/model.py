"""The two-stage flap bending model behind the :class:`~formtwin.simulator.Simulator` seam.

A run: stage 1 load (crank down to bottom dead centre at ``t = 0`` against the press
spring), stage-1 unload (crank up until the punch is clear: springback), stage 2 load and
unload with the stroke-controlled punch (depth set by the control ``u``);
outputs the stage-1 spring force on the spec's time grid and
the two bend angles after springback. See :mod:`.geometry` for the tools and
``docs/explanation/physics.md`` for the assumptions.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from formtwin.physics.bending.assembly import crank
from formtwin.physics.bending.faces import contact_points, face_points
from formtwin.physics.bending.geometry import FlapGeometry, ToolSet, make_toolset
from formtwin.physics.bending.material import Material
from formtwin.physics.bending.solver import OK, run_history
from formtwin.simulator import RunResult
from formtwin.spec import ProcessSpec, load_spec

FloatArray = NDArray[np.float64]
log = logging.getLogger(__name__)

VERSION = "bending-2.4"

#: the control input (spec ``[[control]]``) that sets the stage-2 depth, mm
CONTROL = "stage2_depth"


@dataclass(frozen=True)
class Discretisation:
    """Mesh and solver settings.

    Attributes
    ----------
    n_elements
        Beam elements along the sheet (root to tip, uniform).
    n_layers
        Integration points through the thickness (Gauss-Legendre).
    n_gauss
        Gauss points along each element.
    dt_max1, dt_max2
        Largest time step (s) in stage 1 and stage 2.
    dt_min
        Smallest step before a run is declared failed (s).
    max_iter, tol_force, tol_disp
        Newton settings: iterations per step, residual tolerance (N/mm, per mm of width),
        displacement-correction tolerance (mm).
    cap_disp
        Largest displacement correction per Newton iteration (mm).
    predict
        Weight of the extrapolation of the last increment in the Newton predictor (0..1).
    line_search, ls_ratio, ls_energy
        Largest number of step halvings in the line search, and the ratio (new / old)
        above which the Newton step is halved: of the residual's work along the Newton
        direction (its energy's directional derivative; ``ls_energy``, the default) or of
        the residual norms (``ls_energy=False, ls_ratio=1.0``: the search of the bundled
        DOE's runs, same model to its roundoff level).
    easy_iter, easy_steps
        The step is doubled (up to ``dt_max``) after ``easy_steps`` consecutive steps that
        converged in at most ``easy_iter`` iterations.
    rate_window
        Crank angle (deg) over which each layer's strain rate is smoothed (exponentially,
        over the converged increments) in the process stages; 2.7 deg is 5 ms at 90
        strokes/min. Smoothing makes the Cowper-Symonds factor independent of the adaptive
        step pattern; tied to the crank angle it scales with the press speed.
    pressure_spread
        Half-width, in sheet thicknesses, of the hat over which the nodes' normal contact
        forces are spread into face pressures, which the layers carry as a through-thickness
        stress (:mod:`.kernels`); 0 switches the through-thickness stress off (model 2.0).
    contact_points
        Contact points per element on each face (:mod:`.contact`): 1 puts them at the nodes
        only (model 2.1); more let a tool corner slide smoothly along the sheet.
    transverse_shear
        Whether each element's mean transverse shear stress ``V/t`` (lagged one increment)
        lowers its layers' axial yield stress (von Mises, :mod:`.kernels`); False gives
        model 2.2.
    pinch_reach, pinch_pressure
        Where the punch presses the flap hard, its elements take the largest shear stress
        within ``pinch_reach`` thicknesses (:func:`.kernels.element_shear`): in full where
        the punch's face pressure exceeds ``pinch_pressure[1]`` times the plane-strain
        yield stress ``(2/sqrt 3) sigma_y``, not below ``pinch_pressure[0]`` times it;
        ``pinch_reach = 0`` gives model 2.3; 1.0 (one thickness, the scale of the pressure
        spread) is model 2.4.
    rate_per_speed
        0 (the default): each layer point's Cowper-Symonds factor takes its own equivalent
        strain rate. A positive value (1/mm) replaces every layer's rate by the uniform
        ``rate_per_speed * |c'(t)|`` of the ram speed ``c'`` (mm/s), smoothed over the same
        window: the CalculiX reference's rate law (:mod:`formtwin.physics.calculix`,
        ``FeSettings.rate_per_speed = 0.1``), for like-with-like comparisons with it.
    friction_shear
        Whether the elements' shear stress (``transverse_shear``) counts the face friction's
        distributed moment ``(t/2) F_t`` out of ``dM/ds`` (:func:`.contact.friction_shear`);
        False (the default) is bending-2.4, whose ``V = dM/ds`` includes it.
    """

    n_elements: int = 32
    n_layers: int = 15
    n_gauss: int = 2
    dt_max1: float = 1.0e-3
    dt_max2: float = 1.0e-3
    dt_min: float = 1.0e-7
    max_iter: int = 25
    tol_force: float = 1.0e-6
    tol_disp: float = 1.0e-10
    cap_disp: float = 0.05
    predict: float = 1.0
    line_search: int = 3
    ls_ratio: float = 0.8
    ls_energy: bool = True
    easy_iter: int = 8
    easy_steps: int = 2
    rate_window: float = 2.7
    pressure_spread: float = 1.0
    contact_points: int = 4
    transverse_shear: bool = True
    pinch_reach: float = 1.0
    pinch_pressure: tuple[float, float] = (0.25, 0.5)
    rate_per_speed: float = 0.0
    friction_shear: bool = False

    def opts(self, dt_max: float, rate_tau: float = 0.0) -> FloatArray:
        """Solver option array for :func:`~.solver.run_history` (``rate_tau`` in s)."""
        return np.array([dt_max, self.dt_min, self.max_iter, self.tol_force, self.tol_disp,
                         self.cap_disp, self.predict, self.line_search, self.ls_ratio,
                         self.easy_iter, self.easy_steps, rate_tau, self.pressure_spread,
                         float(self.transverse_shear), float(self.ls_energy),
                         self.pinch_reach, *self.pinch_pressure, self.rate_per_speed,
                         float(self.friction_shear)])


@dataclass
class Sheet:
    """Mesh and mutable state of the sheet (per mm of width).

    ``X (n_nodes, 2)`` reference nodes, ``u (3 n_nodes,)`` nodal ``(u_x, u_y, theta)``,
    layer states ``sig, epb, eps, rate (n_el, n_gauss, n_layers)``.
    """

    X: FloatArray
    thickness: float
    ylay: FloatArray
    wlay: FloatArray
    xg: FloatArray
    wg: FloatArray
    u: FloatArray = field(init=False)
    sig: FloatArray = field(init=False)
    epb: FloatArray = field(init=False)
    eps: FloatArray = field(init=False)
    rate: FloatArray = field(init=False)

    def __post_init__(self) -> None:
        n_el = self.X.shape[0] - 1
        shape = (n_el, self.xg.size, self.ylay.size)
        self.u = np.zeros(3 * self.X.shape[0])
        self.sig, self.epb, self.eps, self.rate = (np.zeros(shape) for _ in range(4))

    @classmethod
    def straight(cls, x0: float, x1: float, y: float, n_el: int, thickness: float,
                 n_layers: int, n_gauss: int) -> Sheet:
        """A straight strip from ``(x0, y)`` to ``(x1, y)``."""
        X = np.zeros((n_el + 1, 2))
        X[:, 0] = np.linspace(x0, x1, n_el + 1)
        X[:, 1] = y
        yl, wl = np.polynomial.legendre.leggauss(n_layers)
        xg, wg = np.polynomial.legendre.leggauss(n_gauss)
        return cls(X, thickness, 0.5 * yl, 0.5 * wl, 0.5 * (xg + 1), 0.5 * wg)

    @property
    def phi0(self) -> FloatArray:
        """Reference direction (rad) of the sheet at each node ``(n_nodes,)``: the mean of
        its elements' directions (the normal ``(-sin, cos)`` points to the upper face)."""
        d = np.diff(self.X, axis=0)
        a = np.arctan2(d[:, 1], d[:, 0])
        out: FloatArray = np.r_[a[0], 0.5 * (a[:-1] + a[1:]), a[-1]]
        return out

    @property
    def positions(self) -> FloatArray:
        """Current node positions ``(n_nodes, 2)``."""
        return np.asarray(self.X + self.u.reshape(-1, 3)[:, :2], dtype=np.float64)


@dataclass
class History:
    """What :func:`solve` recorded at each target time.

    ``u (n_targets, n_dof)``; ``force (n_targets, 8)`` = measured force, ``F_v``, ``F_lat``
    (N/mm), punch position and ram position (mm), cumulative steps, iterations and step
    cuts; ``reactions (n_targets, n_dof)``.
    """

    t: FloatArray
    u: FloatArray
    force: FloatArray
    reactions: FloatArray
    status: int
    counters: NDArray[np.int64]


def solve(sheet: Sheet, material: Material, tools: ToolSet | None, targets: FloatArray,
          disc: Discretisation, *, dt_max: float, t_start: float | None = None,
          mu: FloatArray | None = None, penalty: float = 5.0e5, smooth: float = 5.0e-4,
          press: FloatArray | None = None, fix: NDArray[np.int64] | None = None,
          fix_ref: FloatArray | None = None, fref: FloatArray | None = None,
          lam: FloatArray | None = None, lam_fix: FloatArray | None = None,
          rate_tau: float = 0.0) -> History:
    """Advance ``sheet`` (in place) through ``targets`` (s) and record the history.

    ``tools`` may be None (no contact). ``mu (n_tools,)`` friction coefficients, ``press``
    ``[k (N/mm per mm width; <= 0 prescribed punch), mu_tt, v_eps, crank R, rod, omega]``;
    ``fix`` prescribed dofs with values ``lam_fix(t) * fix_ref``; loads ``lam(t) * fref``
    (``lam, lam_fix (n_targets,)``, piecewise linear in time; ``lam_fix`` defaults to
    ``lam``). The history starts at ``t_start`` (default ``targets[0]``). ``rate_tau`` (s)
    smooths the layers' strain rates (0: the rate of the last increment).
    """
    n = sheet.u.size
    if tools is None:
        tools = ToolSet(np.zeros(1, np.int64), np.zeros((1, 6)), np.zeros(1, np.int64),
                        np.zeros(0, np.int64), np.zeros(0), ())
    n_tools = tools.owner.size
    n_nodes = sheet.X.shape[0]
    phi0 = sheet.phi0  # a property that computes: once
    el, xi, Xp, share = contact_points(sheet.X, phi0, disc.contact_points)
    pen = np.repeat((penalty * share)[:, None], 2, axis=1)
    press = np.array([0.0, 0.0, 1.0, 1.0, 10.0, 1.0]) if press is None else press
    press = np.r_[press, smooth]
    fix = np.array([0, 1, 2], dtype=np.int64) if fix is None else fix
    fix_ref = np.zeros(fix.size) if fix_ref is None else fix_ref
    fref = np.zeros(n) if fref is None else fref
    lam = np.zeros(targets.size) if lam is None else lam
    lam_fix = lam if lam_fix is None else lam_fix
    mu = np.zeros(n_tools) if mu is None else mu
    t0 = float(targets[0]) if t_start is None else t_start
    pa = np.array([crank(t0, press)[0]])
    ct_t = np.zeros((el.size, n_tools))
    ct_rel = np.zeros((el.size, n_tools, 2))  # the points' face positions (tool frame)
    face_points(sheet.X, phi0, sheet.u, el, xi, np.asarray(tools.face, dtype=np.float64),
                tools.owner, 0.5 * sheet.thickness, float(pa[0]), ct_rel)
    ct_act = np.zeros((el.size, n_tools), dtype=np.int64)
    rec_u = np.zeros((targets.size, n))
    rec_f = np.zeros((targets.size, 8))
    rec_r = np.zeros((targets.size, n))
    counters = np.zeros(4, dtype=np.int64)
    mesh = (sheet.X, phi0, sheet.thickness, sheet.ylay, sheet.wlay, sheet.xg, sheet.wg,
            material.array)
    state = (sheet.u, pa, sheet.sig, sheet.epb, sheet.eps, sheet.rate)
    tool_arrays = (tools.ptype, tools.pdata, tools.tstart, tools.owner, tools.face, mu, el, xi,
                   pen, Xp)
    status = run_history(targets, lam, lam_fix, t0, mesh, state, tool_arrays,
                         (ct_t, ct_rel, ct_act, np.zeros((n_nodes, 3)), np.zeros(n_nodes - 1),
                          np.empty((*sheet.sig.shape, 3))),
                         (press, fref, fix, fix_ref),
                         disc.opts(dt_max, rate_tau), (rec_u, rec_f, rec_r, counters))
    return History(targets, rec_u, rec_f, rec_r, int(status), counters)


def flap_angle(sheet: Sheet, length: float) -> float:
    """Bend angle (deg, downward positive) of the chord of the last ``length`` mm of flap."""
    pos = sheet.positions
    s = sheet.X[:, 0]
    j = int(np.searchsorted(s, s[-1] - length))
    d = pos[-1] - pos[j]
    return math.degrees(math.atan2(-d[1], d[0]))


class BendingModel:
    """Two-stage flap bending: corotational layered beams, rigid tools, crank and press.

    Satisfies :class:`formtwin.simulator.Simulator`; picklable.

    Parameters
    ----------
    spec
        Process spec (inputs in internal units); default: the bundled demonstrator.
    geometry
        Tool dimensions and press kinematics (:class:`FlapGeometry`).
    disc
        Mesh and solver settings (:class:`Discretisation`).
    **overrides
        Fields of :class:`Discretisation` to override, e.g. ``n_elements=40``.

    Examples
    --------
    >>> model = BendingModel(n_elements=40)
    >>> r = model.run(model.centre())
    >>> r.ok, r.curve.shape, bool(r.curve.max() > 100), bool(65 < r.angles[1] < 80)
    (True, (101,), True, True)
    """

    def __init__(self, spec: ProcessSpec | None = None, geometry: FlapGeometry | None = None,
                 disc: Discretisation | None = None, **overrides: Any) -> None:
        self.spec = spec if spec is not None else load_spec()
        self.geometry = geometry if geometry is not None else FlapGeometry()
        base = disc if disc is not None else Discretisation()
        self.disc = Discretisation(**{**base.__dict__, **overrides})
        self.version = VERSION
        self._ix = self.spec.run_inputs.index

    def centre(self) -> FloatArray:
        """Centre of Table 1 ``(n_run_inputs,)``: ``mu_mid`` for the state, box centre for the
        parameters, nominal controls."""
        sp = self.spec
        mid = np.r_[sp.state.mu_mid, 0.5 * (sp.params.lo + sp.params.hi), sp.controls.nominal]
        return np.asarray(mid, dtype=np.float64)

    def run(self, inputs: FloatArray) -> RunResult:
        """Run one input point ``(n_run_inputs,)`` = ``(x, theta, u)`` (internal units).

        Never raises for a point that does not converge or has non-finite values (returns
        a failure record with the reason); raises ``ValueError`` for a wrongly shaped input.
        """
        n_t = self.spec.time.size
        x = np.asarray(inputs, dtype=np.float64)
        names = self.spec.run_inputs.names
        if x.shape != (len(names),):
            raise ValueError(f"inputs: expected shape ({len(names)},) in the order "
                             f"{', '.join(names)}; got {x.shape}")
        if not np.all(np.isfinite(x)):
            bad = [n for n, v in zip(names, x, strict=True) if not np.isfinite(v)]
            return RunResult.failure(n_t, f"non-finite input: {', '.join(bad)}")
        try:
            stage1, stage2, _ = self.simulate(x)
        except (FloatingPointError, ValueError, ZeroDivisionError) as exc:
            log.warning("bending run failed: %s", exc)
            return RunResult.failure(n_t, f"error: {exc}")
        if stage1["status"] != OK or stage2["status"] != OK:
            which = "stage 1" if stage1["status"] != OK else "stage 2"
            return RunResult.failure(n_t, f"{which} did not converge (step below dt_min)")
        curve = np.asarray(stage1["curve"], dtype=np.float64)
        angles = np.array([stage1["angle"], stage2["angle"]], dtype=np.float64)
        if not (np.all(np.isfinite(curve)) and np.all(np.isfinite(angles))):
            return RunResult.failure(n_t, "non-finite output")
        info = {"steps": float(stage1["steps"] + stage2["steps"]),
                "iterations": float(stage1["iterations"] + stage2["iterations"]),
                "cuts": float(stage1["cuts"] + stage2["cuts"]),
                "seconds": float(stage1["seconds"] + stage2["seconds"]),
                "release_force": float(stage1["release_force"])}
        return RunResult(curve, angles, ok=True, info=info)

    def simulate(self, x: FloatArray) -> tuple[dict[str, Any], dict[str, Any], Sheet]:
        """Run both stages; returns per-stage records (with histories) and the final sheet."""
        ix, g, d = self._ix, self.geometry, self.disc
        thick = float(x[ix["thickness"]])
        material = Material(yield_stress=float(x[ix["yield_stress"]]),
                            log_rate=float(x[ix["log_rate"]]),
                            rate_exponent=float(x[ix["rate_exponent"]]))
        mu_tf = float(x[ix["friction_tool_flap"]])
        sheet = Sheet.straight(g.x_root, g.x_tip, 0.5 * thick, d.n_elements, thick,
                               d.n_layers, d.n_gauss)
        crank_par = [0.5 * g.stroke, g.rod, g.omega]
        # ---- stage 1
        tools1 = make_toolset([
            ("die", 0, -1, g.die1()), ("holder", 0, +1, g.holder(thick)),
            ("punch", 1, +1, g.punch1(float(x[ix["punch_end_distance"]]),
                                      float(x[ix["horizontal_alignment"]]),
                                      float(x[ix["vertical_alignment"]])))])
        t_rel = g.release_time()
        grid = np.asarray(self.spec.time, dtype=np.float64)
        targets1 = np.r_[grid, np.linspace(grid[-1], t_rel, 8)[1:]]
        press1 = np.array([float(x[ix["press_stiffness"]]) / g.width,
                           float(x[ix["friction_tool_tool"]]), 1.0, *crank_par])
        tic = time.perf_counter()
        tau = math.radians(d.rate_window) / g.omega
        h1 = solve(sheet, material, tools1, targets1, d, dt_max=d.dt_max1, rate_tau=tau,
                   mu=np.full(3, mu_tf), penalty=g.penalty, smooth=g.smooth, press=press1)
        s1: dict[str, Any] = {"status": h1.status, "history": h1, "tools": tools1,
                              "curve": h1.force[:grid.size, 0] * g.width,
                              "angle": flap_angle(sheet, g.angle_length),
                              "release_force": h1.force[-1, 0] * g.width,
                              "steps": int(h1.counters[0]), "iterations": int(h1.counters[1]),
                              "cuts": int(h1.counters[2]),
                              "seconds": time.perf_counter() - tic}
        if h1.status != OK:
            return s1, {"status": -1}, sheet
        # ---- stage 2
        u = float(x[ix[CONTROL]]) if CONTROL in ix else 0.0
        t2 = g.release_time(g.release_height2)
        tools2 = make_toolset([("die", 0, -1, g.die2()), ("holder", 0, +1, g.holder(thick)),
                               ("punch", 1, +1, g.punch2(u))])
        targets2 = np.linspace(-t2, t2, 21)
        press2 = np.array([0.0, 0.0, 1.0, *crank_par])
        tic = time.perf_counter()
        h2 = solve(sheet, material, tools2, targets2, d, dt_max=d.dt_max2, rate_tau=tau,
                   mu=np.full(3, mu_tf), penalty=g.penalty, smooth=g.smooth, press=press2)
        s2: dict[str, Any] = {"status": h2.status, "history": h2, "tools": tools2,
                              "angle": flap_angle(sheet, g.angle_length),
                              "steps": int(h2.counters[0]), "iterations": int(h2.counters[1]),
                              "cuts": int(h2.counters[2]),
                              "seconds": time.perf_counter() - tic}
        return s1, s2, sheet
