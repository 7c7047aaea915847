"""Figures of the study: Fig. 4 (normalised RMSE) and Figs. 5-6 (time series)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from formtwin.figures import pyplot
from formtwin.spec import ProcessSpec
from formtwin.study.metrics import summarise
from formtwin.study.pseudodata import Realisation
from formtwin.study.series import SERIES

FloatArray = NDArray[np.float64]


def component_labels(spec: ProcessSpec) -> list[str]:
    """Names of the study components: the augmented state, then the spec's outputs (20 for
    the demonstrator: 18 and its two angles)."""
    return list(spec.augmented.names) + list(spec.output_names)


def plot_nrmse(spec: ProcessSpec, nrmse: FloatArray, series: tuple[int, ...],
               path: Path) -> Path:
    """Fig. 4 analogue: per component, a bar per series (mean over datasets and
    repetitions), a diamond per dataset (mean over repetitions), a line at 1."""
    plt = pyplot()
    labels = component_labels(spec)
    per_dataset, overall = summarise(nrmse)
    n_comp = len(labels)
    cols = 5
    rows = int(np.ceil(n_comp / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(3.0 * cols, 2.4 * rows), sharex=True)
    colours = plt.cm.tab10(np.arange(len(SERIES)))
    for c, ax in enumerate(axes.flat):
        if c >= n_comp:
            ax.axis("off")
            continue
        for s in series:
            i = s - 1
            if np.isnan(overall[i, c]):
                continue
            ax.bar(s, overall[i, c], color=colours[i], alpha=0.8)
            ax.plot(np.full(per_dataset.shape[1], s), per_dataset[i, :, c], "d",
                    color="black", ms=3)
        ax.axhline(1.0, color="red", lw=0.8)
        ax.set_title(labels[c], fontsize=8)
        ax.set_xticks(list(series))
        ax.tick_params(labelsize=7)
    fig.suptitle("Normalised RMSE over the last products, per series (bars: mean over "
                 "datasets; diamonds: per dataset)", fontsize=10)
    fig.supxlabel("simulation series", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_timeseries(spec: ProcessSpec, real: Realisation, run: dict[str, FloatArray],
                    series: int, path: Path, last: int = 200) -> Path:
    """Figs. 5-6 analogue: truth (black) against E +- 3 s (grey) for the last products."""
    plt = pyplot()
    s = SERIES[series - 1]
    truth = real.truth
    n_show = len(spec.augmented) if s.deviation else len(spec.inputs)
    labels = component_labels(spec)
    idx = list(range(n_show)) + [len(spec.augmented) + k for k in range(spec.n_outputs)]
    cols = 4
    rows = int(np.ceil(len(idx) / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(3.4 * cols, 2.1 * rows), sharex=True)
    products = np.arange(real.n)[-last:]
    angles_true = np.where(real.ok[s.data][:, None], real.angles[s.data], np.nan)
    for ax, c in zip(axes.flat, idx, strict=False):
        if c < len(spec.augmented):
            scale = spec.augmented.variables[c].scale
            m, sd, tr = run["mean"][:, c], run["std"][:, c], truth[:, c]
        else:
            a = c - len(spec.augmented)
            scale = 1.0
            m, sd, tr = run["angles_mean"][:, a], run["angles_std"][:, a], angles_true[:, a]
        m, sd, tr = m[-last:] / scale, sd[-last:] / scale, tr[-last:] / scale
        ax.fill_between(products, m - 3 * sd, m + 3 * sd, color="0.8", lw=0)
        ax.plot(products, m, color="0.45", lw=0.8)
        ax.plot(products, tr, color="black", lw=1.0)
        unit = spec.augmented.variables[c].unit if c < len(spec.augmented) else \
            spec.outputs[c - len(spec.augmented)].unit
        ax.set_title(f"{labels[c]} [{unit}]", fontsize=8)
        ax.tick_params(labelsize=7)
    for ax in list(axes.flat)[len(idx):]:
        ax.axis("off")
    fig.suptitle(f"Series {s.label}: truth (black), E +- 3 s (grey), last {last} products",
                 fontsize=10)
    fig.supxlabel("product", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
