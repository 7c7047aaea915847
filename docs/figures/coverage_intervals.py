"""Make docs/figures/coverage_intervals.png: coverage of the 90 % intervals (7 states, 2
angles) per series with the particles' std, the sandwich, the calibrated floors and the
fit-gated floors, from
benchmarks/results/bench_model_error.json (repetition 0 of every dataset, same runs).

    python docs/figures/coverage_intervals.py [bench_model_error.json]
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

from formtwin.figures import pyplot

SERIES = ("series1", "series3", "series5", "series6")
LABELS = ["yield", "log rate", "rate exp.", "thickness", "fr. tool", "fr. flap",
          "punch end", "angle 1", "angle 2"]


def main() -> None:
    """Read the benchmark JSON and write the figure next to this script."""
    path = Path(sys.argv[1] if len(sys.argv) > 1 else
                "benchmarks/results/bench_model_error.json")
    fig_data = json.loads(path.read_text())["figures"]
    default = fig_data["intervals"]
    blocks = {default: None}
    for name in ("cloud", "calibrated", "calibrated_fit", "sandwich"):
        key = f"intervals_{name}_option"
        if key in fig_data:
            blocks[name] = fig_data[key]["coverage_states_angles"]
    any_block = next(b for b in blocks.values() if b is not None)
    plt = pyplot()
    fig, axes = plt.subplots(1, len(SERIES), figsize=(14, 3.6), sharey=True,
                             layout="constrained")
    order = [n for n in ("cloud", "sandwich", "calibrated", "calibrated_fit") if n in blocks]
    width = 0.8 / len(order)
    x = np.arange(len(LABELS))
    for ax, s in zip(axes, SERIES, strict=True):
        for j, name in enumerate(order):
            b = blocks[name]
            vals = any_block[s]["default"] if b is None else b[s][f"intervals_{name}"]
            ax.bar(x + j * width, vals, width, label=name + (" (default)" if b is None else ""),
                   color=f"C{j}")
        ax.axhspan(0.8, 0.97, color="0.9", zorder=0)
        ax.axhline(0.9, color="k", lw=0.8, ls="--")
        ax.set_xticks(x + 0.4 - width / 2, LABELS, rotation=60, fontsize=8)
        ax.set_title(s.replace("series", "series "))
        ax.set_ylim(0, 1.02)
    axes[0].set_ylabel("coverage of the 90 % interval")
    axes[0].legend(fontsize=8, loc="lower left")
    out = Path(__file__).with_suffix(".png")
    fig.savefig(out, dpi=110)
    print(out)


if __name__ == "__main__":
    main()
