"""Geometry of the two-stage flap bending model: every dimension is an assumption.

The demonstrator's tools are not public; this module designs a plausible set (mm, the
sheet's lower surface at ``y = 0`` before forming, ``x = 0`` where the die radius starts).

Stage 1 (measured): the sheet is clamped between the die top (``y <= 0``, ``x <= 0``) and
a blank holder on its upper surface; the flap sticks out over the die radius ``r_die``
(centre ``(0, -r_die)``), after which the die face descends at 45 deg. A punch with a
45 deg face parallel to the die face, a nose radius at its lower end, comes down on a crank
and wipes the flap around the die radius. At bottom dead centre of the crank (``t = 0``)
and zero alignment, its face is at the *punch end distance* from the die face (normal
gap); just above the sheet thickness, so the flap is pressed flat ("set") against the die
face. Horizontal alignment moves the punch by ``+x`` (away from the die face), vertical
alignment by ``+y``.

Stage 2 (angle only), as the line does it: the same clamp; the die radius continues to a
vertical face; a punch with a vertical face at ``gap2`` from the die's vertical face
(``gap2`` well above the sheet thickness: the flap is never ironed between the faces) and
a nose radius comes down on the same crank to a set depth: its lowest point reaches
``punch2_bdc - u`` at bottom dead centre, ``u`` the press setting (stage-2 depth offset).
The nose stops on the flap (stroke-controlled, like air bending), so the final angle is
the loaded angle at that depth minus the springback, and keeps the stage-1 shape, the
material and the thickness.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

S45 = math.sqrt(0.5)


@dataclass(frozen=True)
class FlapGeometry:
    """Dimensions (mm), press kinematics and contact settings of the demonstrator model.

    Attributes
    ----------
    x_root, x_tip
        Sheet ends: clamped root and free flap tip (the flap sticks out ``x_tip`` beyond the
        start of the die radius).
    r_die
        Die radius (both stages), centre ``(0, -r_die)``.
    x_holder, r_holder
        Blank-holder edge (its vertical face) and its corner radius.
    punch1_x_left, punch1_x_right, r_punch1_nose, r_punch1_heel
        Stage-1 punch: vertical faces at ``x_left, x_right`` bounding its 45 deg face, the
        nose radius at the lower (right) end and the heel radius at the upper (left) end.
    gap2, r_punch2_nose
        Stage-2 punch: normal gap between its vertical face and the die's vertical face
        (0.5 mm: a clearance of 0.2 mm above the 0.3 mm sheet), and its nose radius.
    punch2_bdc
        Height of the stage-2 punch's lowest point at bottom dead centre for the nominal
        setting ``u = 0``; the setting ``u`` (mm) lowers it to ``punch2_bdc - u``.
    release_height2
        Ram height above bottom dead centre at which stage 2 starts and ends.
    stroke, rod, strokes_per_min
        Crank: stroke (2 x crank radius), connecting rod length, rate.
    width
        Width of flap the press force acts on (the 2D model is per mm of width).
    release_height
        Ram height above bottom dead centre at which a stage ends (tools clear of the flap).
    penalty
        Contact penalty per unit contact length (N/mm^3, per mm of width); the same value
        is used for the tangential (stick) stiffness.
    smooth
        Penetration (mm) over which the normal contact force grows quadratically before
        it becomes linear (a smooth onset helps Newton when contacts open and close).
    angle_length
        Length of flap, from the tip, whose chord defines the bend angle.
    """

    x_root: float = -0.6
    x_tip: float = 2.0
    r_die: float = 0.4
    x_holder: float = -0.15
    r_holder: float = 0.1
    punch1_x_left: float = 0.3
    punch1_x_right: float = 2.2
    r_punch1_nose: float = 0.3
    r_punch1_heel: float = 0.1
    gap2: float = 0.5
    r_punch2_nose: float = 0.3
    punch2_bdc: float = -1.2
    release_height2: float = 3.0
    stroke: float = 20.0
    rod: float = 100.0
    strokes_per_min: float = 90.0
    width: float = 10.0
    release_height: float = 2.0
    penalty: float = 5.0e5
    smooth: float = 5.0e-4
    angle_length: float = 0.5

    @property
    def omega(self) -> float:
        """Crank angular speed (rad/s)."""
        return 2.0 * math.pi * self.strokes_per_min / 60.0

    def release_time(self, height: float | None = None) -> float:
        """Time (s) after bottom dead centre at which the ram is at ``height`` (mm; default
        ``release_height``)."""
        R, L = 0.5 * self.stroke, self.rod
        h = self.release_height if height is None else height
        # invert h = R (1 - cos a) + L - sqrt(L^2 - R^2 sin^2 a) by bisection on a
        lo, hi = 0.0, 0.5 * math.pi
        for _ in range(60):
            mid = 0.5 * (lo + hi)
            val = R * (1 - math.cos(mid)) + L - math.sqrt(L * L - (R * math.sin(mid)) ** 2)
            lo, hi = (mid, hi) if val < h else (lo, mid)
        return 0.5 * (lo + hi) / self.omega

    # ------------------------------------------------------------------ tools

    def die1(self) -> list[tuple[FloatArray, FloatArray]]:
        """Stage-1 die: top, radius, 45 deg face (polyline corners and corner radii)."""
        xc = self.r_die * math.tan(math.pi / 8)
        pts = np.array([[-5.0, 0.0], [xc, 0.0], [xc + 6 * S45, -6 * S45]])
        return [(pts, np.array([self.r_die]))]

    def die2(self) -> list[tuple[FloatArray, FloatArray]]:
        """Stage-2 die: top, radius, vertical face."""
        pts = np.array([[-5.0, 0.0], [self.r_die, 0.0], [self.r_die, -6.0]])
        return [(pts, np.array([self.r_die]))]

    def holder(self, thickness: float) -> list[tuple[FloatArray, FloatArray]]:
        """Blank holder resting on the sheet's upper surface ``y = thickness``."""
        pts = np.array([[self.x_holder, thickness + 3.0], [self.x_holder, thickness],
                        [-5.0, thickness]])
        return [(pts, np.array([self.r_holder]))]

    def punch1(self, gap: float, dx: float, dy: float) -> list[tuple[FloatArray, FloatArray]]:
        """Stage-1 punch at bottom dead centre: 45 deg face at normal ``gap`` from the die
        face, shifted by the alignment ``(dx, dy)``."""
        k = (self.r_die * (1 - S45) + gap) / S45  # face: x + y = k
        xl, xr = self.punch1_x_left, self.punch1_x_right
        pts = np.array([[xr, 3.0], [xr, k - xr], [xl, k - xl], [xl, 3.0]])
        pts = pts + np.array([dx, dy])
        return [(pts, np.array([self.r_punch1_nose, self.r_punch1_heel]))]

    def punch2(self, u: float = 0.0) -> list[tuple[FloatArray, FloatArray]]:
        """Stage-2 punch at bottom dead centre for the depth setting ``u`` (mm, + deeper)."""
        x0 = self.r_die + self.gap2
        y0 = self.punch2_bdc - u
        pts = np.array([[x0 + 3.0, y0], [x0, y0], [x0, y0 + 8.0]])
        return [(pts, np.array([self.r_punch2_nose]))]


