"""Make docs/figures/data_flow.png: the data flow of formtwin, offline (spec -> DOE ->
physics runs -> dataset -> metamodel -> measurement model) and online (force curve ->
tracker -> estimates -> store, MQTT, live page, charts, controller).

    python docs/figures/data_flow.py [OUT.png]
"""

from __future__ import annotations

import sys
from pathlib import Path

from formtwin.figures import pyplot

#: (x, y, text, package) of each box; x, y the box centre in axes units
OFFLINE = [
    (0.11, 0.80, "process spec\n(TOML, Table 1)", "spec"),
    (0.11, 0.56, "design of experiments\n(2^11 corners + LHS)", "doe"),
    (0.11, 0.32, "physics model runs\n(processes or Dask)", "physics"),
    (0.36, 0.32, "DOE dataset\n(HDF5)", "dataset"),
    (0.36, 0.56, "metamodel\n(POD + RBF)", "metamodel"),
    (0.36, 0.80, "measurement model\n(K_MC, eq. 12)", "measurement"),
]
ONLINE = [
    (0.64, 0.80, "stroke: punch-force\ncurve (MQTT)", "service"),
    (0.64, 0.56, "tracker: particle filter\nover x, theta, theta_d", "tracker"),
    (0.64, 0.32, "estimates + intervals\n+ model health", "estimates"),
    (0.89, 0.56, "control charts\nand alarms", "monitoring"),
    (0.89, 0.32, "stage-2 setting\n(feedforward)", "control"),
    (0.89, 0.80, "store, MQTT out,\nlive page, report", "service / study"),
]
ARROWS = [(0, 1), (1, 2), (2, 3), (3, 4), (4, 5), (6, 7), (7, 8), (8, 9), (8, 10), (8, 11),
          (4, 7), (5, 7)]


def main() -> None:
    """Draw the diagram and write it to the path given (default: next to this script)."""
    out = Path(sys.argv[1]) if len(sys.argv) > 1 else Path(__file__).with_suffix(".png")
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(11, 5.2))
    ax.set_xlim(0, 1)
    ax.set_ylim(0.12, 1.0)
    ax.axis("off")
    ax.add_patch(plt.Rectangle((0.005, 0.17), 0.485, 0.78, fc="#f3f6fa", ec="#9aaabb"))
    ax.add_patch(plt.Rectangle((0.51, 0.17), 0.485, 0.78, fc="#f7f3ea", ec="#bba98a"))
    ax.text(0.02, 0.92, "offline, once per process", fontsize=11, weight="bold")
    ax.text(0.525, 0.92, "online, for every product", fontsize=11, weight="bold")
    boxes = OFFLINE + ONLINE
    for x, y, text, package in boxes:
        ax.text(x, y, text, ha="center", va="center", fontsize=9,
                bbox={"boxstyle": "round,pad=0.5", "fc": "white", "ec": "#333333"})
        ax.text(x, y - 0.095, f"formtwin.{package}" if "/" not in package else package,
                ha="center", va="center", fontsize=7, color="#555555", family="monospace")
    for a, b in ARROWS:
        (xa, ya, *_), (xb, yb, *_) = boxes[a], boxes[b]
        dx, dy = xb - xa, yb - ya
        # start and end at the box edges, not the centres
        sa = 0.09 if abs(dx) > abs(dy) else 0.06
        norm = (dx * dx + dy * dy) ** 0.5
        ax.annotate("", xy=(xb - dx / norm * sa, yb - dy / norm * sa),
                    xytext=(xa + dx / norm * sa, ya + dy / norm * sa),
                    arrowprops={"arrowstyle": "->", "color": "#333333", "lw": 1.2})
    ax.text(0.5, 0.13, "Arrows point one way: the physics knows nothing of filters, the filters "
            "nothing of MQTT.", ha="center", fontsize=8, color="#555555")
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    main()
