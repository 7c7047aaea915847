"""The study report's sensor section: what the line's other sensors (the strip gauge, the
final-angle camera) add to the curve, from the sensor benchmark's figures
(``benchmarks/results/bench_sensors.json``, written by ``python
benchmarks/bench_sensors.py``: series 1, 5 and 6, 5 datasets x 1000 products, N = 500).

The figure (:func:`plot_sensors`) has three panels, one group of bars per series and one
bar per sensor set (``curve``, ``camera``, ``gauge``, ``both``): the final angle's nRMSE,
the states' nRMSE (mean over the 7) and the coverage of the camera-calibrated 90 %
interval of the measured final angle.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from formtwin.figures import pyplot

#: the sensor sets in the order shown, and their labels
SETS = {"curve": "curve only (paper)", "camera": "+ camera 0.2 deg", "gauge": "+ gauge 0.5 um",
        "both": "+ gauge + camera"}
#: the panels: figure key, title
PANELS = (("final_nrmse", "final angle nRMSE"), ("state_nrmse", "state nRMSE (mean of 7)"),
          ("final_coverage90", "90 % final-angle interval coverage"))

Block = tuple[str, ...] | tuple[str, list[str], list[list[str]]]


def load_sensor_figures(path: str | Path) -> dict[str, Any] | None:
    """The ``figures`` of a sensor benchmark's JSON, ``None`` if the file is absent or has
    none of the sensor sets' tables (:data:`PANELS`)."""
    p = Path(path)
    if not p.is_file():
        return None
    figures: dict[str, Any] = json.loads(p.read_text(encoding="utf-8")).get("figures", {})
    return figures if all(k in figures for k, _ in PANELS) else None


def plot_sensors(figures: dict[str, Any], path: Path) -> Path:
    """The three panels of the module doc from the benchmark's ``figures``."""
    plt = pyplot()
    series = sorted(figures["final_nrmse"], key=int)
    fig, axes = plt.subplots(1, len(PANELS), figsize=(4.2 * len(PANELS), 3.2))
    colours = plt.cm.tab10(np.arange(len(SETS)))
    width = 0.8 / len(SETS)
    for ax, (key, title) in zip(axes, PANELS, strict=True):
        for j, (name, label) in enumerate(SETS.items()):
            v = [figures[key][s].get(name, np.nan) for s in series]
            ax.bar(np.arange(len(series)) + (j - (len(SETS) - 1) / 2) * width, v, width,
                   color=colours[j], label=label)
        if key == "final_coverage90":
            ax.axhline(0.9, color="k", lw=0.8)
            ax.set_ylim(0.5, 1.0)
        else:
            ax.axhline(1.0, color="k", lw=0.8, ls=":")
        ax.set_xticks(np.arange(len(series)), [f"series {s}" for s in series])
        ax.set_title(title, fontsize=10)
    axes[0].legend(fontsize=7, loc="upper left")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def sensor_blocks(figures: dict[str, Any] | None, folder: Path, source: str) -> list[Block]:
    """The report's sensor section (a heading, the figure ``fig_sensors.png`` written into
    ``folder``, a table per series and set, the control figures where present) from the
    benchmark's ``figures`` read from ``source``; without figures a paragraph saying how to
    make them."""
    blocks: list[Block] = [("h2", "Sensors besides the curve")]
    if figures is None:
        blocks.append(("p", "No sensor benchmark figures: run `python benchmarks/"
                            "bench_sensors.py` (series 1, 5, 6 with the strip gauge and the "
                            "camera) and pass its JSON with --sensor-figures."))
        return blocks
    plot_sensors(figures, folder / "fig_sensors.png")
    rows = []
    for s in sorted(figures["final_nrmse"], key=int):
        for name in SETS:
            rows.append([s, SETS[name]] + [
                f"{figures[k][s][name]:.2f}" if name in figures[k][s] else "–"
                for k in ("final_nrmse", "state_nrmse", "state_coverage90",
                          "final_coverage90")])
    settings = figures.get("settings", {})
    # results written before the table scored the default intervals have no cloud twin
    default = "state_coverage90_cloud" in figures
    scored = ("that of the tracker's default 90 % intervals (the fused particles' std with "
              "the calibrated floors, as the tables above)" if default else
              "that of the particles' own 90 % intervals (no calibrated floors)")
    blocks += [
        ("p", f"From {source} (series {', '.join(map(str, settings.get('series', [])))}, "
              f"{settings.get('datasets', '?')} datasets x {settings.get('products', '?')} "
              f"products, N = {settings.get('n_particles', '?')}): the tracker with the "
              "line's other sensors fused as they arrive (the strip gauge's thickness of each "
              "product before it is formed, 0.5 um; the camera's final angle one product "
              "late, 0.2 deg). nRMSE over the last products as above; the state coverage is "
              f"{scored}, the final-angle coverage that of the interval calibrated online "
              "on the camera's values (adaptive conformal inference)."),
        ("img", "fig_sensors.png", "final-angle nRMSE, state nRMSE and final-angle interval "
                                   "coverage per sensor set"),
        ("table", ["series", "sensors", "final angle nRMSE", "state nRMSE",
                   "state coverage" if default else "state coverage (cloud)",
                   "final-angle coverage"], rows),
    ]
    extra = [f"{label} {figures[k]}" for k, label in (
        ("state_coverage90_min", "state coverage of the default intervals, least over "
                                 "series 1, 3, 4, 5:"),
        ("ff_vs_ewma_within_curve", "feedforward / run-to-run EWMA final-angle std within a "
                                    "line, camera 0.2 deg, curve only:"),
        ("ff_vs_ewma_within_gauge", "the same with the gauge:")) if k in figures]
    if extra:
        blocks.append(("p", "; ".join(extra) + "."))
    return blocks


__all__ = ["PANELS", "SETS", "load_sensor_figures", "plot_sensors", "sensor_blocks"]