def rounded_polyline(points: FloatArray, radii: FloatArray) -> list[tuple[int, list[float]]]:
    """Segments and fillet arcs of a polyline whose corners turn right (tool on the right).

    Parameters
    ----------
    points : (m, 2)
        Corner points; the tool lies to the right of the direction of travel.
    radii : (m - 2,)
        Fillet radius at each interior corner.

    Returns
    -------
    list of (type, data)
        ``(0, [x0, y0, x1, y1, 0, 0])`` for a segment and
        ``(1, [cx, cy, R, a0, a1, 0])`` for a convex arc spanning angles ``a0 <= a <= a1``.
    """
    prims: list[tuple[int, list[float]]] = []
    start = points[0].copy()
    for i in range(1, len(points) - 1):
        d_in = points[i] - points[i - 1]
        d_in = d_in / np.linalg.norm(d_in)
        d_out = points[i + 1] - points[i]
        d_out = d_out / np.linalg.norm(d_out)
        turn = math.atan2(d_in[0] * d_out[1] - d_in[1] * d_out[0], float(d_in @ d_out))
        if turn >= 0.0:
            raise ValueError(f"corner {i} of a tool turns left; tools must be convex")
        r = float(radii[i - 1])
        tl = r * math.tan(-0.5 * turn)
        t1 = points[i] - d_in * tl
        t2 = points[i] + d_out * tl
        centre = t1 + r * np.array([d_in[1], -d_in[0]])
        prims.append((0, [start[0], start[1], t1[0], t1[1], 0.0, 0.0]))
        a1 = math.atan2(t1[1] - centre[1], t1[0] - centre[0])
        a0 = math.atan2(t2[1] - centre[1], t2[0] - centre[0])
        if a1 < a0:
            a1 += 2.0 * math.pi
        prims.append((1, [centre[0], centre[1], r, a0, a1, 0.0]))
        start = t2
    prims.append((0, [start[0], start[1], points[-1][0], points[-1][1], 0.0, 0.0]))
    return prims


