"""Figures of the bending model: ``formtwin plot bending`` and ``formtwin plot sensitivity``.

Matplotlib is imported lazily (the ``plot`` extra).
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from formtwin.figures import pyplot
from formtwin.physics.bending.geometry import ToolSet, tool_outline
from formtwin.physics.bending.model import BendingModel, History, Sheet

FloatArray = NDArray[np.float64]
log = logging.getLogger(__name__)

_TOOL_COLOURS = {"die": "0.55", "holder": "0.75", "punch": "tab:blue"}


def _sheet_outline(X: FloatArray, u: FloatArray, thickness: float) -> FloatArray:
    """Closed outline ``(m, 2)`` of the sheet (both surfaces) for displacements ``u``."""
    uu = u.reshape(-1, 3)
    pos = X + uu[:, :2]
    # surface normal from the nodal rotation (initial normal is +y)
    nrm = np.stack([-np.sin(uu[:, 2]), np.cos(uu[:, 2])], axis=1)
    top = pos + 0.5 * thickness * nrm
    bot = pos - 0.5 * thickness * nrm
    return np.vstack([top, bot[::-1], top[:1]])


def draw_state(ax: Any, sheet: Sheet, tools: ToolSet, hist: History, j: int,
               colour: str = "tab:red") -> None:
    """Draw the tools (punch at its recorded position) and the sheet at record ``j``."""
    for k, name in enumerate(tools.names):
        dy = hist.force[j, 3] if tools.owner[k] == 1 else 0.0
        pts = tool_outline(tools, k, dy)
        ax.plot(pts[:, 0], pts[:, 1], color=_TOOL_COLOURS.get(name, "k"), lw=1.2)
    out = _sheet_outline(sheet.X, hist.u[j], sheet.thickness)
    ax.fill(out[:, 0], out[:, 1], color=colour, alpha=0.35, lw=0)
    ax.plot(out[:, 0], out[:, 1], color=colour, lw=0.6)


def plot_bending(model: BendingModel, inputs: FloatArray, out: str | Path) -> Path:
    """Tools and deformed flap at several instants of both stages, and the stage-1 force.

    Parameters
    ----------
    model
        The bending model.
    inputs : (n_run_inputs,)
        Input point ``(x, theta, u)`` in internal units.
    out
        Image file to write.
    """
    plt = pyplot()

    s1, s2, sheet = model.simulate(np.asarray(inputs, dtype=np.float64))
    h1: History = s1["history"]
    t_ms = 1e3 * h1.t
    picks1 = [int(np.argmin(abs(t_ms - v))) for v in (-50.0, -30.0, -10.0, 0.0)]
    picks1.append(len(h1.t) - 1)
    fig, axes = plt.subplots(2, 4, figsize=(15, 7.5))
    for ax, j in zip(axes[0, :3], picks1[1:4], strict=True):
        draw_state(ax, sheet, s1["tools"], h1, j)
        force = h1.force[j, 0] * model.geometry.width
        ax.set_title(f"stage 1, t = {t_ms[j]:.0f} ms, F = {force:.0f} N")
    ax = axes[0, 3]
    ax.plot(1e3 * model.spec.time, s1["curve"], color="k")
    ax.set_xlabel("time (ms)")
    ax.set_ylabel("punch force (N)")
    ax.set_title("stage-1 force (spring force of the press)")
    ax.grid(alpha=0.3)
    draw_state(axes[1, 0], sheet, s1["tools"], h1, picks1[-1], colour="tab:green")
    axes[1, 0].set_title(f"after stage 1 (springback): {s1['angle']:.2f} deg")
    if "history" in s2:
        h2: History = s2["history"]
        n2 = len(h2.t)
        for ax, j in zip(axes[1, 1:], (n2 // 4, n2 // 2, n2 - 1), strict=True):
            draw_state(ax, sheet, s2["tools"], h2, j,
                       colour="tab:green" if j == n2 - 1 else "tab:red")
            ax.set_title(f"stage 2, t = {1e3 * h2.t[j]:.0f} ms")
        axes[1, 3].set_title(f"after stage 2 (springback): {s2['angle']:.2f} deg")
    for ax in list(axes[0, :3]) + list(axes[1, :]):
        ax.set_aspect("equal")
        ax.set_xlim(-0.7, 2.6)
        ax.set_ylim(-2.4, 1.6)
        ax.set_xlabel("x (mm)")
        ax.set_ylabel("y (mm)")
    fig.suptitle("formtwin.physics.bending: two-stage flap bending (tools as rigid lines)")
    fig.tight_layout()
    path = Path(out)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_sensitivity(model: BendingModel, out: str | Path) -> Path:
    """Stage-1 force of each run input (Table 1 and the press setting) at its minimum and
    maximum (others central).

    The centre is :meth:`BendingModel.centre`; each panel's title gives the two bend angles
    at the minimum and the maximum.
    """
    plt = pyplot()

    spec = model.spec
    centre = model.centre()
    base = model.run(centre)
    t_ms = 1e3 * spec.time
    box = spec.run_inputs
    n_col = -(-len(box) // 2)
    fig, axes = plt.subplots(2, n_col, figsize=(3.8 * n_col, 7.5), sharex=True)
    for ax in axes.ravel()[len(box):]:
        ax.set_visible(False)
    for ax, var in zip(axes.ravel(), box, strict=False):
        i = box.index[var.name]
        ax.plot(t_ms, base.curve, color="0.4", ls="--", lw=1, label="centre")
        angles = []
        for value, colour, tag in ((var.lo, "tab:blue", "min"), (var.hi, "tab:red", "max")):
            x = centre.copy()
            x[i] = value
            r = model.run(x)
            if not r.ok:
                log.warning("sensitivity run %s=%g failed: %s", var.name, value, r.reason)
                continue
            shown = value / var.scale
            ax.plot(t_ms, r.curve, color=colour, lw=1.3, label=f"{tag} {shown:g} {var.unit}")
            angles.append(f"{r.angles[0]:.2f}/{r.angles[1]:.2f}")
        ax.set_title(f"{var.label}\nangles (deg) {' -> '.join(angles)}", fontsize=9)
        ax.legend(fontsize=7, loc="upper left")
        ax.grid(alpha=0.3)
    for ax in axes[1]:
        ax.set_xlabel("time (ms)")
    for ax in axes[:, 0]:
        ax.set_ylabel("punch force (N)")
    fig.suptitle("formtwin.physics.bending: each Table-1 input and the stage-2 setting from "
                 "min to max, the others at the centre")
    fig.tight_layout()
    path = Path(out)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path
