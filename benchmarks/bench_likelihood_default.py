"""Benchmark: the default likelihood, with or without ``learn_residuals``, each with its
own interval calibration.

Two parts, on the embedded default (bundled metamodel with its 5-fold held-out residual
statistics, N = 500):

1. The study's series (``--series``, default 1, 5, 6) on the study's pseudo-data (seed 0,
   5 datasets x 1000 products, made or reloaded in ``--out``), ``--repetitions`` runs per
   dataset (seeds as the study draws them) with the default tracker and with
   ``learn_residuals = True`` (a sibling folder sharing the data). Per series and setting:
   state nRMSE (7 states) and final-angle nRMSE (mean over datasets and repetitions),
   the coverage of the 90 % intervals (last 500 products; mean over the 7 states, their
   smallest, and the two angles), mean ESS, and the step time (one tracker, one core,
   series 5 dataset 0, ``--time-products`` products). The intervals of each setting are
   scored with the calibration learned for it (the package's
   ``interval_calibration.json`` and ``interval_calibration_learn_residuals.json``, or
   ``--calibration``): where a run was made with another calibration's floors its std
   is rescored from its stored fit distances (``rescore_intervals.py``; exact, the floors
   do not change the means).
2. A mismatch that persists (``bench_monitoring.py``'s force-sensor faults, gain +-10 %
   and offset +-2 N from product ``--at`` for ``--fault-products`` products, on the
   metamodel's curves with the likelihood's noise, mu known): per setting the charts are
   calibrated on its own in-control runs, then the false alarms and alarm episodes per
   10^4 charted in-control products and, after the fault, the products to the first
   mismatch alarm, the share of 50-product windows with one (``signalled_share``) and the
   episodes per 1000 products, counted as ``bench_monitoring.py`` counts them (smaller
   sizes than there: ``--calib-runs``, ``--ic-runs``, ``--fault-reps``).

Writes ``benchmarks/results/bench_likelihood_default.json`` (``--quick``: smoke sizes,
printed only).
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

import bench_monitoring as bm
import numpy as np
from rescore_intervals import run_coverage

from formtwin._bench import CACHE, write_result
from formtwin._threads import single_blas_thread
from formtwin.defaults import default_metamodel, physics_model
from formtwin.monitoring.calibrate import ChartDesign, calibrate_series, in_control_runs
from formtwin.monitoring.scenarios import Change, Fault
from formtwin.study.keys import cache_key
from formtwin.study.run import StudyResult, StudySettings, run_study
from formtwin.study.series import SERIES, Task, measurement_file, prepare
from formtwin.tracker import TrackerConfig
from formtwin.tracker.build import build_measurement
from formtwin.tracker.intervals import calibration_path

SETTINGS = {"default": False, "learn_residuals": True}


def _mean(a: Any, axis: Any = None) -> Any:
    with np.errstate(all="ignore"):
        return np.nanmean(a, axis=axis)


def step_ms(settings: StudySettings, folder: Path, mm_path: Path, products: int
            ) -> tuple[float, dict[str, Any] | None]:
    """Milliseconds per product of one series-5 tracker of ``settings`` on dataset 0 (one
    core), and the interval calibration that tracker found."""
    tracker, known = settings.tracker, SERIES[4].mu_known
    real = folder / "data" / "realisation_0.nc"
    meas = measurement_file(folder, 0, known, tracker.likelihood, cache_key(
        tracker.to_dict(), settings.seed, known, files=(mm_path, real)))
    task = Task(5, 0, 0, str(mm_path), str(real), str(meas), "", tracker, settings.seed, "")
    trk, _, curves, u = prepare(task)
    with single_blas_thread():
        t0 = time.perf_counter()
        trk.run(curves[:products], u=None if u is None else u[:products])
        ms = (time.perf_counter() - t0) / products * 1e3
    return ms, trk.floors.calibration.data if trk.floors is not None else None


def study_block(res: StudyResult, folder: Path, cal: dict[str, Any] | None,
                used: dict[str, Any] | None, reps: int) -> dict[str, Any]:
    """Figures per series of one setting's runs (``cal``: its calibration, ``used``: the
    one its runs were made with; rescored where they differ)."""
    rescore = cal is not None and used is not None and cal != used
    nx = len(res.realisations[0].x[0])
    n_aug = len(res.realisations[0].truth[0])
    out: dict[str, Any] = {}
    for s in res.settings.series:
        cov = []
        for k in range(res.settings.n_realisations):
            for r in range(reps):
                path = folder / "runs" / f"series{s}_real{k}_rep{r}.npz"
                cov.append(run_coverage(path, s, k, folder / "data", used or {}, cal)
                           if rescore else
                           np.r_[res.coverage[s - 1, k, r, :nx],
                                 res.coverage[s - 1, k, r, n_aug:n_aug + 2]])
        c = _mean(np.array(cov), axis=0)
        out[f"series{s}"] = {
            "state_nrmse": round(float(_mean(res.nrmse[s - 1, :, :reps, :nx])), 4),
            "final_angle_nrmse": round(float(_mean(res.nrmse[s - 1, :, :reps, n_aug + 1])), 4),
            "stage1_angle_nrmse": round(float(_mean(res.nrmse[s - 1, :, :reps, n_aug])), 4),
            "state_coverage90_mean": round(float(np.mean(c[:nx])), 3),
            "state_coverage90_min": round(float(np.min(c[:nx])), 3),
            "state_coverage90": [round(float(v), 3) for v in c[:nx]],
            "angle_coverage90": [round(float(v), 3) for v in c[nx:]],
            "mean_ess": round(float(_mean(res.ess[s - 1, :, :reps])), 1),
            "intervals_rescored": rescore}
    return out


def monitoring_block(learn: bool, args: argparse.Namespace) -> dict[str, Any]:
    """False alarms in control and the persistent faults' alarms of one setting."""
    from formtwin._bench import bundled_metamodel
    model, _, info = bundled_metamodel()
    mu = model.spec.state.mu_mid
    tcfg = TrackerConfig(n_particles=args.particles, mu=tuple(mu), seed=args.seed,
                         learn_residuals=learn)
    mm = build_measurement(model, tcfg, np.random.default_rng(args.seed))
    key = {"metamodel": info["metamodel"], "tracker": tcfg.to_dict(),
           "code": bm.estimates_code(), "seed": args.seed, "at": args.at,
           "purpose": "bench_likelihood_default"}
    runs = bm.Runs(CACHE / "likelihood_default_monitoring", key)
    names = model.spec.state.names
    n_fault = args.at + args.fault_products
    with single_blas_thread():
        calib = [runs.get(f"calib{r}_{args.calib_products}", lambda r=r: in_control_runs(
            model, mm, dataclasses.replace(tcfg, seed=tcfg.seed + r), args.calib_products, 1,
            seed=args.seed + r)[0]) for r in range(args.calib_runs)]
        ic = [runs.get(f"ic{r}_{args.ic_products}", lambda r=r: in_control_runs(
            model, mm, dataclasses.replace(tcfg, seed=tcfg.seed + 5000 + r), args.ic_products,
            1, seed=args.seed + 10_000 + r)[0]) for r in range(args.ic_runs)]
        faults: dict[str, list[bm.Series]] = {}
        for k, (g, o) in enumerate(bm.FAULTS):
            fault = Fault(args.at, g, o)
            faults[f"gain{g:+g}_offset{o:+g}"] = [runs.get(
                f"fault_{g:+g}_{o:+g}_{r}_{n_fault}", lambda f=fault, s=args.seed + 300_000
                + 100 * k + r: bm.changed(model, mm, tcfg, Change("none"), n_fault, s, True,
                                          f))[0] for r in range(args.fault_reps)]
    truths = [np.column_stack([t[n] for n in names]) for _, t in calib]
    config = calibrate_series([e for e, _ in calib], names, mu, ChartDesign(), truths)
    charted = len(ic) * (args.ic_products - config.warmup - config.phase1)
    ic_alarms = sum(len(bm.chart(config, e)) for e, _ in ic)
    ic_eps = sum(len(bm.episodes(config, e)) for e, _ in ic)
    per_fault = {k: [bm.persistence(bm.chart(config, s), bm.episodes(config, s), args.at,
                                    n_fault) for s in v] for k, v in faults.items()}
    flat = [r for v in per_fault.values() for r in v]
    first = [r["first_mismatch"] for r in flat if r["first_mismatch"] is not None]
    return {
        "false_alarms_per_10k_products": round(ic_alarms / charted * 1e4, 2),
        "false_alarm_episodes_per_10k_products": round(ic_eps / charted * 1e4, 2),
        "false_alarm_episodes_in_control": ic_eps, "charted_products_in_control": charted,
        "fault_runs": len(flat), "fault_detected": len(first),
        "fault_first_mismatch_median": float(np.median(first)) if first else None,
        "fault_signalled_share_mean": round(float(np.mean(
            [r["signalled_share"] for r in flat])), 3),
        "fault_episodes_per_1000_mean": round(float(np.mean(
            [r["episodes_per_1000"] for r in flat])), 1),
        "per_fault": {k: [{n: r[n] for n in ("first_mismatch", "signalled_share",
                                             "episodes_per_1000")} for r in v]
                      for k, v in per_fault.items()}}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", default=str(CACHE / "likelihood_default"))
    p.add_argument("--series", default="1,5,6")
    p.add_argument("--repetitions", type=int, default=2)
    p.add_argument("--calibration", help="learn_residuals' calibration (JSON; default: the "
                   "package's)")
    p.add_argument("--time-products", type=int, default=300)
    p.add_argument("--particles", type=int, default=500)
    p.add_argument("--seed", type=int, default=2026)
    p.add_argument("--at", type=int, default=250)
    p.add_argument("--fault-products", type=int, default=750)
    p.add_argument("--fault-reps", type=int, default=1)
    p.add_argument("--calib-runs", type=int, default=6)
    p.add_argument("--calib-products", type=int, default=1000)
    p.add_argument("--ic-runs", type=int, default=4)
    p.add_argument("--ic-products", type=int, default=1500)
    p.add_argument("--skip-study", action="store_true")
    p.add_argument("--skip-monitoring", action="store_true")
    p.add_argument("--quick", action="store_true", help="smoke sizes, printed only")
    args = p.parse_args()
    out = Path(args.out)
    products, datasets = 1000, 5
    if args.quick:  # one dataset of the study's data (its runs are reused by a full run)
        datasets, args.series, args.repetitions, args.time_products = 1, "5", 1, 30
        args.fault_products, args.at, args.fault_reps = 150, 100, 1
        args.calib_runs, args.calib_products, args.ic_runs, args.ic_products = 2, 300, 1, 300
    t0 = time.perf_counter()
    figures: dict[str, Any] = {"settings": {
        "particles": args.particles, "series": args.series, "repetitions": args.repetitions,
        "products": products, "window": products // 2, "study_seed": 0,
        "monitoring": {k: getattr(args, k) for k in ("seed", "at", "fault_products",
                                                     "fault_reps", "calib_runs",
                                                     "calib_products", "ic_runs",
                                                     "ic_products")}}}
    if not args.skip_monitoring:  # one process per setting (each tracks sequentially)
        with ProcessPoolExecutor(len(SETTINGS)) as pool:
            blocks = {name: pool.submit(monitoring_block, learn, args)
                      for name, learn in SETTINGS.items()}
            for name, fut in blocks.items():
                figures[name] = {"persistent_mismatch": fut.result()}
    if not args.skip_study:
        cals = {name: json.loads(Path(args.calibration if (learn and args.calibration) else
                                      calibration_path(learn)).read_text("utf-8"))
                for name, learn in SETTINGS.items()}
        mm, mm_path = default_metamodel(out / "model", "bending")
        physics = physics_model("bending", mm.spec)
        base = StudySettings(n_products=products, window=products // 2,
                             n_realisations=datasets,
                             series=tuple(int(s) for s in args.series.split(",")),
                             n_repetitions=args.repetitions, paper_repetitions=0)
        for name, learn in SETTINGS.items():
            folder = out if not learn else out.parent / f"{out.name}_{name}"
            folder.mkdir(parents=True, exist_ok=True)
            if learn:
                if not (folder / "data").is_symlink():
                    (folder / "data").symlink_to((out / "data").resolve())
            settings = dataclasses.replace(base, tracker=dataclasses.replace(
                base.tracker, learn_residuals=learn))
            t1 = time.perf_counter()
            res = run_study(settings, folder, mm, mm_path, physics)
            runs_s = time.perf_counter() - t1
            ms, used = step_ms(settings, folder, mm_path, args.time_products)
            figures[name] = {
                **figures.get(name, {}),
                **study_block(res, folder, cals[name], used, args.repetitions),
                "step_ms": round(ms, 2),
                "calibration": {"settings": cals[name].get("settings"),
                                "used_by_the_tracker": used == cals[name]},
                "runs_s": round(runs_s, 1)}
    figures["total_s"] = round(time.perf_counter() - t0, 1)
    figures["load_average_1min_end"] = round(os.getloadavg()[0], 2)
    if args.quick:
        print(json.dumps(figures, indent=1))
        return
    write_result("likelihood_default", figures)


if __name__ == "__main__":
    main()
