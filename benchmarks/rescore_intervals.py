"""Coverage of stored study runs with another interval calibration, without re-running them.

The calibrated, fit-gated intervals add ``s b_fit^2`` to the variance the filter reports
without floors (:class:`formtwin.tracker.intervals.Floors`); the means, the fit distances
and that variance do not depend on the floors. So a run's std under a calibration ``new``
is ``sqrt(std^2 - s_old b_old^2 + s_new b_new^2)`` with each gate ``s`` recomputed from the
run's stored fit distances (tested: with ``new = old`` it returns the stored coverage).

Usage (after ``python benchmarks/bench_model_error.py``, which leaves the option
``learn_residuals``'s runs in ``benchmarks/.cache/study_learn_residuals``, and
``python -m formtwin.study.calibrate --learn-residuals --write CAL.json``)::

    python benchmarks/rescore_intervals.py --calibration CAL.json

prints the coverage of the 90 % intervals (7 states, 2 angles; repetition 0, mean over the
datasets) per series of the default's runs, the option's as stored (the shipped floors) and
the option's under ``CAL.json``, and the range over series 1, 3, 5, 6 (``bench_model_error``'s
``coverage90_min/max``).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np

from formtwin._bench import CACHE
from formtwin.study.metrics import coverage
from formtwin.study.series import SERIES, _realisation
from formtwin.tracker.intervals import CALIBRATION_PATH, fit_ewma, gate_scale

ISSUE_SERIES = (1, 3, 5, 6)


def gated_variance(cal: dict[str, Any], key: str, d2: np.ndarray) -> np.ndarray:
    """``s b_fit^2`` (n, 20) of calibration ``cal``'s entry ``key`` for a run's fit
    distances ``d2`` (n,)."""
    E = fit_ewma(d2, cal["fit_gate"]["ewma"])[0]
    s = gate_scale(E, cal["fit_gate"]["d0"], cal[key]["fit_s_max"])
    b = np.r_[cal[key]["fit_floors"], cal[key]["fit_angle_floors"]]
    out: np.ndarray = s[:, None] * b**2
    return out


def run_coverage(path: Path, series: int, k: int, data: Path, old: dict[str, Any],
                 new: dict[str, Any] | None) -> np.ndarray:
    """Coverage (9,) of the 7 states and 2 angles of one run, over its last 500 products,
    under ``new`` (None: as stored)."""
    s = SERIES[series - 1]
    real = _realisation(str(data / f"realisation_{k}.nc"))
    with np.load(path) as f:
        run = {n: f[n] for n in f.files}
    std = np.c_[run["std"], run["angles_std"]]
    if new is not None:
        key = "deviation" if s.deviation else "no_deviation"
        d2 = run["fit_distance2"]
        var = std**2 - gated_variance(old, key, d2) + gated_variance(new, key, d2)
        std = np.sqrt(np.maximum(var, 0.0))
    angles = np.where(real.ok[s.data][:, None], real.angles[s.data], np.nan)
    c = np.r_[coverage(run["mean"], std[:, :18], real.truth),
              coverage(run["angles_mean"], std[:, 18:], angles)]
    return np.r_[c[:7], c[18:20]]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--calibration", required=True, help="the other calibration (JSON)")
    p.add_argument("--default", default=str(CACHE / "study"), help="the default's study")
    p.add_argument("--option", default=str(CACHE / "study_learn_residuals"))
    p.add_argument("--series", default="1,3,4,5,6")
    p.add_argument("--datasets", type=int, default=5)
    args = p.parse_args()
    old = json.loads(CALIBRATION_PATH.read_text(encoding="utf-8"))
    new = json.loads(Path(args.calibration).read_text(encoding="utf-8"))
    data = Path(args.default) / "data"
    series = [int(v) for v in args.series.split(",")]
    rows = {"default": (Path(args.default), None), "option": (Path(args.option), None),
            "option, new floors": (Path(args.option), new)}
    table: dict[str, dict[int, np.ndarray]] = {name: {} for name in rows}
    for s in series:
        for name, (folder, cal) in rows.items():
            c = np.nanmean([run_coverage(folder / "runs" / f"series{s}_real{k}_rep0.npz", s, k,
                                         data, old, cal) for k in range(args.datasets)],
                           axis=0)
            table[name][s] = c
            print(f"series {s} {name:>18}: {np.round(c, 3)}")
    for name, by_series in table.items():
        sel = np.concatenate([c for s, c in by_series.items() if s in ISSUE_SERIES])
        print(f"{name:>18}: coverage90 over series 1, 3, 5, 6 {sel.min():.3f} - {sel.max():.3f}")


if __name__ == "__main__":
    main()
