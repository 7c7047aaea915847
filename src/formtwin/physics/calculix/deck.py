"""The CalculiX input deck of the stage-1 process (plane strain, rigid tools, press spring).

The deck is formtwin's own process (:mod:`formtwin.physics.bending.geometry`, ``.material``):

- sheet: CPE8R (plane strain, reduced integration), 1 mm thick section, so forces are per
  mm of width; elastic ``E, nu``, von Mises plasticity with the hardening table
  ``sigma_y h(eps_bar)``;
- rate dependence (Cowper-Symonds ``1 + (epsdot / epsdot0)^q``): a uniform factor in time,
  carried as the nodal *temperature* on which the plastic table depends linearly (tables at
  factors 1 and :data:`T_HI`), with ``epsdot = rate_per_speed * |ram speed|`` smoothed over the
  bending model's rate window (an assumption: CalculiX has no Cowper-Symonds law without a
  user subroutine);
- tools: rows of CPE4 whose nodes are all prescribed (die, blank holder) or tied to the
  punch's reference node (punch), i.e. rigid; their faces are the contact master surfaces;
- contact: surface-to-surface, linear pressure-overclosure penalty, Coulomb friction
  ``mu_tf`` on every tool;
- press: a SPRINGA of stiffness ``k / width`` between the punch's reference node and the ram
  node, which follows the crank ``c(t) - c(t_0)``; the ram's reaction is the spring force.

Time in the deck is ``t - t_0`` with ``t_0`` the first sample of the spec's time grid.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from io import StringIO

import numpy as np
from numpy.typing import NDArray

from formtwin.physics.bending.geometry import FlapGeometry
from formtwin.physics.bending.material import HARD_EPS, HARD_RATIO, Material
from formtwin.physics.calculix.mesh import SheetMesh, ToolMesh, sample_tool, sheet_mesh, tool_mesh

FloatArray = NDArray[np.float64]

#: rate factor of the upper plastic table (the "temperature" axis)
T_HI = 4.0


@dataclass(frozen=True)
class FeSettings:
    """Mesh, contact and increment settings of the CalculiX model.

    Attributes
    ----------
    n_thick
        CPE8R elements through the thickness.
    aspect
        Element length along the sheet / element thickness.
    tool_h, tool_arc_deg, tool_depth
        Tool facets: longest straight facet (mm), largest arc facet (deg), depth of the
        tool's element row (mm).
    contact_stiffness, stick_slope
        Pressure-overclosure slope (MPa/mm) and friction stick slope (MPa/mm).
    dt_max, dt_min
        Largest and smallest increment (s).
    rate_per_speed
        Representative equivalent strain rate of the bend per unit ram speed (1/mm).
    rate_window
        Crank angle (deg) over which that rate is smoothed (the bending model's window).
    """

    n_thick: int = 4
    aspect: float = 1.5
    tool_h: float = 0.05
    tool_arc_deg: float = 4.0
    tool_depth: float = 0.05
    contact_stiffness: float = 1.0e6
    stick_slope: float = 1.0e5
    dt_max: float = 1.0e-3
    dt_min: float = 1.0e-8
    rate_per_speed: float = 0.1
    rate_window: float = 2.7

    def n_along(self, geometry: FlapGeometry, thickness: float) -> int:
        """Elements along the sheet for a given thickness."""
        le = self.aspect * thickness / self.n_thick
        return max(2, math.ceil((geometry.x_tip - geometry.x_root) / le))


@dataclass(frozen=True)
class ProcessPoint:
    """The physical inputs of one run (internal units: mm, N, s, MPa)."""

    material: Material
    thickness: float
    mu_tool_tool: float
    mu_tool_flap: float
    gap: float
    dx: float
    dy: float
    press_stiffness: float


def ram_height(t: FloatArray, g: FlapGeometry) -> tuple[FloatArray, FloatArray]:
    """Ram height above bottom dead centre ``c(t)`` (mm) and its speed (mm/s), ``t`` in s.

    The crank with connecting rod of :func:`formtwin.physics.bending.assembly.crank`.
    """
    R, L, w = 0.5 * g.stroke, g.rod, g.omega
    a = w * np.asarray(t, dtype=np.float64)
    sa, ca = np.sin(a), np.cos(a)
    root = np.sqrt(L * L - (R * sa) ** 2)
    return R * (1.0 - ca) + L - root, R * w * sa + R * R * w * sa * ca / root


def rate_factor(t: FloatArray, g: FlapGeometry, material: Material,
                s: FeSettings) -> FloatArray:
    """Cowper-Symonds factor ``1 + (epsdot / epsdot0)^q`` at times ``t`` (s, increasing).

    ``epsdot = rate_per_speed * |c'(t)|`` smoothed exponentially over ``rate_window``.
    """
    _, v = ram_height(t, g)
    tau = math.radians(s.rate_window) / g.omega
    rate = s.rate_per_speed * np.abs(v)
    sm = np.empty_like(rate)
    sm[0] = rate[0]
    for k in range(1, rate.size):
        a = 1.0 - math.exp(-(t[k] - t[k - 1]) / tau) if tau > 0 else 1.0
        sm[k] = sm[k - 1] + a * (rate[k] - sm[k - 1])
    if not material.rate:
        return np.ones_like(sm)
    out: FloatArray = 1.0 + (sm / 10.0**material.log_rate) ** material.rate_exponent
    return out


def _fmt_rows(rows: NDArray[np.generic], per_line: int = 8) -> str:
    """Comma-separated numbers, at most ``per_line`` a line (CalculiX's 16-entry limit)."""
    flat = [f"{v:.10g}" if isinstance(v, float | np.floating) else str(v)
            for v in np.ravel(rows)]
    return "\n".join(", ".join(flat[i:i + per_line]) for i in range(0, len(flat), per_line))


def _nodes(out: StringIO, nset: str, ids: NDArray[np.int64], xy: FloatArray) -> None:
    out.write(f"*NODE, NSET={nset}\n")
    for i, (x, y) in zip(ids, xy, strict=True):
        out.write(f"{i}, {x:.10g}, {y:.10g}\n")


def _elements(out: StringIO, kind: str, elset: str, ids: NDArray[np.int64],
              conn: NDArray[np.int64]) -> None:
    out.write(f"*ELEMENT, TYPE={kind}, ELSET={elset}\n")
    for e, c in zip(ids, conn, strict=True):
        out.write(f"{e}, " + ", ".join(str(n) for n in c) + "\n")


def _set(out: StringIO, kind: str, name: str, ids: NDArray[np.int64]) -> None:
    out.write(f"*{kind}, {kind}={name}\n{_fmt_rows(np.asarray(ids))}\n")


def _surface(out: StringIO, name: str, faces: list[tuple[int, int]]) -> None:
    out.write(f"*SURFACE, NAME={name}, TYPE=ELEMENT\n")
    for e, f in faces:
        out.write(f"{e}, S{f}\n")


def _node_surface(out: StringIO, name: str, ids: NDArray[np.int64]) -> None:
    out.write(f"*SURFACE, NAME={name}, TYPE=NODE\n" + "\n".join(str(i) for i in ids) + "\n")


def time_at_height(h: float, g: FlapGeometry) -> float:
    """Time (s) after bottom dead centre at which the ram is ``h`` mm above it."""
    lo, hi = 0.0, 0.5 * math.pi / g.omega
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if ram_height(np.array([mid]), g)[0][0] < h else (lo, mid)
    return 0.5 * (lo + hi)


def stage2_tools(g: FlapGeometry, u: float) -> tuple[tuple[FloatArray, FloatArray],
                                                     tuple[FloatArray, FloatArray], float]:
    """Stage-2 die and punch (at bottom dead centre for the depth setting ``u``, mm) and the
    ram height (mm) at which stage 2 starts and ends, as the bending model defines them."""
    try:
        punch = g.punch2(u)  # type: ignore[call-arg, unused-ignore]
    except TypeError:  # a geometry without the stage-2 setting
        if u != 0.0:
            raise ValueError("this FlapGeometry has no stage-2 depth setting u") from None
        punch = g.punch2()
    return g.die2()[0], punch[0], float(getattr(g, "release_height2", 3.0))


@dataclass(frozen=True)
class ProcessDeck:
    """A deck: its text, the sheet mesh, the tools, the stage-1 output times (s, from
    ``t0``), whether stage 2 is in it and the deck's end time (s, CalculiX's total time)."""

    text: str
    sheet: SheetMesh
    tools: tuple[ToolMesh, ...]
    times: FloatArray
    t0: float
    stage2: bool
    end: float


def _tool_surfaces(p: ProcessPoint, g: FlapGeometry, s: FeSettings, c0: float, stage2: bool,
                   u: float) -> dict[str, FloatArray]:
    """Working surfaces ``(m, 2)`` of the tools: the die's top and radius up to the end of
    the stage-1 arc (``DIE``, both stages), the stage-1 die face (``DIEF1``, dropped after
    stage 1), the stage-1 punch (lifted to ``c0`` above bottom dead centre) and, with
    ``stage2``, the stage-2 die's arc beyond 45 deg and vertical face (``DIEF2``, inside
    die 1 during stage 1) and the stage-2 punch (``release_height2`` up)."""
    x_split = g.r_die * math.sin(math.pi / 4)
    die1 = sample_tool(*g.die1()[0], s.tool_h, s.tool_arc_deg, 1.5, 3.5)
    k = int(np.argmin(np.abs(die1[:, 0] - x_split)))
    punch1 = sample_tool(*g.punch1(p.gap, p.dx, p.dy)[0], s.tool_h, s.tool_arc_deg, 1.0, 1.0)
    out = {"DIE": die1[:k + 1], "DIEF1": die1[k:], "PUNCH": punch1 + np.array([0.0, c0])}
    if stage2:
        (pts, radii), punch2, h2 = stage2_tools(g, u)
        die2 = sample_tool(pts, radii, s.tool_h, s.tool_arc_deg, 1.5, 3.0)
        out["DIEF2"] = np.vstack([die1[k], die2[die2[:, 0] > die1[k, 0] + 1e-9]])
        out["PUNCH2"] = sample_tool(*punch2, s.tool_h, s.tool_arc_deg, 1.0, 1.5) + [0.0, h2]
    return out


def process_deck(p: ProcessPoint, g: FlapGeometry, s: FeSettings, grid: FloatArray,
                 stage2: bool = True, u: float = 0.0) -> ProcessDeck:
    """The deck of the process: stage 1 (load to bottom dead centre, unload until the ram is
    at ``g.release_height``: springback; outputs at the grid times ``grid`` (s) and the end),
    then, with ``stage2``, the stage-1 die face drops away (step 2) and the stage-2 punch runs on
    the crank from ``release_height2`` above bottom dead centre down (its nose to
    ``punch2_bdc - u``) and back (step 3); the stage-2 die face lies inside die 1 until then."""
    t = p.thickness
    sheet = sheet_mesh(g.x_root, g.x_tip, t, s.n_along(g, t), s.n_thick)
    t0 = float(grid[0])
    t_end = g.release_time()
    c0 = float(ram_height(np.array([t0]), g)[0][0])
    tools = []
    first_node = int(sheet.node_ids.max()) + 1
    first_el = sheet.elements.shape[0] + 1
    for name, surf in _tool_surfaces(p, g, s, c0, stage2, u).items():
        tools.append(tool_mesh(name, surf, s.tool_depth, first_node, first_el))
        first_node += tools[-1].node_ids.size
        first_el += tools[-1].element_ids.size
    # ids stay compact: CalculiX sizes its arrays by the largest node number
    ref_node, ram_node, spring_el = first_node, first_node + 1, first_el
    times = np.r_[grid, t_end] - t0
    names = [tm.name for tm in tools]
    out = StringIO()
    out.write("*HEADING\nformtwin flap bending (plane strain)\n")
    _nodes(out, "NSHEET", sheet.node_ids, sheet.nodes)
    _elements(out, "CPE8R", "ESHEET", np.arange(1, sheet.elements.shape[0] + 1), sheet.elements)
    for tm in tools:
        _nodes(out, "N" + tm.name, tm.node_ids, tm.nodes)
        _elements(out, "CPE4", "E" + tm.name, tm.element_ids, tm.elements)
    ref = np.array([g.punch1_x_right + 1.0, 3.0 + c0])
    _nodes(out, "NREF", np.array([ref_node]), ref[None, :])
    _nodes(out, "NRAM", np.array([ram_node]), (ref + [0.0, 1.0])[None, :])
    out.write(f"*ELEMENT, TYPE=SPRINGA, ELSET=ESPRING\n{spring_el}, {ref_node}, "
              f"{ram_node}\n*SPRING, ELSET=ESPRING\n{p.press_stiffness / g.width:.10e}\n")
    x, y = sheet.nodes[:, 0], sheet.nodes[:, 1]
    _set(out, "NSET", "NCLAMP", sheet.node_ids[x <= g.x_holder + 1e-9])
    _set(out, "NSET", "NMID", sheet.mid)
    out.write("*ELSET, ELSET=ETOOLS\n" + ", ".join("E" + n for n in names) + "\n"
              "*NSET, NSET=NALL\nNSHEET, " + ", ".join("N" + n for n in names) + "\n")
    free = x > g.x_holder + 1e-9
    top = free & ((np.abs(y - t) < 1e-9) | (np.abs(x - g.x_tip) < 1e-9))
    _node_surface(out, "SBOT", sheet.node_ids[free & (np.abs(y) < 1e-9)])
    _node_surface(out, "STOP", sheet.node_ids[top & (x > 0.5 * g.x_holder)])
    for tm in tools:
        _surface(out, "M" + tm.name, [(int(e), 4) for e in tm.element_ids])
    _material(out, p.material)
    out.write(f"*SURFACE INTERACTION, NAME=SI\n*SURFACE BEHAVIOR, PRESSURE-OVERCLOSURE=LINEAR\n"
              f"{s.contact_stiffness:.10e}, 1., 1.e-3\n")
    if p.mu_tool_flap > 0:
        out.write(f"*FRICTION\n{p.mu_tool_flap:.10g}, {s.stick_slope:.10e}\n")
    for tm in tools:
        slave = "SBOT" if tm.name.startswith("DIE") else "STOP"
        out.write(f"*CONTACT PAIR, INTERACTION=SI, TYPE=NODE TO SURFACE\n{slave}, M{tm.name}\n")
    # rigid punch: every node follows the reference node vertically
    out.write("*EQUATION\n")
    for n in tools[names.index("PUNCH")].node_ids:
        out.write(f"2\n{n}, 2, 1., {ref_node}, 2, -1.\n")
    fixed = "".join(f"N{n}, 1, 2\n" for n in names if n != "PUNCH")
    out.write(f"*BOUNDARY\nNCLAMP, 1, 2\n{fixed}NPUNCH, 1, 1\n"
              f"{ref_node}, 1, 1\n{ref_node}, 3, 3\n{ram_node}, 1, 1\n{ram_node}, 3, 3\n")
    ta = np.linspace(0.0, times[-1], max(2, math.ceil(times[-1] / 5e-4) + 1))
    c, _ = ram_height(ta + t0, g)
    factor = rate_factor(ta + t0, g, p.material, s)
    _amplitude(out, "ARAM", ta, c - c0)
    _amplitude(out, "ARATE", ta, factor)
    out.write(f"*INITIAL CONDITIONS, TYPE=TEMPERATURE\nNALL, {factor[0]:.10g}\n")
    out.write("*TIME POINTS, NAME=TP\n" + _fmt_rows(times) + "\n")
    steps2 = _stage2(out, p, g, s, u, ram_node, float(c[-1] - c0)) if stage2 else ""
    # one set of time points per step: CalculiX uses the last one given for all prints
    inc = f"{min(s.dt_max, 2e-4):.6g}, {{:.10g}}, {s.dt_min:.6g}, {s.dt_max:.6g}\n"
    out.write("*STEP, NLGEOM, INC=100000\n*STATIC\n" + inc.format(times[-1])
              + f"*BOUNDARY, AMPLITUDE=ARAM\n{ram_node}, 2, 2, 1.\n"
              "*TEMPERATURE, AMPLITUDE=ARATE\nNALL, 1.\n"
              "*NODE PRINT, NSET=NRAM, TIME POINTS=TP\nRF\n"
              "*NODE PRINT, NSET=NPUNCH, TOTALS=ONLY, TIME POINTS=TP\nRF\n"
              "*NODE PRINT, NSET=NMID, TIME POINTS=TP\nU\n*END STEP\n")
    out.write(steps2)
    end = times[-1] + (1e-3 + 2 * time_at_height(stage2_tools(g, u)[2], g) if stage2 else 0.0)
    return ProcessDeck(out.getvalue(), sheet, tuple(tools), times, t0, stage2, float(end))


def _material(out: StringIO, m: Material) -> None:
    """Sheet material: plastic tables at rate factors 1 and :data:`T_HI` (linear in it)."""
    ratio = HARD_RATIO if m.hardening else np.ones_like(HARD_RATIO)
    out.write(f"*MATERIAL, NAME=SHEET\n*ELASTIC\n{m.E:.10g}, {m.nu:.10g}\n*PLASTIC\n")
    for level in (1.0, T_HI):
        for e, r in zip(HARD_EPS, ratio, strict=True):
            out.write(f"{level * m.yield_stress * r:.10g}, {e:.10g}, {level:.10g}\n")
    out.write(f"*MATERIAL, NAME=TOOL\n*ELASTIC\n{m.E:.10g}, {m.nu:.10g}\n")
    out.write("*SOLID SECTION, ELSET=ESHEET, MATERIAL=SHEET\n1.\n"
              "*SOLID SECTION, ELSET=ETOOLS, MATERIAL=TOOL\n1.\n")


def _amplitude(out: StringIO, name: str, t: FloatArray, v: FloatArray) -> None:
    out.write(f"*AMPLITUDE, NAME={name}\n" + _fmt_rows(np.column_stack([t, v])) + "\n")


def _stage2(out: StringIO, p: ProcessPoint, g: FlapGeometry, s: FeSettings, u: float,
            ram_node: int, ram_end: float) -> str:
    """Writes stage 2's amplitudes (which precede all steps) and returns its steps.

    Step 2: the stage-1 die face drops 3 mm, the stage-1 ram rises 5 mm more. Step 3: the
    stage-2 punch on the crank from ``release_height2`` down to bottom dead centre and back.
    """
    _, _, h2 = stage2_tools(g, u)
    t2 = time_at_height(h2, g)
    ta = np.linspace(-t2, t2, max(2, math.ceil(2 * t2 / 5e-4) + 1))
    c, _ = ram_height(ta, g)
    _amplitude(out, "ARAM2", ta + t2, c - c[0])
    _amplitude(out, "ARATE2", ta + t2, rate_factor(ta, g, p.material, s))
    out.write(f"*TIME POINTS, NAME=TP3\n{2 * t2:.10g}\n")
    inc = f"{min(s.dt_max, 2e-4):.6g}, {{:.10g}}, {s.dt_min:.6g}, {s.dt_max:.6g}\n"
    return ("*STEP, NLGEOM, INC=100000\n*STATIC\n" + inc.format(1e-3)
            + f"*BOUNDARY\nNDIEF1, 2, 2, -3.\n{ram_node}, 2, 2, {ram_end + 5.0:.10g}\n"
            "*TEMPERATURE\nNALL, 1.\n*END STEP\n"
            "*STEP, NLGEOM, INC=100000\n*STATIC\n" + inc.format(2 * t2)
            + "*BOUNDARY, AMPLITUDE=ARAM2\nNPUNCH2, 2, 2, 1.\n"
            "*TEMPERATURE, AMPLITUDE=ARATE2\nNALL, 1.\n"
            "*NODE PRINT, NSET=NMID, TIME POINTS=TP3\nU\n*END STEP\n")
