"""Run the control study (:mod:`formtwin.study.control`) over its datasets, score it and draw
its figure: ``control_study.json`` and ``control_study.png`` in the output folder, the
per-dataset results in ``dataset_<k>.npz`` (reused when present with the same settings, the
same model and the same code)."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import multiprocessing
import os
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from formtwin.figures import pyplot
from formtwin.measurement import ProcessModel
from formtwin.simulator import Simulator
from formtwin.study.control import (
    CONTROLLERS,
    R2R_LAMS,
    ControlStudySettings,
    choose_weights,
    default_target,
    finish_dataset,
    plant_run,
    r2r_gain,
    run_dataset,
    scores,
)
from formtwin.study.control_ff import ADAPTIVE

log = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]

LABELS = {"fixed": "fixed u (no control)", "ewma": "run-to-run EWMA",
          "feedforward": "feedforward (formtwin: trim, weight learned on the line)",
          "oracle": "oracle (true state)",
          "feedforward_open": "feedforward without trim",
          "feedforward_fixed": "feedforward with trim, fixed weight",
          "feedforward_full": "feedforward with trim, whole change trusted",
          "feedforward_angle": "feedforward with trim, angles in the filter",
          "trim_only": "the same trim, estimates' change unused (weight 0)"}
#: the cases of the figure (those the study ran)
SHOWN = ("fixed", "ewma", "feedforward", "feedforward_angle", "oracle")


#: packages whose code does not change a control-study result
NOT_IN_RESULTS = ("service", "cli", "monitoring", "figures.py")


def result_key(settings: ControlStudySettings, target: float, version: str,
               metamodel: ProcessModel) -> str:
    """Hash of what makes a dataset's result: settings (not the worker count), target,
    physics version, the metamodel (its curve and angles at the box's middle, its residual
    statistics ``K_res`` if it has them), the source of the package outside
    :data:`NOT_IN_RESULTS` (tracker, controllers, plant, study) and its data files' JSON
    (the interval calibration)."""
    d = dataclasses.asdict(settings)
    d["tracker"] = settings.tracker.to_dict()
    for name in ("workers", "datasets"):  # a dataset's result depends on neither
        d.pop(name)
    h = hashlib.sha256(json.dumps([d, target, version], sort_keys=True,
                                  default=str).encode())
    spec = metamodel.spec
    mid = 0.5 * (spec.inputs.lo + spec.inputs.hi)[None, :]
    h.update(np.ascontiguousarray(metamodel.predict_curves(mid), dtype="<f8").tobytes())
    h.update(np.ascontiguousarray(metamodel.predict_angles(mid), dtype="<f8").tobytes())
    residuals = getattr(metamodel, "residuals", None)
    if residuals is not None:
        for cov in (residuals.curve_cov, residuals.angle_cov):
            h.update(np.ascontiguousarray(cov, dtype="<f8").tobytes())
    pkg = Path(__file__).resolve().parents[1]
    for f in sorted(pkg.rglob("*.py")):
        if f.relative_to(pkg).parts[0] not in NOT_IN_RESULTS:
            h.update(f.read_bytes())
    for f in sorted((pkg / "data").glob("*.json")):
        h.update(f.read_bytes())
    return h.hexdigest()[:16]


def build_plants(metamodel: ProcessModel, physics: Simulator, settings: ControlStudySettings,
                 out: str | Path) -> int:
    """Run (or complete) the physics of every dataset's plant
    (:func:`~formtwin.study.control.plant_path` in ``out``) without any controller, so that
    the study itself can run later from the cache; return the number of datasets."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    for k in range(settings.datasets):
        log.info("control study: plant of dataset %d of %d", k + 1, settings.datasets)
        plant_run(metamodel.spec, physics, settings, k, out)
    return settings.datasets