@dataclass(frozen=True)
class ToolSet:
    """Rigid tools as flat arrays for the kernels.

    ``ptype (n_p,)`` 0 segment / 1 arc, ``pdata (n_p, 6)``, ``tstart (n_tools + 1,)`` the
    primitive range of each tool, ``owner (n_tools,)`` 1 if the tool moves with the punch,
    ``face (n_tools,)`` the sheet face the tool touches (+1 upper, -1 lower), ``names`` for
    plots.
    """

    ptype: IntArray
    pdata: FloatArray
    tstart: IntArray
    owner: IntArray
    face: FloatArray
    names: tuple[str, ...]


def make_toolset(tools: list[tuple[str, int, int, list[tuple[FloatArray, FloatArray]]]]
                 ) -> ToolSet:
    """Flatten ``[(name, owner, face, [(points, radii), ...]), ...]`` into a
    :class:`ToolSet` (``face`` +1: the tool touches the sheet's upper face, -1 the lower)."""
    ptype: list[int] = []
    pdata: list[list[float]] = []
    tstart = [0]
    for _, _, _, chains in tools:
        for pts, radii in chains:
            for kind, data in rounded_polyline(pts, radii):
                ptype.append(kind)
                pdata.append(data)
        tstart.append(len(ptype))
    return ToolSet(np.array(ptype, dtype=np.int64), np.array(pdata, dtype=np.float64),
                   np.array(tstart, dtype=np.int64),
                   np.array([o for _, o, _, _ in tools], dtype=np.int64),
                   np.array([f for _, _, f, _ in tools], dtype=np.float64),
                   tuple(n for n, _, _, _ in tools))


def tool_outline(ts: ToolSet, k: int, dy: float = 0.0, n_arc: int = 12) -> FloatArray:
    """Points ``(m, 2)`` along tool ``k`` shifted by ``dy`` (for plotting)."""
    pts: list[tuple[float, float]] = []
    for j in range(ts.tstart[k], ts.tstart[k + 1]):
        d = ts.pdata[j]
        if ts.ptype[j] == 0:
            pts += [(d[0], d[1]), (d[2], d[3])]
        else:
            a = np.linspace(d[4], d[3], n_arc)
            pts += list(zip(d[0] + d[2] * np.cos(a), d[1] + d[2] * np.sin(a), strict=True))
    out = np.array(pts)
    out[:, 1] += dy
    return out
