"""``formtwin metamodel fit|validate|calibrate``: fit the POD + RBF metamodel to a DOE
dataset, report its k-fold error with plots, or learn its interval calibration on physics
runs and store it in the metamodel's file (the tracker then uses it)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any


def register(subparsers: Any) -> None:
    """Add the ``metamodel`` commands to the subparsers ``sub``."""
    p = subparsers.add_parser("metamodel", help="fit, validate or calibrate the POD + RBF "
                              "metamodel",
                              description=__doc__)
    sub = p.add_subparsers(dest="action", required=True, metavar="ACTION")
    fit = sub.add_parser("fit", help="fit a metamodel to a DOE dataset and save it")
    fit.add_argument("dataset", help="DOE dataset file (formtwin doe run / import)")
    fit.add_argument("--out", required=True, help="metamodel file to write (.npz)")
    fit.add_argument("--cv-folds", type=int, default=5,
                     help="folds of the cross-validation whose held-out residuals are stored "
                          "with the metamodel for the calibrated likelihood (0: none; "
                          "default: %(default)s)")
    _model_options(fit)
    fit.set_defaults(run=_fit)
    val = sub.add_parser("validate", help="k-fold error of the metamodel on a DOE dataset")
    val.add_argument("dataset", help="DOE dataset file")
    val.add_argument("--k", type=int, default=5, help="number of folds (default: %(default)s)")
    val.add_argument("--seed", type=int, default=0, help="seed of the folds")
    val.add_argument("--plots", help="folder for angles.png and worst_curves.png")
    val.add_argument("--json", help="also write the figures to this JSON file")
    _model_options(val)
    val.set_defaults(run=_validate)
    cal = sub.add_parser(
        "calibrate", help="learn the metamodel's interval calibration on physics runs and "
        "store it in its file", description="Learn the floors that make the tracker's 90 % "
        "intervals hold 90 % on physics pseudo-data of the metamodel's own process "
        "(series 1, 5, 6 of the study with a seed of their own; heavy: datasets x products "
        "physics runs) and store them in the metamodel file: trackers on it then report "
        "intervals='calibrated_fit' instead of 'uncalibrated'.")
    cal.add_argument("metamodel", help="metamodel file (.npz, with held-out residuals)")
    cal.add_argument("--physics", default="bending",
                     help="process model that makes the physics pseudo-data: bending, "
                          "analytic or calculix (default: %(default)s)")
    cal.add_argument("--fe-data", metavar="DATASET.h5",
                     help="make the physics pseudo-data from this FE dataset of the "
                          "metamodel's process (thin-plate RBF of its runs, as `formtwin study "
                          "--fe-data`) instead of a --physics model")
    cal.add_argument("--out", help="metamodel file to write (default: the input, in place)")
    cal.add_argument("--work", help="folder of the pseudo-data and filter runs (default: "
                                    "<metamodel>.calibration beside the file)")
    cal.add_argument("--datasets", type=int, default=8, help="default: %(default)s")
    cal.add_argument("--repetitions", type=int, default=2, help="default: %(default)s")
    cal.add_argument("--products", type=int, default=1000,
                     help="products per dataset, the last half scored (default: %(default)s)")
    cal.add_argument("--seed", type=int, default=8101,
                     help="study seed of the calibration's own data (default: %(default)s)")
    cal.set_defaults(run=_calibrate)


def _model_options(p: argparse.ArgumentParser) -> None:
    modes = p.add_mutually_exclusive_group()
    modes.add_argument("--modes", type=int, help="number of POD modes (default: 40)")
    modes.add_argument("--energy", type=float,
                       help="keep the fewest POD modes capturing this share of the variance")
    p.add_argument("--kernel", default=None,
                   help="RBF kernel, or several separated by commas to choose by "
                        "leave-one-out (default: the library default, cubic)")
    p.add_argument("--centres", type=int, default=None,
                   help="RBF centres of the curve model (default: the library default; "
                        "0: interpolate every run)")
    p.add_argument("--angle-centres", type=int, default=None,
                   help="RBF centres of each angle model (default: the library default)")
    p.add_argument("--scales", choices=("loo", "box"), default="loo",
                   help="per-dimension length scales by leave-one-out, or the unit box")


def _metamodel(args: argparse.Namespace) -> Any:
    from formtwin.metamodel import POD, RBF, Metamodel

    pod = POD(energy=args.energy) if args.energy is not None else \
        POD(n_modes=args.modes if args.modes is not None else 40)
    def rbf(centres: int | None, default: RBF) -> RBF:
        m = default.n_centres if centres is None else (centres or None)
        kernels = default.kernels if args.kernel is None else \
            [k.strip() for k in args.kernel.split(",") if k.strip()]
        return RBF(kernels, length_scales=args.scales, n_centres=m)

    defaults = Metamodel()
    assert isinstance(defaults.approximation, RBF)
    assert isinstance(defaults.angle_approximation, RBF)
    return Metamodel(pod, rbf(args.centres, defaults.approximation),
                     rbf(args.angle_centres, defaults.angle_approximation))


def _load(path: str) -> Any:
    from formtwin.dataset import DoeDataset

    return DoeDataset.load(path)


def _fit(args: argparse.Namespace) -> int:
    from formtwin.metamodel import calibrate

    data = _load(args.dataset)
    mm = _metamodel(args).fit(data)
    print(f"fitted {mm.n_modes} POD modes + RBF to {mm.n_train} of {len(data.ok)} runs "
          f"in {mm.fit_seconds:.1f} s")
    if args.cv_folds:
        calibrate(mm, data, k=args.cv_folds)
        print(f"stored the statistics of {args.cv_folds}-fold held-out residuals")
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    print(f"-> {mm.save(args.out)}")
    return 0


def _validate(args: argparse.Namespace) -> int:
    from formtwin.metamodel.validate import cross_validate, figures, plot_validation

    data = _load(args.dataset)
    cv = cross_validate(_metamodel(args), data, k=args.k, seed=args.seed)
    figs = figures(cv)
    width = max(len(k) for k in figs)
    print(f"{args.k}-fold validation on {figs['n_runs']} successful runs of {args.dataset}")
    for key, value in figs.items():
        print(f"  {key:<{width}}  {_fmt(value)}")
    if args.json:
        with open(args.json, "w", encoding="utf-8") as fh:
            json.dump(figs, fh, indent=2)
        print(f"wrote {args.json}")
    if args.plots:
        for path in plot_validation(cv, args.plots):
            print(f"wrote {path}")
    return 0


def _calibrate(args: argparse.Namespace) -> int:
    from formtwin.cli.study import physics_source
    from formtwin.metamodel import Metamodel
    from formtwin.study.calibrate import SERIES_OF, learn_calibration

    path = Path(args.metamodel)
    mm = Metamodel.load(path)
    work = Path(args.work) if args.work else path.with_suffix(".calibration")
    try:
        physics, _ = physics_source(args, mm.spec)
        cal = learn_calibration(mm, path, physics, work, args.datasets, args.repetitions,
                                args.products, args.seed)
    except (ValueError, KeyError) as exc:
        print(f"formtwin metamodel calibrate: {path}: {exc}")
        return 2
    mm.calibration = cal
    out = mm.save(args.out or path)
    n, n_out = mm.spec.n_inputs, mm.spec.n_outputs  # theta_d is not estimated in series 5
    for key, series in SERIES_OF.items():
        e = cal[key]
        kind = "fit" if "fit_floors" in e else ""  # else: constant floors, no fit gate
        fit, cloud = (e[k][:n] + e[k][-n_out:] for k in (
            f"coverage_calibrated{'_' + kind if kind else ''}_in_sample", "coverage_cloud"))
        print(f"{key} (series {series}, {e['runs']} runs): the 90 % intervals of x, theta "
              f"and the outputs hold {min(fit):.3f}-{max(fit):.3f} in sample (the cloud's std "
              f"{min(cloud):.3f}-{max(cloud):.3f})"
              + ("" if kind else f"; constant floors: {e['fit_gate_unusable']}"))
    print(f"interval calibration of fit {mm.fit_id} -> {out}")
    return 0


def _fmt(value: Any) -> str:
    if isinstance(value, float):
        return f"{value:.4g}"
    if isinstance(value, list) and value and isinstance(value[0], float):
        return "[" + ", ".join(f"{v:.4g}" for v in value) + "]"
    return str(value)