def _datasets(metamodel: ProcessModel, physics: Simulator, settings: ControlStudySettings,
              out: Path, key: str, target: float, gain: float) -> list[dict[str, Any]]:
    """Every dataset's :func:`~formtwin.study.control.run_dataset`, from ``dataset_<k>.npz``
    when stored there with ``key``; the others computed, ``settings.workers`` at a time
    (their plants first, one after the other)."""
    paths = [out / f"dataset_{k}.npz" for k in range(settings.datasets)]
    res: list[dict[str, Any] | None] = [load_result(p, key) for p in paths]
    todo = [k for k, r in enumerate(res) if r is None]
    if not todo:
        return [r for r in res if r is not None]
    for k in todo:
        plant_run(metamodel.spec, physics, settings, k, out)
    args = [(metamodel, physics, settings, k, out, target, gain) for k in todo]
    n = min(settings.workers or os.cpu_count() or 1, len(todo))
    log.info("control study: %d datasets, %d at a time", len(todo), n)
    if n > 1:
        with ProcessPoolExecutor(n, mp_context=multiprocessing.get_context("forkserver")) as pool:
            done = list(pool.map(_run_dataset, args))
    else:
        done = [_run_dataset(a) for a in args]
    for k, r in zip(todo, done, strict=True):
        save_result(paths[k], key, r)
        res[k] = r
    return [r for r in res if r is not None]


def _run_dataset(args: tuple[Any, ...]) -> dict[str, Any]:
    """:func:`~formtwin.study.control.run_dataset` of one argument tuple (for a pool)."""
    log.info("control study: dataset %d", args[3])
    return run_dataset(*args)


def _tuned_result(base: dict[str, Any], tuned: dict[str, float]) -> dict[str, Any]:
    """A dataset's result in the controllers' names with the weights ``tuned``: the grids'
    rows of ``feedforward`` (``ff_lam``, learned, ``ff_rho``), ``feedforward_fixed`` (the
    tuned fixed ``(lam, weight, rho)``), ``feedforward_full`` (``full_lam``, 1, 0),
    ``trim_only`` (the feedforward's ``lam`` and ``rho``, weight 0) and ``ewma``
    (``r2r_lam``)."""
    grid = [tuple(g) for g in np.asarray(base["grid"]).tolist()]
    rows = {"feedforward": grid.index((tuned["ff_lam"], ADAPTIVE, tuned["ff_rho"])),
            "feedforward_fixed": grid.index((tuned["fffixed_lam"], tuned["fffixed_weight"],
                                             tuned["fffixed_rho"])),
            "feedforward_full": grid.index((tuned["full_lam"], 1.0, 0.0))}
    if (tuned["ff_lam"], 0.0, tuned["ff_rho"]) in grid:
        rows["trim_only"] = grid.index((tuned["ff_lam"], 0.0, tuned["ff_rho"]))
    r = {n: v for n, v in base.items() if not n.endswith(("_grid", "_r2r")) and n != "grid"}
    for name, row in rows.items():
        r[f"u_{name}"], r[f"angle_{name}"] = base["u_grid"][row], base["angle_grid"][row]
    r["pred"] = base["pred_grid"][rows["feedforward"]]
    lam = R2R_LAMS.index(tuned["r2r_lam"])
    r["u_ewma"], r["angle_ewma"] = base["u_r2r"][lam], base["angle_r2r"][lam]
    return r


