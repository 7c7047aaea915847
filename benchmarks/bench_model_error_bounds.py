"""Benchmark: how far any statement of the metamodel's error can take the physics series.

The targets of the default likelihood are a state error of at most 0.7 (series 5) and 0.8
(series 6) of the paper's on physics data. This script measures, on the data of
``bench_model_error`` (the study folder ``--out``, seed 0, 5 datasets x 1000 products; made
here if missing), what the same filter (N = 500, the study's seeds, the paper's
``K_MC / 4`` about the filter's mu) reaches when the covariance added for the metamodel's
error is, per line (dataset):

* ``learned``: the default with ``learn_residuals`` (the line's own residual moment,
  learned online from its estimates, :mod:`formtwin.tracker.learned`): a method;
* ``kres_x1``, ``kres_x8``: the bundled ``K_res`` (held-out DOE residuals), times 1 (the
  calibrated likelihood) and 8;
* ``other_lines``: the second moment of ``physics - metamodel`` at the true inputs of the
  *other* four lines' products (statistics learned offline on production-like physics runs,
  leave one line out);
* ``own_residuals``: ``K_res`` plus the second moment of this line's residuals at the
  default filter's own estimates (two passes over the line; what a line could learn itself);
* ``line_oracle``: the second moment of this line's own residuals at the true inputs
  (needs the truth: a bound for any covariance, not a method);
* ``no_error``: the default filter on the metamodel's curves at the true inputs (the data
  with every product's metamodel error removed: series 1's data in series 5, ``g(MM)`` in
  series 6; a bound, not a method).

``default`` and ``paper`` are the study's own runs (repetitions 0..``--repetitions``-1, the
runs ``bench_model_error`` scores). Figures (``benchmarks/results/bench_model_error_bounds.json``),
per series and variant: mean state nRMSE (7 variables, last 500 products, datasets x
repetitions), its ratio to the paper's, per-state nRMSE, the smallest state skill, the final
angle's nRMSE, mean ESS;
in series 1 (metamodel data) only ``learned``; in series 8 (learned mu) ``learned`` and
``no_error``, and ``s8_vs_s6`` (learned over assumed mu) with and without the metamodel's
error. Run under the heavy lock (~6 min on 2 cores when the
study's runs are cached).
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

from formtwin._bench import CACHE, write_result
from formtwin._threads import single_blas_thread
from formtwin.cli import study
from formtwin.defaults import default_metamodel, physics_model
from formtwin.deviation import DeviationModel
from formtwin.measurement import MeasurementModel, monte_carlo_inputs
from formtwin.metamodel import Metamodel
from formtwin.study.metrics import normalised_rmse, normalisers, prior_estimate, rmse
from formtwin.study.pseudodata import Realisation
from formtwin.study.run import run_study
from formtwin.study.series import (  # the study's cached loaders of its files
    SERIES,
    _metamodel,
    _realisation,
    series_config,
)
from formtwin.tracker import TrackerConfig
from formtwin.tracker.build import build_tracker
from formtwin.tracker.discrepancy import residual_covariance

VARIANTS = ("learned", "kres_x1", "kres_x8", "other_lines", "own_residuals", "line_oracle",
            "no_error")
#: ``bench_model_error``'s targets on the state nRMSE ratio to the paper's likelihood
TARGETS = {1: 1.05, 5: 0.7, 6: 0.8}


def variants_of(series: int) -> tuple[str, ...]:
    """The variants run in ``series``: all on physics data (5, 6); the learned residual
    moment on metamodel data (1: what it costs where there is no error); with learned mu
    (8) that and the error-free data (whether learning mu pays once the error is gone)."""
    return {1: ("learned",), 8: ("learned", "no_error")}.get(series, VARIANTS)


def _residual_moment(real: Realisation) -> np.ndarray:
    """Second moment ``E[r r^T]`` (n_t, n_t) of ``physics - metamodel`` at a line's true
    inputs (the ``FE`` and ``MM`` curves of its products), N^2."""
    ok = real.ok["FE"]
    r = real.curves["FE"][ok] - real.curves["MM"][ok]
    return r.T @ r / len(r)


def _own_moment(mm: Metamodel, real: Realisation, series: int, run_path: str) -> np.ndarray:
    """Second moment of the line's residuals at the default filter's estimates: the data
    (``g^-1`` of them with the estimated theta_d in series 6) minus the metamodel at the
    estimated inputs, over the products of the stored run."""
    s = SERIES[series - 1]
    ok = real.ok[s.data]
    with np.load(run_path) as run:
        mean = run["mean"][ok]
    n_in = len(mm.spec.inputs)
    z = real.curves[s.data][ok]
    if s.deviation:
        z = DeviationModel.from_spec(mm.spec).invert(z, mean[:, n_in:])
    r = z - mm.predict_curves(mean[:, :n_in])
    return r.T @ r / len(r)


def variant_run(variant: str, series: int, k: int, rep: int, folder: str, mm_path: str,
                seed: int, base: TrackerConfig, n_lines: int,
                window: int) -> tuple[np.ndarray, np.ndarray, float, float]:
    """One filter run of ``variant`` on line ``k`` -> state nRMSE (7,) and skill (7,), the
    final angle's nRMSE over the last ``window`` products (as the study scores them), mean
    ESS."""
    mm = _metamodel(mm_path)
    spec = mm.spec
    s = SERIES[series - 1]
    data = Path(folder) / "data"
    real = _realisation(str(data / f"realisation_{k}.nc"))
    mu = real.mu if s.mu_known else spec.state.mu_mid
    ss = np.random.SeedSequence([seed, series, k, rep])  # the study's tracker seed
    config = series_config(base, s, mu, int(ss.generate_state(1)[0]))
    ok = real.ok[s.data]
    curves = real.curves[s.data][ok]
    extra = None
    if variant == "no_error":
        curves = real.curves["gMM" if s.deviation else "MM"][ok]
    elif variant == "learned":
        config = dataclasses.replace(config, learn_residuals=True)
    else:
        config = dataclasses.replace(config, likelihood="paper")
        if variant.startswith("kres_x"):
            extra = float(variant[6:]) * residual_covariance(mm)
        elif variant == "other_lines":
            extra = sum(_residual_moment(_realisation(str(data / f"realisation_{j}.nc")))
                        for j in range(n_lines) if j != k) / (n_lines - 1)
        elif variant == "own_residuals":
            run = Path(folder) / "runs" / f"series{series}_real{k}_rep{rep}.npz"
            extra = residual_covariance(mm) + _own_moment(mm, real, series, str(run))
        else:  # line_oracle
            extra = _residual_moment(real)
    # K_MC as the study makes it (same curves, same seed), plus the variant's covariance
    rng = np.random.default_rng(np.random.SeedSequence([seed, 7919, int(s.mu_known)]))
    X = monte_carlo_inputs(spec, config.n_mc, rng, mu)
    with single_blas_thread():
        meas = MeasurementModel.from_curves(mm.predict_curves(X), fraction=config.fraction,
                                            sensor_noise=config.sensor_noise, nu=config.nu,
                                            extra_cov=extra)
        est = build_tracker(mm, config, meas).run(curves)
    n, d = real.n, len(spec.augmented)
    mean, angles = np.full((n, d), np.nan), np.full((n, 2), np.nan)
    mean[ok], angles[ok] = est.mean, est.angles_mean
    source = "MM" if variant == "no_error" else s.data  # the angles of the curves' source
    truth_angles = np.where(ok[:, None], real.angles[source], np.nan)
    nr = normalised_rmse(spec, mean, real.truth, angles, truth_angles, window)
    x = slice(0, len(spec.state))
    prior = rmse(np.tile(prior_estimate(spec, mu)[x], (window, 1)), real.truth[-window:, x])
    return nr[x], 1.0 - nr[x] / (prior / normalisers(spec)[x]), nr[-1], float(np.mean(est.ess))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--out", default=str(CACHE / "study"), help="bench_model_error's folder")
    p.add_argument("--repetitions", type=int, default=2)
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--series", default="1,5,6,8")
    args = p.parse_args()
    out = Path(args.out)
    series = tuple(int(v) for v in args.series.split(","))
    mm, mm_path = default_metamodel(out / "model", "bending")
    base = study.settings_from_args(study.build_namespace(out=str(out), physics="bending"))
    st = dataclasses.replace(base, series=series, n_repetitions=args.repetitions,
                             paper_repetitions=args.repetitions,
                             paper_series=tuple(s for s in series if s in TARGETS))
    ref = run_study(st, out, mm, mm_path, physics_model("bending", mm.spec))
    n_lines, reps = st.n_realisations, args.repetitions
    jobs = [(v, s, k, r) for s in series for v in variants_of(s) for k in range(n_lines)
            for r in range(reps)]
    run = functools.partial(variant_run, folder=str(out), mm_path=str(mm_path), seed=st.seed,
                            base=st.tracker, n_lines=n_lines, window=st.window)
    with ProcessPoolExecutor(args.workers) as pool:
        done = list(pool.map(run, *zip(*jobs, strict=True)))
    results = dict(zip(jobs, done, strict=True))
    figures: dict[str, object] = {"targets_state_ratio": {f"series{s}": t
                                                          for s, t in TARGETS.items()}}
    print(f"{'series':>6} {'variant':>14} {'state nRMSE':>11} {'/ paper':>8} {'min skill':>9}"
          f" {'angle 2':>7} {'ESS':>6}  per state")
    means: dict[tuple[int, str], float] = {}
    for s in series:
        rows = {"default": (ref.nrmse[s - 1, :, :reps, :7], ref.skill[s - 1, :, :reps, :7],
                            ref.nrmse[s - 1, :, :reps, 19], ref.ess[s - 1, :, :reps])}
        if s in TARGETS:
            rows["paper"] = (ref.paper["nrmse"][s - 1, :, :reps, :7],
                             ref.paper["skill"][s - 1, :, :reps, :7],
                             ref.paper["nrmse"][s - 1, :, :reps, 19],
                             ref.paper["ess"][s - 1, :, :reps])
        for v in variants_of(s):
            got = [results[(v, s, k, r)] for k in range(n_lines) for r in range(reps)]
            rows[v] = tuple(np.array([g[i] for g in got]) for i in range(4))
        paper = float(np.mean(rows["paper"][0])) if "paper" in rows else np.nan
        block = {}
        for v, (nr, sk, final, ess) in rows.items():
            nr, sk = nr.reshape(-1, 7), sk.reshape(-1, 7)
            per_state = nr.mean(axis=0)
            means[(s, v)] = float(nr.mean())
            block[v] = {"state_nrmse": round(float(nr.mean()), 4),
                        "state_ratio_to_paper": round(float(nr.mean()) / paper, 4),
                        "per_state_nrmse": [round(float(x), 3) for x in per_state],
                        "min_state_skill": round(float(sk.mean(axis=0).min()), 3),
                        "final_angle_nrmse": round(float(np.nanmean(final)), 4),
                        "mean_ess": round(float(np.mean(ess)), 1)}
            print(f"{s:>6} {v:>14} {nr.mean():11.3f} {nr.mean() / paper:8.3f} "
                  f"{block[v]['min_state_skill']:9.3f} {np.nanmean(final):7.3f} "
                  f"{np.mean(ess):6.1f}  {np.round(per_state, 2)}")
        figures[f"series{s}"] = block
    if 6 in series and 8 in series:  # learned mu over assumed mu, with and without the error
        figures["s8_vs_s6"] = {v: round(means[(8, v)] / means[(6, v)], 4)
                               for v in ("default", "learned", "no_error")}
        print("series 8 / 6 (learned / assumed mu):", figures["s8_vs_s6"])
    figures["states"] = list(mm.spec.state.names)
    figures["settings"] = {"repetitions": reps, "datasets": n_lines, "seed": st.seed,
                           "products": st.n_products, "window": st.window,
                           "particles": st.tracker.n_particles}
    model = {"name": "metamodel of the bundled physics DOE", "physics": "bending",
             "physics_version": mm.model_version, "metamodel_file": str(mm_path)}
    write_result("model_error_bounds", figures, model=model)


if __name__ == "__main__":
    main()
