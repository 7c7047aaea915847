"""Benchmark: deviation models chosen by evidence on series-6 data.

Series 6 (data ``g(FE)``: physics-model curves distorted by the paper's 4+4-knot ``g`` with
the realisation's theta_d; filter ``g(MM)`` estimating theta_d, mu assumed mid-range,
the default likelihood, N = 500) with deviation models of 2, 3, 4 (the paper's) and 6 knots
each for force and speed scaling. The filter's model differs only in the spec's
``[deviation] knots`` (same metamodel, same K_MC, same tracker seed). Per model: the
cumulative log-evidence ``sum_i log p(z_i | z_1..i-1)`` over the 1000 products (higher:
the data are more probable under that model), the mean state nRMSE over the last 500
products and the coverage of the 90 % intervals of the states (the particles' own std,
``intervals="cloud"`` for every model: the bundled interval calibration has floors for the
4+4 model only); per dataset and averaged.
The data come from ``--data`` (the full study's pseudo-data).
"""

from __future__ import annotations

import argparse
import re
from concurrent.futures import ProcessPoolExecutor
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np
import xarray as xr

from formtwin._bench import study_metamodel_info, write_result
from formtwin._threads import single_blas_thread
from formtwin.defaults import bundled_metamodel
from formtwin.metamodel import Metamodel
from formtwin.spec import ProcessSpec, parse_spec
from formtwin.study.metrics import coverage, normalised_rmse
from formtwin.study.pseudodata import Realisation
from formtwin.study.series import SERIES, series_config
from formtwin.tracker import TrackerConfig, build_measurement, build_tracker

KNOTS = (2, 3, 4, 6)
#: the intervals of every model (the calibrated floors exist for the 4+4 model only)
INTERVALS = "cloud"


class WithDeviation:
    """The metamodel seen through a spec with another number of deviation knots."""

    def __init__(self, model: Metamodel, knots: int) -> None:
        text = re.sub(r"(?m)^knots = \d+", f"knots = {knots}", model.spec_text)
        self._spec: ProcessSpec = parse_spec(text, f"{model.spec.source} ({knots} knots)")
        self.model = model
        self.residuals = model.residuals

    @property
    def spec(self) -> ProcessSpec:
        """The spec with ``knots`` deviation knots."""
        return self._spec

    def predict_curves(self, X: np.ndarray) -> np.ndarray:
        """The metamodel's curves."""
        return self.model.predict_curves(X)

    def predict_angles(self, X: np.ndarray, u: Any = None) -> np.ndarray:
        """The metamodel's angles (at press settings ``u``, None: nominal)."""
        return self.model.predict_angles(X, u)


@lru_cache(maxsize=1)
def _metamodel(path: str) -> Metamodel:
    return Metamodel.load(path)


def one_run(mm_path: str, data: str, k: int, knots: int) -> dict[str, Any]:
    """Series 6 on dataset ``k`` with a ``knots``-knot deviation model."""
    mm = _metamodel(mm_path)
    model = WithDeviation(mm, knots)
    with xr.open_dataset(Path(data) / f"realisation_{k}.nc", engine="h5netcdf") as ds:
        real = Realisation.from_dataset(ds.load())
    spec = model.spec
    cfg = series_config(TrackerConfig(intervals=INTERVALS), SERIES[5], spec.state.mu_mid,
                        seed=1000 + k)
    with single_blas_thread():
        meas = build_measurement(model, cfg, np.random.default_rng(k))
        est = build_tracker(model, cfg, meas).run(real.curves["gFE"][real.ok["gFE"]])
    ok = real.ok["gFE"]
    truth = real.inputs[ok]  # theta_d differs in size between models: score x and theta
    n_in = spec.n_inputs
    nr = normalised_rmse(mm.spec, np.c_[est.mean[:, :n_in], np.zeros((ok.sum(), 8))],
                         np.c_[truth, np.zeros((ok.sum(), 8))], est.angles_mean,
                         real.angles["FE"][ok])
    cov = coverage(est.mean[:, :7], est.std[:, :7], truth[:, :7])
    return {"dataset": k, "knots": knots, "log_evidence": float(np.sum(est.loglik)),
            "state_nrmse": float(nr[:7].mean()), "angles_nrmse": [float(v) for v in nr[18:]],
            "coverage_state": float(cov.mean()), "mean_ess": float(np.mean(est.ess))}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--data", default="benchmarks/.cache/study/data")
    parser.add_argument("--metamodel", default=str(bundled_metamodel("bending")))
    parser.add_argument("--datasets", type=int, default=5)
    parser.add_argument("--workers", type=int, default=2)
    args = parser.parse_args()
    jobs = [(args.metamodel, args.data, k, n) for k in range(args.datasets) for n in KNOTS]
    with ProcessPoolExecutor(args.workers) as pool:
        rows = list(pool.map(one_run, *zip(*jobs, strict=True)))
    figures: dict[str, Any] = {"per_run": rows}
    summary = {}
    for n in KNOTS:
        mine = [r for r in rows if r["knots"] == n]
        summary[f"knots{n}"] = {
            "log_evidence": round(float(np.mean([r["log_evidence"] for r in mine])), 1),
            "state_nrmse": round(float(np.mean([r["state_nrmse"] for r in mine])), 4),
            "coverage_state": round(float(np.mean([r["coverage_state"] for r in mine])), 3),
            "mean_ess": round(float(np.mean([r["mean_ess"] for r in mine])), 1),
            "wins_by_evidence": sum(
                r["log_evidence"] == max(q["log_evidence"] for q in rows
                                         if q["dataset"] == r["dataset"]) for r in mine)}
    figures["summary"] = summary
    winner = max(summary, key=lambda key: summary[key]["log_evidence"])
    figures["winner_by_mean_log_evidence"] = winner
    figures["winner_state_nrmse_vs_paper"] = round(
        summary[winner]["state_nrmse"] / summary["knots4"]["state_nrmse"], 4)
    figures["settings"] = {"series": 6, "likelihood": TrackerConfig().likelihood,
                           "intervals": INTERVALS,
                           "particles": TrackerConfig().n_particles, "knots": list(KNOTS),
                           "datasets": args.datasets, "metamodel": args.metamodel}
    write_result("deviation_models", figures,
                 model=study_metamodel_info(_metamodel(args.metamodel), args.metamodel))


if __name__ == "__main__":
    main()
