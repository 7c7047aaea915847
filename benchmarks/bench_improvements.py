"""Benchmark: learned statistics mu (series 7, 8) against the paper's mid-range mu (4, 6).

The paper's Discussion proposes to identify the statistics mu during the estimation
instead of assuming ``(mu_min + mu_max)/2`` (its series 4 and 6). Series 7 and 8 of
:mod:`formtwin.study.series` do that (``TrackerConfig(learn_mu=True)``) on the same data
and K_MC as series 4 and 6. This script runs the pairs with plain SIR at the paper's N = 500
on the embedded default (bundled physics DOE, its metamodel) and reports per series:

* ``state_nrmse``: normalised RMSE over the last ``window`` products, mean over the 7 state
  variables (and ``state_nrmse_per_variable``);
* ``angles_nrmse``: the same for the two angles;
* for the learned-mu series, ``mu_error_over_sigma``: mean ``|E[mu] - mu_true| / sigma``
  after the last product (per variable and averaged), next to the same figure for the
  mid-range guess (``midrange_mu_error_over_sigma``).

The pseudo-data are those of the full study (``--data``, default
``benchmarks/.cache/study/data``, linked into ``--out``); nothing in the study folder is
written. Filter runs are cached in ``--out``/runs.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import xarray as xr

from formtwin._bench import study_metamodel_info, write_result
from formtwin.defaults import bundled_metamodel, default_metamodel, physics_model
from formtwin.study.pseudodata import Realisation
from formtwin.study.run import StudySettings, run_study
from formtwin.study.series import SERIES
from formtwin.tracker import TrackerConfig


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--out", default="benchmarks/.cache/improvements")
    parser.add_argument("--data", default="benchmarks/.cache/study/data")
    parser.add_argument("--metamodel", default=str(bundled_metamodel("bending")),
                        help="metamodel file (default: the bundled one)")
    parser.add_argument("--series", default="4,7,6,8")
    parser.add_argument("--products", type=int, default=1000)
    parser.add_argument("--window", type=int, default=500)
    parser.add_argument("--realisations", type=int, default=5)
    parser.add_argument("--repetitions", type=int, default=5)
    parser.add_argument("--particles", type=int, default=500)
    parser.add_argument("--workers", type=int)
    args = parser.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    data = Path(args.data)
    if data.is_dir() and not (out / "data").exists():
        (out / "data").symlink_to(data.resolve(), target_is_directory=True)
    first = out / "data" / "realisation_0.nc"
    if (out / "data").is_symlink() and first.exists():  # never regenerate the study's data
        with xr.open_dataset(first, engine="h5netcdf") as ds:
            n_cached = Realisation.from_dataset(ds.load()).n
        if n_cached != args.products:
            parser.error(f"--products {args.products}: the linked data hold {n_cached}")
    mm_file = Path(args.metamodel)
    metamodel, mm_path = default_metamodel(out / "model", "bending",
                                           mm_file if mm_file.exists() else None)
    spec = metamodel.spec
    settings = StudySettings(n_products=args.products, window=args.window,
                             n_realisations=args.realisations,
                             n_repetitions=args.repetitions,
                             tracker=TrackerConfig(n_particles=args.particles),
                             series=tuple(int(s) for s in args.series.split(",")),
                             workers=args.workers)
    t0 = time.perf_counter()
    result = run_study(settings, out, metamodel, mm_path, physics_model("bending", spec))
    wall = time.perf_counter() - t0
    nx = len(spec.state)
    n_aug = len(spec.augmented)
    sigma = spec.state.sigma
    mid = spec.state.mu_mid
    figures: dict[str, object] = {
        "settings": {"products": args.products, "window": args.window,
                     "realisations": args.realisations, "repetitions": args.repetitions,
                     "particles": args.particles, "filter": "sir", "alpha": settings.tracker.alpha,
                     "learn_mu": "conjugate", "metamodel": str(mm_path)},
        "wall_s": round(wall, 1),
        "filter_runs_computed": int(result.timings.get("filter_runs_computed", 0)),
    }
    for s in settings.series:
        nr = result.nrmse[s - 1]  # (realisation, repetition, component)
        entry: dict[str, object] = {
            "label": SERIES[s - 1].label,
            "state_nrmse": round(float(np.nanmean(nr[..., :nx])), 4),
            "angles_nrmse": round(float(np.nanmean(nr[..., n_aug:n_aug + 2])), 4),
            "state_nrmse_per_variable": {
                n: round(float(np.nanmean(nr[..., j])), 4) for j, n in enumerate(spec.state.names)},
            "state_nrmse_per_dataset": [round(float(np.nanmean(nr[k, :, :nx])), 4)
                                        for k in range(args.realisations)],
        }
        truth = np.array([r.mu for r in result.realisations])  # (K, 7)
        entry["midrange_mu_error_over_sigma"] = round(
            float(np.mean(np.abs(mid - truth) / sigma)), 4)
        if SERIES[s - 1].learn_mu:
            err = np.full((args.realisations, args.repetitions, nx), np.nan)
            for (ss, k, r), p in result.run_paths.items():
                if ss != s:
                    continue
                with np.load(p, allow_pickle=False) as run:
                    mu_mean = run["mu_mean"]
                last = mu_mean[np.all(np.isfinite(mu_mean), axis=1)][-1]
                err[k, r] = np.abs(last - truth[k]) / sigma
            entry["mu_error_over_sigma"] = round(float(np.mean(err)), 4)
            entry["mu_error_over_sigma_per_variable"] = {
                n: round(float(np.mean(err[..., j])), 4) for j, n in enumerate(spec.state.names)}
            entry["midrange_mu_error_over_sigma_per_variable"] = {
                n: round(float(np.mean(np.abs(mid[j] - truth[:, j]) / sigma[j])), 4)
                for j, n in enumerate(spec.state.names)}
        figures[f"series{s}"] = entry
    write_result("improvements", figures, model=study_metamodel_info(metamodel, mm_path))


if __name__ == "__main__":
    main()
