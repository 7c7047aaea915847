"""Figures of the foundation pieces (matplotlib, imported lazily: extra ``plot``)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from formtwin.deviation import DeviationModel
from formtwin.spec import ProcessSpec

FloatArray = NDArray[np.float64]


def pyplot() -> Any:
    """``matplotlib.pyplot`` on the headless Agg backend (extra ``plot``, imported lazily)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_deviation(spec: ProcessSpec, curve: FloatArray, path: str | Path,
                   amount: float = 0.2) -> Path:
    """Effect of each deviation knot on ``curve`` (n_t,) N, as in the paper's Fig. 1.

    One panel per knot: the curve, and the curve with that knot's force scaling and
    speed scaling set to ``-amount`` and ``+amount``. Writes ``path`` (PNG/PDF/SVG).
    """
    plt = pyplot()

    g = DeviationModel.from_spec(spec)
    k = spec.deviation.n_knots
    t_ms = spec.time * 1e3
    fig, axes = plt.subplots(2, k, figsize=(3.2 * k, 5.5), sharex=True, sharey=True)
    for row, (kind, offset) in enumerate((("force scaling", 0), ("speed scaling", k))):
        for j in range(k):
            ax = axes[row, j]
            ax.plot(t_ms, curve, color="black", lw=1.5, label="model z~")
            for sign, style in ((-1, "--"), (1, ":")):
                theta_d = np.zeros(2 * k)
                theta_d[offset + j] = sign * amount
                ax.plot(t_ms, g.apply(curve, theta_d)[0], style, color="tab:red" if sign > 0
                        else "tab:blue", label=f"{sign * amount:+.0%}")
            ax.axvline(spec.deviation.knots[j] * 1e3, color="grey", lw=0.6)
            ax.set_title(f"{kind}, knot {j + 1}", fontsize=9)
            if row == 1:
                ax.set_xlabel("time [ms]")
        axes[row, 0].set_ylabel("punch force [N]")
    axes[0, 0].legend(fontsize=8)
    fig.suptitle("Deviation model z = g(z~, theta_d): effect of each knot (cf. paper Fig. 1)")
    fig.tight_layout()
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=120)
    plt.close(fig)
    return out
