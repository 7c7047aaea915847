"""Benchmark: every sensor the line has: the strip gauge, the camera's late and
noisy final angle, and the camera-calibrated interval of the final angle.

On the embedded default (bundled physics DOE, its metamodel), N = 500, the study's seeds,
in the folder ``--out`` (default ``benchmarks/.cache/sensors``, reused when present):

1. the study's pseudo-data and measurement models of series 1, 5 and 6 (5 datasets x 1000
   products), and the study's own curve-only runs (repetition 0), exactly as ``formtwin
   study --series 1,5,6`` makes them: ``s1_final_nrmse_curve`` is the final angle's nRMSE
   of series 1 there (the report's figure, repetition 0);
2. for every series, dataset and sensor set of
   :data:`~formtwin.study.sensor_study.SENSOR_SETS` (``curve``, ``camera``: 0.2 deg,
   delay 1; ``gauge``: 0.5 um; ``both``), one run of :func:`~formtwin.study.sensor_study.
   sensor_run` (the same tracker seed as the study's repetition 0): the posterior after
   what has arrived, the final angle's interval calibrated by ACI on the camera's
   residuals.

Figures (means over the 5 datasets; nRMSE over the last 500 products, normalised as the
study does):

* ``final_nrmse[series][set]``, ``state_nrmse[series][set]`` (mean over the 7 states),
  ``state_coverage90[series][set]`` (the tracker's default 90 % intervals: the fused
  cloud's std with what the step's estimate adds to it, the calibrated floors and the
  assumed mu's term, as the report's other tables), ``state_coverage90_cloud`` (the
  particles' own, no floors);
* ``s1_final_nrmse_gauge``: series 1 with the 0.5 um gauge (target <= 0.45), its
  value entering its product's step (:mod:`formtwin.tracker.ahead`);
  ``s1_final_nrmse_gauge_after_step``: the same fused after the step instead (plain SIR's
  way), at N = 500 and, as the Monte-Carlo reference, N = 2000;
* ``ewma_final_nrmse[series]`` and ``ewma_weight[series]``: the camera-only run-to-run
  EWMA predictor at its best weight for the series (chosen on the same datasets: a
  flattering choice);
* ``final_nrmse_fused_vs_best_single[series]``: curve + camera over the better of the
  curve-only twin and that EWMA; ``_max`` (target <= 1.0) and ``_s6`` (target <= 0.85);
* ``final_coverage90[series][set]``: how often the calibrated 90 % interval holds the
  measured final angle; ``final_coverage90_min/max`` over series 1, 5, 6 with curve +
  camera (targets 0.87 and 0.93).

* ``linear_discrepancy_bound[series]`` (and over the best single source,
  ``linear_discrepancy_bound_vs_best_single``): the least final-angle nRMSE of a
  discrepancy linear in the twin's own numbers (its predicted angle, posterior means,
  the curve's principal scores) learned from the 0.2 deg camera
  (:func:`linear_discrepancy_bound`; optimistic: the best coefficients on the scored
  products' true angles, plus the cost of learning them from the camera);

* ``bound_s1_final[set]``: the linear-Gaussian bound of ``formtwin sensors`` on the
  study's series-1 lines (their mu and theta, seed 0), for ``curve``, ``gauge_0.5um``,
  ``camera_0.05deg`` and ``both`` (gauge 0.5 um + camera 0.2 deg, the sets simulated);
* ``bound_vs_sim[set]``: the simulated series-1 nRMSE over the bound at the same noise
  (curve, gauge 0.5 um, camera 0.2 deg, both); ``bound_vs_sim_min/max``.

``state_coverage90_min`` (the default study's intervals, series 1, 3, 4, 5) and the
feedforward's ``ff_vs_ewma_within_curve`` / ``_gauge`` (the closed-loop study with the
camera's noise and the gauge): ``benchmarks/_sensor_control.py``. ``study_s`` (the
default ``make demo`` study's time): ``python benchmarks/_sensor_control.py --only
study``, kept from its last run.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np
from _sensor_control import measured_apart, sensor_control_figures

from formtwin._bench import bundled_metamodel, file_digest, write_result
from formtwin.defaults import physics_model
from formtwin.spec.sensors import line_sensors
from formtwin.study.metrics import Z90, coverage, normalisers
from formtwin.study.run import StudySettings, _tasks, run_study
from formtwin.study.sensor_bound import linearise, sensor_rows, set_bound
from formtwin.study.sensor_study import SENSOR_SETS, ewma_prediction, sensor_run
from formtwin.study.series import SERIES, Task

SERIES_RUN = (1, 5, 6)
#: EWMA weights tried for the camera-only predictor
LAMBDAS = (0.02, 0.05, 0.1, 0.2, 0.3, 0.5, 0.7, 1.0)


#: the gauge fused after its product's step (plain SIR's way), series 1: name -> particles
GAUGE_AFTER = {"gauge_after": 500, "gauge_after_n2000": 2000}


def _job(args: tuple[Task, str, str]) -> str:
    """One sensor run, saved as npz (reused when present)."""
    task, name, path = args
    if not Path(path).exists():
        if name in GAUGE_AFTER:
            tr = dataclasses.replace(task.tracker, n_particles=GAUGE_AFTER[name])
            out = sensor_run(dataclasses.replace(task, tracker=tr), ("gauge",),
                             gauge_ahead=False)
        else:
            out = sensor_run(task, SENSOR_SETS[name])
        tmp = Path(path).with_suffix(".tmp.npz")
        np.savez_compressed(tmp, **{k: np.asarray(v) for k, v in out.items()})
        tmp.replace(path)
    return path


def _final_nrmse(pred: np.ndarray, true: np.ndarray, window: int) -> float:
    p, t = pred[-window:], true[-window:]
    ok = np.isfinite(p) & np.isfinite(t)
    return float(np.sqrt(np.mean((p[ok] - t[ok]) ** 2)) / t[ok].std())


def linear_discrepancy_bound(run: dict[str, np.ndarray], curves: np.ndarray,
                             true: np.ndarray, camera_sd: float, window: int) -> float:
    """What a discrepancy linear in the twin's own numbers can reach at best, in the
    study's nRMSE: for nested feature sets ``F`` of each product (the curve-only twin's
    predicted final angle; + its posterior means of ``[x, theta]``; + the curve's 10
    leading principal scores, fitted on the products before the scored window),

        nRMSE^2 >= r^2(F) + (camera_sd^2 + r^2 v) p / (n v),

    ``r^2`` the in-sample residual of the least-squares fit of the *true* final angles of
    the scored window on ``F`` over their variance ``v`` (the best coefficients, known:
    optimistic), the second term the excess risk of ``p = |F|`` coefficients learned from
    ``n`` values of the camera instead (least squares with Gaussian noise, ``n`` the mean
    number of camera values before a scored product). The smallest over the sets."""
    m, mean = run["angles_mean"][:, 1], run["mean"][:, :10]
    n_all = true.size
    ok = np.isfinite(true) & np.isfinite(m) & np.all(np.isfinite(curves), axis=1)
    test = ok & (np.arange(n_all) >= n_all - window)
    train = ok & ~test
    c0 = curves[train].mean(axis=0)
    vt = np.linalg.svd(curves[train] - c0, full_matrices=False)[2][:10]
    scores = np.where(ok[:, None], np.nan_to_num(curves) - c0, 0.0) @ vt.T
    y, v = true[test], float(true[test].var())
    n_cam = float(np.mean(np.flatnonzero(test)))  # camera values known before each
    best = np.inf
    for feats in ([m[:, None]], [m[:, None], mean], [m[:, None], mean, scores]):
        X = np.hstack([np.ones((n_all, 1)), *feats])[test]
        X = (X - X.mean(axis=0)) / np.where(X.std(axis=0) > 0, X.std(axis=0), 1.0)
        X[:, 0] = 1.0
        res = y - X @ np.linalg.lstsq(X, y, rcond=None)[0]
        r2 = float(np.mean(res**2)) / v
        p = X.shape[1]
        best = min(best, r2 + (camera_sd**2 + r2 * v) * p / (n_cam * v))
    return float(np.sqrt(best))


#: the default study's figures (``_sensor_control.py --only study``), kept from their run
STUDY_FIGURES = ("study_s", "study_wall_s", "study_timings", "study_load_avg_1_5_15min")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--out", default="benchmarks/.cache/sensors")
    parser.add_argument("--quick", action="store_true", help="smoke test (2 x 200 products)")
    parser.add_argument("--products", type=int, help="products per dataset (smoke tests)")
    parser.add_argument("--realisations", type=int, help="datasets (smoke tests)")
    parser.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    args = parser.parse_args()
    out = Path(args.out)
    t0 = time.perf_counter()
    mm, mm_path, model_info = bundled_metamodel(out / "model")
    sizes: dict[str, Any] = {"n_products": 200, "n_realisations": 2, "window": 100} \
        if args.quick else {}
    if args.products:
        sizes.update(n_products=args.products, window=args.products // 2)
    if args.realisations:
        sizes["n_realisations"] = args.realisations
    smoke = bool(sizes)
    settings = StudySettings(series=SERIES_RUN, n_repetitions=1, paper_repetitions=0, **sizes)
    study = run_study(settings, out, mm, mm_path, physics_model("bending", mm.spec))
    t_study = time.perf_counter() - t0
    tasks = [t for t in _tasks(settings, out, mm_path, out / "data") if t.repetition == 0]
    runs_dir = out / "sensor_runs"
    runs_dir.mkdir(parents=True, exist_ok=True)
    # a run's file is named for its task and the code that makes it
    import formtwin.study.sensor_study as ss
    import formtwin.tracker.angle_discrepancy as ad
    import formtwin.tracker.fusion as fu
    code = "".join(file_digest(m.__file__ or "")[:6] for m in (ss, fu, ad))
    jobs = [(t, name, str(runs_dir / f"series{t.series}_real{t.realisation}_{name}_"
                                     f"{t.key[:12]}_{code}.npz"))
            for t in tasks for name in SENSOR_SETS]
    after = [(t, name, str(runs_dir / f"series1_real{t.realisation}_{name}_{t.key[:12]}_"
                                      f"{code}.npz"))
             for t in tasks if t.series == 1 for name in GAUGE_AFTER]
    t1 = time.perf_counter()
    with ProcessPoolExecutor(args.workers) as pool:
        paths = list(pool.map(_job, jobs))
        after_paths = list(pool.map(_job, after))
    t_runs = time.perf_counter() - t1
    spec, w = mm.spec, settings.window
    nx = len(spec.state)
    final: dict[int, dict[str, list[float]]] = {s: {n: [] for n in SENSOR_SETS} for s in SERIES_RUN}
    state, scov, ccov, fcov = ({s: {n: [] for n in SENSOR_SETS} for s in SERIES_RUN}
                               for _ in range(4))
    rejected = 0
    for (task, name, _), path in zip(jobs, paths, strict=True):
        real = study.realisations[task.realisation]
        data = SERIES[task.series - 1].data
        true = np.where(real.ok[data], real.angles[data][:, 1], np.nan)
        with np.load(path, allow_pickle=False) as f:
            r = {k: f[k] for k in f.files}
        rejected += int(r["rejected"])
        final[task.series][name].append(_final_nrmse(r["angles_mean"][:, 1], true, w))
        err = (r["mean"][-w:, :nx] - real.truth[-w:, :nx]) / normalisers(spec)[:nx]
        state[task.series][name].append(float(np.mean(np.sqrt(np.nanmean(err**2, axis=0)))))
        for table, key in ((scov, "std"), (ccov, "cloud_std")):
            table[task.series][name].append(float(np.mean(coverage(
                r["mean"][:, :nx], r[key][:, :nx], real.truth[:, :nx], w, Z90))))
        cam = r["camera"][-w:]
        inside = (cam >= r["final_lo"][-w:]) & (cam <= r["final_hi"][-w:])
        fcov[task.series][name].append(float(np.mean(inside[np.isfinite(cam)])))
    ewma, ewma_w = {}, {}
    for s in SERIES_RUN:
        data = SERIES[s - 1].data
        scores = []
        for lam in LAMBDAS:
            per = []
            for task, name, path in jobs:
                if task.series != s or name != "curve":
                    continue
                real = study.realisations[task.realisation]
                true = np.where(real.ok[data], real.angles[data][:, 1], np.nan)
                with np.load(path, allow_pickle=False) as f:
                    cam = f["camera"]
                per.append(_final_nrmse(ewma_prediction(cam, lam), true, w))
            scores.append(float(np.mean(per)))
        best = int(np.argmin(scores))
        ewma[s], ewma_w[s] = scores[best], LAMBDAS[best]
    cam_sd = next(s for s in line_sensors(spec) if s.name == "camera").noise
    lin_bound: dict[int, list[float]] = {s: [] for s in SERIES_RUN}
    for task, name, path in jobs:
        if name != "curve":
            continue
        real = study.realisations[task.realisation]
        data = SERIES[task.series - 1].data
        with np.load(path, allow_pickle=False) as f:
            run = {k: f[k] for k in ("angles_mean", "mean")}
        true = np.where(real.ok[data], real.angles[data][:, 1], np.nan)
        lin_bound[task.series].append(linear_discrepancy_bound(
            run, real.curves[data], true, cam_sd, w))

    def mean(d: dict[int, dict[str, list[float]]]) -> dict[str, dict[str, float]]:
        return {str(s): {n: round(float(np.mean(v)), 4) for n, v in d[s].items()}
                for s in SERIES_RUN}

    gauge_after: dict[str, list[float]] = {n: [] for n in GAUGE_AFTER}
    for (task, name, _), path in zip(after, after_paths, strict=True):
        real = study.realisations[task.realisation]
        with np.load(path, allow_pickle=False) as f:
            gauge_after[name].append(_final_nrmse(f["angles_mean"][:, 1], np.where(
                real.ok["MM"], real.angles["MM"][:, 1], np.nan), w))
    fm = mean(final)
    ratio = {str(s): round(fm[str(s)]["camera"] / min(fm[str(s)]["curve"], ewma[s]), 4)
             for s in SERIES_RUN}
    cov_cam = [float(np.mean(fcov[s]["camera"])) for s in SERIES_RUN]
    nrmse_report = float(np.nanmean(study.nrmse[0, :, 0, len(spec.augmented) + 1]))
    gauge, camera = (next(s for s in line_sensors(spec) if s.name == n)
                     for n in ("gauge", "camera"))
    bound_sets = {"curve": ([], None), "gauge_0.5um": ([gauge], None),
                  "camera_0.05deg": ([camera], {"camera": 0.05}),
                  "camera_0.2deg": ([camera], None), "both": ([gauge, camera], None)}
    bounds: dict[str, list[float]] = {n: [] for n in bound_sets}
    for real in study.realisations:
        lin = linearise(mm, real.mu, real.theta, settings.seed)
        for n, (chosen, noise) in bound_sets.items():
            bounds[n].append(set_bound(lin, sensor_rows(lin, chosen, spec.state.names,
                                                        noise)).final)
    bound = {n: round(float(np.mean(v)), 4) for n, v in bounds.items()}
    sim_of = {"curve": "curve", "gauge_0.5um": "gauge", "camera_0.2deg": "camera",
              "both": "both"}
    vs = {b: round(fm["1"][s] / bound[b], 4) for b, s in sim_of.items()}
    figures: dict[str, Any] = {
        "s1_final_nrmse_curve": round(nrmse_report, 4),
        "s1_final_nrmse_gauge": fm["1"]["gauge"],
        "s1_final_nrmse_gauge_after_step": {
            f"n{GAUGE_AFTER[n]}": round(float(np.mean(v)), 4) for n, v in gauge_after.items()},
        "final_nrmse_fused_vs_best_single": ratio,
        "final_nrmse_fused_vs_best_single_max": max(ratio.values()),
        "final_nrmse_fused_vs_best_single_s6": ratio["6"],
        "final_coverage90_min": round(min(cov_cam), 4),
        "final_coverage90_max": round(max(cov_cam), 4),
        "bound_s1_final": {k: bound[k] for k in ("curve", "gauge_0.5um", "camera_0.05deg",
                                                 "both")},
        "bound_s1_final_camera_0.2deg": bound["camera_0.2deg"],
        "bound_vs_sim": vs, "bound_vs_sim_min": min(vs.values()),
        "bound_vs_sim_max": max(vs.values()),
        "final_nrmse": fm, "state_nrmse": mean(state), "state_coverage90": mean(scov),
        "state_coverage90_cloud": mean(ccov),
        "final_coverage90": mean(fcov),
        "ewma_final_nrmse": {str(s): round(v, 4) for s, v in ewma.items()},
        "linear_discrepancy_bound": {str(s): round(float(np.mean(v)), 4)
                                     for s, v in lin_bound.items()},
        "linear_discrepancy_bound_vs_best_single": {
            str(s): round(float(np.mean(v)) / min(fm[str(s)]["curve"], ewma[s]), 4)
            for s, v in lin_bound.items()},
        "ewma_weight": {str(s): v for s, v in ewma_w.items()},
        "values_rejected": rejected,
        "settings": {"series": list(SERIES_RUN), "datasets": settings.n_realisations,
                     "products": settings.n_products, "window": w,
                     "n_particles": settings.tracker.n_particles, "seed": settings.seed,
                     "camera_deg": 0.2, "gauge_um": 0.5, "aci_gamma": 0.005,
                     "smoke_test": smoke},
        "study_data_and_curve_runs_s": round(t_study, 1),
        "sensor_runs_s": round(t_runs, 1), "sensor_runs": len(jobs),
    }
    figures.update(sensor_control_figures(settings, out, mm, mm_path, smoke))
    results = Path(__file__).parent / "results" / "bench_sensors.json"
    apart: list[dict[str, Any]] = []
    if not smoke and results.exists():  # study_s: measured apart, kept
        old = json.loads(results.read_text())
        figures.update({k: v for k, v in old["figures"].items() if k in STUDY_FIGURES})
        apart = [e for e in measured_apart(old.get("figures_measured_apart"), [], "")
                 if e["keys"] and all(k in STUDY_FIGURES for k in e["keys"])]
    path = write_result("sensors", figures, directory=out if smoke else None,
                        model=model_info)
    if not smoke and apart:
        doc = json.loads(path.read_text())
        path.write_text(json.dumps({**doc, "figures_measured_apart": apart}, indent=2)
                        + "\n", encoding="utf-8")


if __name__ == "__main__":
    main()