def run_control_study(metamodel: ProcessModel, physics: Simulator,
                      settings: ControlStudySettings, out: str | Path) -> dict[str, Any]:
    """Run (or reuse) every dataset, choose each one's weights on the others (leave one
    dataset out), write the figure and ``control_study.json``; return the summary (per
    controller: mean error, std, RMSE, share in the band; the ratios of the feedforward's
    std to the others'; the weights chosen on all datasets, for the service)."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    target = default_target(metamodel) if settings.target is None else settings.target
    gain = r2r_gain(metamodel, np.random.default_rng(settings.seed))
    key = result_key(settings, target, str(getattr(physics, "version", "")), metamodel)
    bases = _datasets(metamodel, physics, settings, out, key, target, gain)
    b = settings.burn_in
    grid = bases[0]["grid"]
    ff_std = np.array([np.nanstd(r["angle_grid"][:, b:], axis=1) for r in bases])
    r2r_std = np.array([np.nanstd(r["angle_r2r"][:, b:], axis=1) for r in bases])
    fixed_std = np.array([np.nanstd(r["angle_fixed"][b:]) for r in bases])
    K = len(bases)
    chosen = [choose_weights(np.delete(ff_std, k, 0), np.delete(r2r_std, k, 0),
                             np.delete(fixed_std, k), grid) for k in range(K)]
    results = []
    for k, (base, tuned) in enumerate(zip(bases, chosen, strict=True)):
        r = _tuned_result(base, tuned)
        fin_key = f"{key}-{sorted(tuned.items())}"
        fin = load_result(out / f"final_{k}.npz", fin_key)
        if fin is None:
            fin = finish_dataset(metamodel, physics, settings, k, out, target, tuned,
                                 r["u_feedforward"])
            save_result(out / f"final_{k}.npz", fin_key, fin)
        if "interp_idx" in fin:
            fin["interp_error"] = (fin["interp_angle"]
                                   - r["angle_feedforward"][np.asarray(fin["interp_idx"])])
        results.append({**r, **fin})
    names = [c for c in CONTROLLERS if all(f"angle_{c}" in r for r in results)]
    pooled = {c: np.concatenate([r[f"angle_{c}"][b:] for r in results]) for c in names}
    summary: dict[str, Any] = {c: scores(pooled[c], target, settings.band) for c in names}
    sd = {c: summary[c]["std_deg"] for c in names}
    per = {c: [float(np.nanstd(r[f"angle_{c}"][b:])) for r in results] for c in names}
    for ff, tag in (("feedforward", "ff"), ("feedforward_fixed", "fffixed"),
                    ("feedforward_angle", "ffangle"), ("feedforward_full", "fffull"),
                    ("trim_only", "trim")):
        for other in ("fixed", "oracle", "ewma"):
            if ff not in sd:
                continue
            summary[f"angle2_std_ratio_{tag}_vs_{other}"] = (
                round(sd[ff] / sd[other], 4) if sd[other] > 0 else None)
            r = np.array(per[ff]) / np.array(per[other])
            summary[f"within_dataset_std_ratio_{tag}_vs_{other}"] = {
                "per_dataset": np.round(r, 3).tolist(),
                "median": round(float(np.median(r)), 3),
                "of_mean_std": round(float(np.mean(per[ff]) / np.mean(per[other])), 4)}
    summary.update({
        "target_deg": target, "r2r_gain_deg_per_unit": round(gain, 6),
        **choose_weights(ff_std, r2r_std, fixed_std, grid),  # on every dataset: the service's
        "tuning": "leave one dataset out: dataset k scored with the weights best on the "
                  "others (per_dataset_weights); the top-level weights are the best on all; "
                  "best: least mean within-dataset ratio of the std to fixed u's",
        "per_dataset_weights": chosen, "burn_in": b,
        "per_dataset_std_deg": {c: [round(v, 4) for v in per[c]] for c in names},
        "tuning_std_deg": {"ff_grid": np.asarray(grid).tolist(),
                           "ff_per_dataset": np.round(ff_std, 4).tolist(),
                           "ff": np.round(ff_std.mean(0), 4).tolist(),
                           "fixed_per_dataset": np.round(fixed_std, 4).tolist(),
                           "r2r_lams": list(R2R_LAMS),
                           "r2r_per_dataset": np.round(r2r_std, 4).tolist(),
                           "r2r": np.round(r2r_std.mean(0), 4).tolist()},
    })
    for ff, key in (("feedforward", "pred"), ("feedforward_angle", "pred_angle")):
        if ff in names:
            summary.update(prediction_scores(np.concatenate([r[key][b:] for r in results]),
                                             pooled[ff], ff))
    summary.update(estimate_worth(results, b))
    summary["angle_drivers"] = angle_drivers(results, b, list(metamodel.spec.inputs.names))
    errs = [r["interp_error"] for r in results if "interp_error" in r]
    if errs:
        e = np.concatenate(errs)
        summary["plant_interpolation_max_abs_error_deg"] = round(float(np.nanmax(np.abs(e))), 4)
    summary["settings"] = {**{k: v for k, v in dataclasses.asdict(settings).items()
                              if k != "tracker"}, "tracker": settings.tracker.to_dict()}
    plot_control(results[0], target, settings.band, out / "control_study.png")
    (out / "control_study.json").write_text(json.dumps(summary, indent=2) + "\n")
    return summary


def load_result(path: Path, key: str) -> dict[str, Any] | None:
    """The arrays stored in ``path`` with ``key`` (None: absent or another key)."""
    if path.exists():
        with np.load(path, allow_pickle=False) as f:
            if str(f["key"]) == key:
                return {n: (f[n].item() if f[n].ndim == 0 else f[n])
                        for n in f.files if n != "key"}
    return None


def save_result(path: Path, key: str, res: dict[str, Any]) -> None:
    """Store the arrays ``res`` in ``path`` with ``key``."""
    np.savez(path, key=np.array(key), **{n: np.asarray(v) for n, v in res.items()})  # type: ignore[arg-type]


def prediction_scores(pred: FloatArray, angle: FloatArray, name: str) -> dict[str, float]:
    """Coverage of the 90 % intervals and RMSE of the predicted final angles ``pred``
    (n, 3: mean, lo, hi) against the plant's ``angle`` (n,)."""
    ok = np.all(np.isfinite(pred), axis=1) & np.isfinite(angle)
    a, p = angle[ok], pred[ok]
    return {f"{name}_interval_coverage": round(float(np.mean((a >= p[:, 1]) & (a <= p[:, 2]))), 4),
            f"{name}_prediction_rmse_deg": round(float(np.sqrt(np.mean((a - p[:, 0]) ** 2))), 4)}


