"""Meshes of the CalculiX deck: the sheet (CPE8R) and the rigid tools (one row of CPE4).

Coordinates in mm as in :mod:`formtwin.physics.bending.geometry`: the sheet's lower
surface at ``y = 0`` before forming, ``x = 0`` where the die radius starts. Node and
element numbers start at 1 for the sheet; each tool gets its own block of numbers.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from formtwin.physics.bending.geometry import rounded_polyline

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


@dataclass(frozen=True)
class SheetMesh:
    """A structured CPE8R mesh of the sheet, ``n_along`` x ``n_thick`` elements.

    ``nodes (n_nodes, 2)`` with ids ``node_ids (n_nodes,)``; ``elements (n_el, 8)`` node ids
    (corners counter-clockwise, then mid-sides), element ids ``1..n_el`` row by row from the
    bottom layer; ``root`` the node ids on the clamped end; ``mid (2 n_along + 1,)`` the ids
    of the mid-thickness line from root to tip (``n_thick`` even) or of the line just below.
    """

    nodes: FloatArray
    node_ids: IntArray
    elements: IntArray
    n_along: int
    n_thick: int
    root: IntArray
    mid: IntArray

    def element_id(self, i: int, j: int) -> int:
        """Element id of column ``i`` (from the root) in layer ``j`` (from the bottom)."""
        return 1 + i + j * self.n_along

    def faces(self, which: str) -> list[tuple[int, int]]:
        """``(element id, face number)`` of the ``"bottom"``, ``"top"`` or ``"tip"`` faces."""
        if which == "bottom":
            return [(self.element_id(i, 0), 1) for i in range(self.n_along)]
        if which == "top":
            return [(self.element_id(i, self.n_thick - 1), 3) for i in range(self.n_along)]
        if which == "tip":
            return [(self.element_id(self.n_along - 1, j), 2) for j in range(self.n_thick)]
        raise ValueError(f"faces: unknown side {which!r}; use 'bottom', 'top' or 'tip'")

    def element_x(self, element_id: int) -> float:
        """Reference x (mm) of the centre of element ``element_id``."""
        corners = self.elements[element_id - 1, :4]
        return float(self.nodes[np.searchsorted(self.node_ids, corners), 0].mean())

    def node_index(self, node_id: int) -> int:
        """Row of ``nodes`` holding node ``node_id``."""
        return int(np.searchsorted(self.node_ids, node_id))


def sheet_mesh(x0: float, x1: float, thickness: float, n_along: int, n_thick: int) -> SheetMesh:
    """Structured CPE8R mesh of the strip ``[x0, x1] x [0, thickness]`` (uniform)."""
    if n_along < 1 or n_thick < 1:
        raise ValueError(f"sheet mesh: need n_along, n_thick >= 1, got {n_along}, {n_thick}")
    nx, ny = 2 * n_along + 1, 2 * n_thick + 1
    xs = np.linspace(x0, x1, nx)
    ys = np.linspace(0.0, thickness, ny)

    def nid(i: int, j: int) -> int:
        return 1 + i + j * nx

    used = np.ones((ny, nx), dtype=bool)
    used[1::2, 1::2] = False  # element centres: CPE8R has none
    jj, ii = np.nonzero(used)
    node_ids = np.array([nid(int(i), int(j)) for i, j in zip(ii, jj, strict=True)], dtype=np.int64)
    nodes = np.column_stack([xs[ii], ys[jj]])
    order = np.argsort(node_ids)
    node_ids, nodes = node_ids[order], nodes[order]
    elements = np.zeros((n_along * n_thick, 8), dtype=np.int64)
    for j in range(n_thick):
        for i in range(n_along):
            a, b = 2 * i, 2 * j
            elements[i + j * n_along] = [
                nid(a, b), nid(a + 2, b), nid(a + 2, b + 2), nid(a, b + 2),
                nid(a + 1, b), nid(a + 2, b + 1), nid(a + 1, b + 2), nid(a, b + 1)]
    root = np.array([nid(0, j) for j in range(ny)], dtype=np.int64)
    mid = np.array([nid(i, n_thick) for i in range(nx)], dtype=np.int64)
    return SheetMesh(nodes, node_ids, elements, n_along, n_thick, root, mid)


@dataclass(frozen=True)
class ToolMesh:
    """One rigid tool as a row of CPE4 elements along its working surface.

    ``nodes (n, 2)``, ids ``node_ids``; ``elements (m, 4)`` node ids; the contact face of
    every element is face 4 (its edge on the working surface).
    """

    name: str
    nodes: FloatArray
    node_ids: IntArray
    element_ids: IntArray
    elements: IntArray


def sample_tool(points: FloatArray, radii: FloatArray, h: float, arc_deg: float,
                keep_first: float, keep_last: float) -> FloatArray:
    """Points ``(m, 2)`` along a tool's rounded polyline (tool on the right).

    Straight pieces are cut into pieces of at most ``h`` (mm), arcs into pieces of at most
    ``arc_deg`` degrees; only the last ``keep_first`` mm of the first segment and the first
    ``keep_last`` mm of the last segment are kept (the far ends never touch the sheet).
    """
    prims = rounded_polyline(points, radii)
    out: list[FloatArray] = []
    last = len(prims) - 1
    for k, (kind, d) in enumerate(prims):
        if kind == 0:
            p0, p1 = np.array(d[:2]), np.array(d[2:4])
            length = float(np.linalg.norm(p1 - p0))
            u = (p1 - p0) / length
            if k == 0 and length > keep_first:
                p0, length = p1 - u * keep_first, keep_first
            if k == last and length > keep_last:
                p1, length = p0 + u * keep_last, keep_last
            n = max(1, math.ceil(length / h))
            s = np.linspace(0.0, 1.0, n + 1)[:, None]
            out.append(p0 + s * (p1 - p0))
        else:
            cx, cy, r, a0, a1 = d[:5]
            n = max(2, math.ceil(math.degrees(a1 - a0) / arc_deg))
            a = np.linspace(a1, a0, n + 1)  # clockwise: the tool turns right
            out.append(np.column_stack([cx + r * np.cos(a), cy + r * np.sin(a)]))
    pts = np.vstack(out)
    keep = np.r_[True, np.linalg.norm(np.diff(pts, axis=0), axis=1) > 1e-9]
    return np.asarray(pts[keep], dtype=np.float64)


def tool_mesh(name: str, surface: FloatArray, depth: float, first_node: int,
              first_element: int) -> ToolMesh:
    """A row of CPE4 elements of ``depth`` mm behind the surface points ``(m, 2)``."""
    tang = np.gradient(surface, axis=0)
    tang /= np.linalg.norm(tang, axis=1)[:, None]
    inward = np.column_stack([tang[:, 1], -tang[:, 0]])  # the tool lies on the right
    back = surface + depth * inward
    m = surface.shape[0]
    nodes = np.vstack([surface, back])
    node_ids = first_node + np.arange(2 * m, dtype=np.int64)
    s, b = node_ids[:m], node_ids[m:]
    # (p_i, q_i, q_i+1, p_i+1) is counter-clockwise; face 4 (p_i+1 -> p_i) is the surface
    elements = np.column_stack([s[:-1], b[:-1], b[1:], s[1:]])
    element_ids = first_element + np.arange(m - 1, dtype=np.int64)
    return ToolMesh(name, nodes, node_ids, element_ids, elements)
