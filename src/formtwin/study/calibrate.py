"""The interval calibration of ``TrackerConfig(intervals="calibrated")``, learned offline on
physics runs of its own (``python -m formtwin.study.calibrate``).

Under the metamodel's error the posterior is overconfident, and the largest part of the
error is a bias that neither the particle cloud nor the linear response to ``K_res``
(:mod:`formtwin.tracker.intervals`) shows (docs/explanation/likelihood.md). As ``K_res`` is
learned on held-out DOE runs, this learns per component the floor ``b`` that, added in
quadrature to the cloud's std, makes the 90 % interval ``mean +- 1.645 sqrt(std^2 + b^2)`` hold the
truth in 90 % of the products of independent physics pseudo-data: realisations drawn with
the study seed :data:`SEED` (the study's default is 0, so they share no realisation with
the study or the benchmarks), filtered as series 5 (no deviation model) and series 6
(deviation estimated, mu assumed), the last ``window`` products of each run. The runs'
std are the cloud's plus, where mu is assumed (series 6), the linearised error of assuming
it (:mod:`formtwin.tracker.sandwich`), so the floors cover what that term does not. The floors
are stored with the metamodel's fit id and, as a sanity check, the diagonal of its
``K_res`` (:func:`~formtwin.tracker.intervals.find_calibration`): another fit gets none.
``formtwin metamodel calibrate`` learns and stores them for any metamodel file.

The fit gate of ``intervals="calibrated_fit"`` (:class:`~formtwin.tracker.intervals.Floors`)
is learned on the same runs: ``d0``, the mean running fit distance on the metamodel's own
curves, from series 1 runs of the same realisations (metamodel data, mu known), and floors
``b_fit`` per unit of the gate's factor ``s``: ``b_fit^2`` the ``target`` quantile of
``need / s``, so they too hold 90 % on these runs.

>>> import numpy as np
>>> err = np.array([[0.0], [1.0], [2.0], [3.0]]); std = np.full((4, 1), 1.0)
>>> b = learn_floors(err, std, target=0.75, z=1.0)   # needs b^2 = 0, 0, 3, 8: the 75 %
>>> round(float(b[0]) ** 2, 6)                       # quantile (linear interpolation)
4.25
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from formtwin.defaults import default_metamodel, physics_model
from formtwin.metamodel import Metamodel
from formtwin.simulator import Simulator
from formtwin.study.metrics import Z90
from formtwin.study.run import StudyResult, StudySettings, run_study
from formtwin.study.series import SERIES
from formtwin.tracker import TrackerConfig
from formtwin.tracker.intervals import (
    CALIBRATION_PATH,
    calibration_path,
    fit_ewma,
    gate_scale,
    residual_rule,
    residual_signature,
)

FloatArray = NDArray[np.float64]

#: study seed of the calibration's own pseudo-data (the study and the benchmarks use 0)
SEED = 8101
#: the series whose runs give the floors of a tracker without / with the deviation model
SERIES_OF = {"no_deviation": 5, "deviation": 6}
#: the series whose runs give the fit gate's ``d0`` (the metamodel's own curves)
GATE_SERIES = 1
#: weight of the newest product in the fit gate's running mean (a memory of ~20 products)
FIT_EWMA = 0.05


def learn_floors(err: FloatArray, std: FloatArray, target: float = 0.9,
                 z: float = Z90, scale: FloatArray | None = None) -> FloatArray:
    """Floors ``b`` (d,) with ``mean(|err| <= z sqrt(std^2 + s b^2)) = target`` per column
    of the errors ``err`` and the cloud's ``std`` (n, d) (rows with NaN left out; 0 where
    the cloud's intervals already hold ``target``), ``s`` the rows' ``scale`` (n,) >= 0
    (default 1): ``b^2`` is the ``target`` quantile of ``max((err / z)^2 - std^2, 0) / s``
    (a row that needs a floor where ``s = 0`` is not covered by any).

    >>> b = learn_floors(np.array([[2.0], [2.0]]), np.zeros((2, 1)), 1.0, 1.0,
    ...                  scale=np.array([4.0, 1.0]))
    >>> float(b[0])   # needs b^2 >= 4 / 4 and 4 / 1: both covered from b = 2
    2.0
    """
    s = np.ones(err.shape[0]) if scale is None else np.asarray(scale, dtype=np.float64)
    out = np.zeros(err.shape[1])
    for j in range(err.shape[1]):
        ok = np.isfinite(err[:, j]) & np.isfinite(std[:, j])
        if ok.any():
            need = np.maximum((err[ok, j] / z) ** 2 - std[ok, j] ** 2, 0.0)
            per = np.divide(need, s[ok], out=np.where(need > 0, np.inf, 0.0),
                            where=s[ok] > 0)
            out[j] = float(np.sqrt(np.quantile(per, target)))
    return out


def gate_d0(result: StudyResult, a: float = FIT_EWMA) -> tuple[float, int]:
    """The fit gate's ``d0``: the mean running fit distance (weight ``a``) over the last
    ``window`` products of every :data:`GATE_SERIES` run in ``result``, and the runs."""
    window, runs = result.settings.window, []
    for (s, _i, _r), path in sorted(result.run_paths.items()):
        if s == GATE_SERIES:
            with np.load(path) as run:
                runs.append(fit_ewma(run["fit_distance2"], a)[0][-window:])
    return float(np.nanmean(np.concatenate(runs))), len(runs)


def floors_from_study(result: StudyResult, series: int, d0: float,
                      a: float = FIT_EWMA) -> dict[str, Any]:
    """Floors of the augmented components and the outputs from every run of ``series`` in
    ``result`` (last ``window`` products), constant and fit-gated (``d0``, weight ``a``;
    none, with ``fit_gate_unusable`` saying why, where the gate is 0 on rows that need a
    floor), with the coverage of the cloud's and of the calibrated intervals on these
    runs."""
    window = result.settings.window
    src = SERIES[series - 1].data
    n_out = result.realisations[0].angles[src].shape[1]  # the spec's scalar outputs
    errs, stds, E = [], [], []
    for (s, i, _r), path in sorted(result.run_paths.items()):
        if s != series:
            continue
        real = result.realisations[i]
        with np.load(path) as run:
            errs.append(np.c_[run["mean"] - real.truth,
                              run["angles_mean"] - real.angles[src]][-window:])
            stds.append(np.c_[run["std"], run["angles_std"]][-window:])
            E.append(fit_ewma(run["fit_distance2"], a)[0][-window:])
    err, std, e = np.concatenate(errs), np.concatenate(stds), np.concatenate(E)
    b = learn_floors(err, std)
    s_max = float(np.nanmax(e)) - d0
    gate = gate_scale(e, d0, s_max)[:, None]
    b_fit = learn_floors(err, std, scale=gate[:, 0])
    gate_ok = s_max > 0 and bool(np.all(np.isfinite(b_fit)))

    def cover(s: FloatArray) -> list[float]:
        with np.errstate(invalid="ignore"):
            inside = np.where(np.isfinite(err) & np.isfinite(s), np.abs(err) <= Z90 * s, np.nan)
        return [round(float(v), 3) for v in np.nanmean(inside, axis=0)]

    if not SERIES[series - 1].deviation:  # theta_d is not estimated (std 0): no floor
        real = result.realisations[0]
        b[real.x.shape[1] + real.theta.size:-n_out] = 0.0
        b_fit[real.x.shape[1] + real.theta.size:-n_out] = 0.0
    out: dict[str, Any] = {
        "series": series, "runs": len(errs), "floors": [float(v) for v in b[:-n_out]],
        "angle_floors": [float(v) for v in b[-n_out:]],
        "fit_distance_mean": round(float(np.nanmean(e)), 3), "coverage_cloud": cover(std),
        "coverage_calibrated_in_sample": cover(np.sqrt(std**2 + b**2))}
    if not gate_ok:  # Floors then uses the constant floors for "calibrated_fit" too
        out["fit_gate_unusable"] = (f"the fit gate is 0 where floors are needed (d0 = "
                                    f"{d0:.3g}, largest running fit distance {s_max + d0:.3g})")
        return out
    return out | {"fit_floors": [float(v) for v in b_fit[:-n_out]],
                  "fit_angle_floors": [float(v) for v in b_fit[-n_out:]], "fit_s_max": s_max,
                  "coverage_calibrated_fit_in_sample": cover(np.sqrt(std**2 + gate * b_fit**2))}


def learn_calibration(mm: Metamodel, mm_path: Path, physics: Simulator, folder: Path,
                      datasets: int = 8, repetitions: int = 2, products: int = 1000,
                      seed: int = SEED, learn_residuals: bool = False) -> dict[str, Any]:
    """The interval calibration of the metamodel ``mm`` (file ``mm_path``, fit
    :attr:`~formtwin.metamodel.Metamodel.fit_id`): ``datasets`` realisations of
    ``products`` products of physics pseudo-data made with ``physics`` (study seed
    ``seed``, not the study's), filtered ``repetitions`` times as series 1, 5 and 6 in
    ``folder``; the floors of the last half of each run (JSON-safe dict, the format of
    :data:`~formtwin.tracker.intervals.CALIBRATION_PATH`)."""
    if seed == StudySettings().seed:
        raise ValueError(f"seed = {seed}: the study's own seed would calibrate on its data")
    signature = residual_signature(mm)
    if signature is None:
        raise ValueError(f"{mm_path}: the metamodel has no held-out residual statistics "
                         "(fit it with --cv-folds > 0)")
    settings = StudySettings(n_realisations=datasets, n_repetitions=repetitions,
                             n_products=products, window=products // 2, seed=seed,
                             series=(GATE_SERIES, *SERIES_OF.values()), paper_repetitions=0,
                             tracker=dataclasses.replace(TrackerConfig(), intervals="cloud_mu",
                                                         learn_residuals=learn_residuals))
    result = run_study(settings, folder, mm, mm_path, physics)
    d0, n_gate = gate_d0(result)
    return {"what": "floors (internal units; angles degrees) added in quadrature to the "
                    "cloud's std (plus the assumed mu's term where mu is assumed) by "
                    "TrackerConfig(intervals='calibrated'), learned on independent physics "
                    "pseudo-data (formtwin.study.calibrate)",
            "model_version": mm.model_version, "fit_id": mm.fit_id,
            "residuals": residual_rule(mm),
            "physics": physics.version,
            "k_res_diag": [float(v) for v in signature],
            "names": list(mm.spec.augmented.names) + list(mm.spec.output_names),
            "settings": {"seed": seed, "datasets": datasets, "repetitions": repetitions,
                         "products": settings.n_products, "window": settings.window,
                         "tracker": settings.tracker.to_dict()},
            "fit_gate": {"d0": d0, "ewma": FIT_EWMA, "series": GATE_SERIES, "runs": n_gate},
            **{key: floors_from_study(result, s, d0) for key, s in SERIES_OF.items()}}


def main(argv: list[str] | None = None) -> None:
    """Make the pseudo-data (physics runs: heavy), run series 1, 5 and 6, write the
    floors of the bundled metamodel (default: the package's calibration file)."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", default="benchmarks/.cache/calibration",
                        help="folder of the calibration's pseudo-data and filter runs")
    parser.add_argument("--model", default="benchmarks/.cache/study/model",
                        help="folder of the metamodel's fit where none is bundled")
    parser.add_argument("--datasets", type=int, default=8)
    parser.add_argument("--repetitions", type=int, default=2)
    parser.add_argument("--products", type=int, default=1000,
                        help="products per dataset (the last half are scored)")
    parser.add_argument("--seed", type=int, default=SEED)
    parser.add_argument("--write", help=f"the calibration file (default: the package's, "
                        f"{CALIBRATION_PATH.name} or, with --learn-residuals, "
                        f"{calibration_path(True).name})")
    parser.add_argument("--learn-residuals", action="store_true",
                        help="calibrate trackers with learn_residuals "
                        "(docs/notes/likelihood-learn-residuals.md)")
    args = parser.parse_args(argv)
    mm, mm_path = default_metamodel(Path(args.model), "bending")
    try:
        out = learn_calibration(mm, mm_path, physics_model("bending", mm.spec), Path(args.out),
                                args.datasets, args.repetitions, args.products, args.seed,
                                args.learn_residuals)
    except ValueError as exc:
        raise SystemExit(str(exc)) from None
    write = Path(args.write) if args.write else calibration_path(args.learn_residuals)
    write.write_text(json.dumps(out, indent=1) + "\n", encoding="utf-8")
    print(json.dumps({k: out[k] for k in ("fit_gate", *SERIES_OF)}, indent=1))


if __name__ == "__main__":
    main()