def estimate_worth(results: list[dict[str, Any]], burn_in: int) -> dict[str, float]:
    """What the estimates know of the products' final angles before any setting is chosen:
    the correlation, within each dataset after ``burn_in``, of the posterior mean of the
    final angle at the nominal setting (from the stage-1 curve alone) with the plant's angle
    there, of their levels and of their product-to-product changes (what feedforward can
    act on), and the regression slope of the plant's change on the estimate's; and the
    correlation of the plant's changes with those of the metamodel at the true inputs."""
    lev_a, lev_p, d_a, d_p = [], [], [], []
    for r in results:
        a, p = r["angle_fixed"][burn_in:], r["nominal_mean"][burn_in:]
        ok = np.isfinite(a) & np.isfinite(p)
        lev_a.append(a[ok] - a[ok].mean())
        lev_p.append(p[ok] - p[ok].mean())
        both = ok[1:] & ok[:-1]
        d_a.append(np.diff(a)[both])
        d_p.append(np.diff(p)[both])
    la, lp, da, dp = (np.concatenate(v) for v in (lev_a, lev_p, d_a, d_p))
    truth = {}
    if all("truth_nominal" in r for r in results):  # the metamodel at the true inputs
        dt = np.concatenate([np.diff(r["truth_nominal"][burn_in:]) for r in results])
        da_all = np.concatenate([np.diff(r["angle_fixed"][burn_in:]) for r in results])
        okt = np.isfinite(da_all) & np.isfinite(dt)
        truth = {"metamodel_at_truth_change_corr": round(float(np.corrcoef(
            da_all[okt], dt[okt])[0, 1]), 4)}
    return {**truth, "estimate_level_corr": round(float(np.corrcoef(la, lp)[0, 1]), 4),
            "estimate_change_corr": round(float(np.corrcoef(da, dp)[0, 1]), 4),
            "estimate_change_slope": round(float(np.polyfit(dp, da, 1)[0]), 4),
            "plant_change_std_deg": round(float(da.std()), 4),
            "estimate_change_std_deg": round(float(dp.std()), 4)}


