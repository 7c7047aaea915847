"""The study report's honest metrics: skill against the prior-only guess, coverage of the
90 % intervals, ESS and log-evidence, per series, for the tracker's likelihood and the
paper's on the same data (table, figure and JSON)."""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from formtwin.figures import pyplot
from formtwin.spec import ProcessSpec
from formtwin.study.run import StudyResult

FloatArray = NDArray[np.float64]


def _mean(a: FloatArray, axis: Any = None) -> Any:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN slices stay NaN
        return np.nanmean(a, axis=axis)


def series_scores(spec: ProcessSpec, arrays: dict[str, FloatArray],
                  series: int) -> dict[str, Any]:
    """Summary of one series (means over datasets and repetitions): state nRMSE (mean of
    7), skill per state variable / its minimum, angle skill, coverage of states, parameters
    and angles, mean ESS, log-evidence."""
    nx, n_in, n_aug = len(spec.state), len(spec.inputs), len(spec.augmented)
    i = series - 1
    skill = _mean(arrays["skill"][i], axis=(0, 1))
    cov = _mean(arrays["coverage"][i], axis=(0, 1))
    nr = _mean(arrays["nrmse"][i], axis=(0, 1))
    return {
        "state_nrmse": float(_mean(nr[:nx])),
        "angles_nrmse": [float(v) for v in nr[n_aug:]],
        "skill_state": [float(v) for v in skill[:nx]],
        "skill_state_min": float(np.nanmin(skill[:nx])),
        "skill_params": [float(v) for v in skill[nx:n_in]],
        "skill_angles": [float(v) for v in skill[n_aug:]],
        "coverage_state": float(_mean(cov[:nx])),
        "coverage_state_min": float(np.nanmin(cov[:nx])),
        "coverage_params": float(_mean(cov[nx:n_in])),
        "coverage_angles": [float(v) for v in cov[n_aug:]],
        "ess": float(_mean(arrays["ess"][i])),
        "log_evidence": float(_mean(arrays["log_evidence"][i])),
    }


def honest_summary(result: StudyResult, spec: ProcessSpec) -> dict[str, Any]:
    """Per series, the scores of the tracker's likelihood and (if run) the paper's."""
    mine = {"nrmse": result.nrmse, "skill": result.skill, "coverage": result.coverage,
            "ess": result.ess, "log_evidence": result.log_evidence}
    out: dict[str, Any] = {}
    for s in result.settings.series:
        entry = {result.settings.tracker.likelihood: series_scores(spec, mine, s)}
        if result.paper and s in result.settings.paper_series:
            entry["paper"] = series_scores(spec, result.paper, s)
        out[f"series{s}"] = entry
    return out


def _f(v: float, digits: int = 2) -> str:
    return "–" if not np.isfinite(v) else f"{v:.{digits}f}"


def honest_table(summary: dict[str, Any]) -> tuple[list[str], list[list[str]]]:
    """Header and rows: one row per series and likelihood."""
    head = ["series", "likelihood", "state nRMSE", "state skill (min / mean)",
            "angle skill (1 / 2)", "coverage 90 %: states (min)", "params", "angles (1 / 2)",
            "mean ESS", "log-evidence"]
    rows = []
    for name, entry in summary.items():
        for lik, sc in entry.items():
            mean_skill = float(np.nanmean(sc["skill_state"]))
            rows.append([name.removeprefix("series"), lik, _f(sc["state_nrmse"]),
                         f"{_f(sc['skill_state_min'])} / {_f(mean_skill)}",
                         " / ".join(_f(v) for v in sc["skill_angles"]),
                         f"{_f(sc['coverage_state'])} ({_f(sc['coverage_state_min'])})",
                         _f(sc["coverage_params"]),
                         " / ".join(_f(v) for v in sc["coverage_angles"]),
                         _f(sc["ess"], 0), _f(sc["log_evidence"], 0)])
    return head, rows


def plot_honest(summary: dict[str, Any], path: Path) -> Path:
    """Skill of the state variables (mean, min) and coverage of states and angles per
    series, tracker's likelihood vs the paper's."""
    plt = pyplot()
    names = list(summary)
    liks = list(dict.fromkeys(lik for entry in summary.values() for lik in entry))
    nan = {"skill_state": [np.nan], "skill_state_min": np.nan, "coverage_state": np.nan,
           "coverage_angles": [np.nan]}  # a series not run with that likelihood
    fig, axes = plt.subplots(1, 2, figsize=(11, 3.8), layout="constrained")
    width = 0.8 / len(liks)
    x = np.arange(len(names))
    for j, lik in enumerate(liks):
        sc = [summary[n].get(lik, nan) for n in names]
        axes[0].bar(x + j * width, [_mean(s["skill_state"]) for s in sc], width,
                    label=f"{lik}: mean", color=f"C{j}")
        axes[0].plot(x + j * width, [s["skill_state_min"] for s in sc], "kv", ms=5)
        axes[1].bar(x + j * width, [s["coverage_state"] for s in sc], width,
                    label=f"{lik}: states", color=f"C{j}")
        axes[1].plot(x + j * width, [_mean(s["coverage_angles"]) for s in sc], "kD",
                     ms=4)
    axes[0].axhline(0, color="k", lw=0.8)
    axes[0].set(ylabel="skill = 1 - RMSE/RMSE_prior", title="state skill (bar mean, v min)")
    axes[1].axhline(0.9, color="k", lw=0.8, ls="--")
    axes[1].set(ylabel="coverage of the 90 % interval", ylim=(0, 1.02),
                title="coverage (bar states, diamond angles)")
    for ax in axes:
        ax.set_xticks(x + 0.4 - width / 2, [n.removeprefix("series") for n in names])
        ax.set_xlabel("series")
        ax.legend(fontsize=8)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path