def angle_drivers(results: list[dict[str, Any]], burn_in: int, names: list[str]
                  ) -> dict[str, dict[str, float]]:
    """Per run input: its share of the final angle's variation along the runs (the slope of
    the metamodel's angle at the true inputs and nominal setting, fitted on all inputs
    within each dataset, times the input's std there), degrees, and how well the estimates
    follow it: the correlation of its posterior mean with the truth, of levels and of
    product-to-product changes (within datasets, after ``burn_in``). Inputs fixed within
    every dataset (the machine parameters) are left out."""
    xs, ys, es = [], [], []
    for r in results:
        ok = np.isfinite(r["truth_nominal"][burn_in:]) & np.all(
            np.isfinite(r["input_mean"][burn_in:]), axis=1)
        x, e = r["inputs"][burn_in:][ok], r["input_mean"][burn_in:][ok]
        xs.append(x - x.mean(axis=0))
        es.append(e - e.mean(axis=0))
        ys.append(r["truth_nominal"][burn_in:][ok] - r["truth_nominal"][burn_in:][ok].mean())
    x, e, y = np.concatenate(xs), np.concatenate(es), np.concatenate(ys)
    scale = np.max([np.abs(r["inputs"]).max(axis=0) for r in results], axis=0)
    varies = x.std(axis=0) > 1e-9 * np.maximum(scale, 1e-300)  # not fixed within every run
    slope = np.zeros(x.shape[1])
    slope[varies] = np.linalg.lstsq(x[:, varies], y, rcond=None)[0]
    out: dict[str, dict[str, float]] = {}
    for j in np.argsort(-np.abs(slope * x.std(axis=0))):
        if not varies[j]:
            continue
        dx = np.concatenate([np.diff(v[:, j]) for v in xs])
        de = np.concatenate([np.diff(v[:, j]) for v in es])
        out[names[j]] = {"angle_std_deg": round(float(slope[j] * x[:, j].std()), 4),
                         "estimate_level_corr": round(float(np.corrcoef(
                             x[:, j], e[:, j])[0, 1]), 3),
                         "estimate_change_corr": round(float(np.corrcoef(dx, de)[0, 1]), 3)}
    return out


def plot_control(res: dict[str, Any], target: float, band: float, path: Path) -> Path:
    """The final angle over the products of one dataset for the controllers of
    :data:`SHOWN`."""
    plt = pyplot()
    shown = [c for c in SHOWN if f"angle_{c}" in res]
    fig, axes = plt.subplots(len(shown), 1, figsize=(10, 2.25 * len(shown)), sharex=True,
                             sharey=True)
    for ax, c in zip(axes, shown, strict=True):
        a = res[f"angle_{c}"]
        ax.plot(np.arange(a.size), a, ".", ms=2, color="#1f5fa8")
        ax.axhline(target, color="k", lw=0.8)
        ax.axhspan(target - band, target + band, color="#2a7a2a", alpha=0.12, lw=0)
        e = a[np.isfinite(a)] - target
        ax.set_title(f"{LABELS[c]}: std {e.std():.3f} deg, within +-{band} deg "
                     f"{np.mean(np.abs(e) <= band):.0%}", fontsize=9)
        ax.set_ylabel("final angle (deg)")
    axes[-1].set_xlabel("product")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


__all__ = ["LABELS", "angle_drivers", "estimate_worth", "plot_control", "prediction_scores",
           "run_control_study"]
