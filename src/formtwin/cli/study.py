"""``formtwin study``: the paper's six simulation series and their report."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

import numpy as np

from formtwin.cli.options import add_tracker_options, tracker_config
from formtwin.study.run import StudySettings

QUICK = {"n_products": 120, "window": 60, "n_realisations": 2, "n_repetitions": 1}
#: the tracker settings of --quick
QUICK_TRACKER = {"n_particles": 200}
#: the sensor benchmark's results in a source checkout (``python benchmarks/bench_sensors.py``)
SENSOR_FIGURES = "benchmarks/results/bench_sensors.json"
#: TrackerConfig fields each series sets itself (no flags)
SERIES_FIELDS = ("estimate_deviation", "mu", "seed", "learn_mu", "mu_known")


def register(sub: Any) -> None:
    """Add the ``study`` command to the subparsers ``sub``."""
    p = sub.add_parser("study", help="run the paper's study (6 series) and write a report")
    p.add_argument("--out", default="out/study", help="study folder (default: %(default)s)")
    p.add_argument("--quick", action="store_true",
                   help="smoke test: " + ", ".join(f"{k}={v}" for k, v in QUICK.items()))
    p.add_argument("--physics", choices=("bending", "analytic"), default="bending",
                   help="process model behind the DOE and the FE data (default: %(default)s)")
    p.add_argument("--metamodel", help="metamodel file (default: fitted from the bundled DOE)")
    p.add_argument("--fe-data", metavar="DATASET.h5",
                   help="your own FE dataset (formtwin doe import) as the physics data of "
                   "the sources FE and gFE (series 5, 6): interpolated with a thin-plate RBF "
                   "independent of the metamodel (docs/howto/own-process.md); needed for "
                   "a spec the built-in --physics models do not know")
    p.add_argument("--products", type=int, help="products per realisation (paper: 1000)")
    p.add_argument("--realisations", type=int, help="dataset realisations (paper: 5)")
    p.add_argument("--repetitions", type=int, help="filter repetitions per dataset (paper: 5)")
    p.add_argument("--window", type=int, help="products at the end scored (paper: 500)")
    p.add_argument("--paper-repetitions", type=int,
                   help="repetitions per dataset with the paper's likelihood beside the "
                        "tracker's, on the same data (default 1; 0: none)")
    p.add_argument("--series", help="comma-separated series numbers (default: the paper's "
                   "1,2,3,4,5,6; 7, 8: series 4, 6 with learned mu)")
    p.add_argument("--seed", type=int, default=0, help="master seed (default: %(default)s)")
    p.add_argument("--sensor-figures", default=SENSOR_FIGURES, metavar="JSON",
                   help="the sensor benchmark's results, shown in the report's sensor section "
                   "(default: %(default)s, when present)")
    p.add_argument("--workers", type=int, help="worker processes (default: all cores; 1: in "
                   "this process)")
    p.add_argument("--scheduler", help="Dask scheduler address tcp://HOST:PORT")
    add_tracker_options(p, exclude=SERIES_FIELDS)
    p.set_defaults(run=run)


def build_namespace(**given: Any) -> argparse.Namespace:
    """The namespace ``formtwin study`` would parse, with defaults and ``given`` values."""
    sub = argparse.ArgumentParser().add_subparsers()
    register(sub)
    ns = sub.choices["study"].parse_args([])
    for key, value in given.items():
        setattr(ns, key, value)
    return ns


def settings_from_args(args: argparse.Namespace) -> StudySettings:
    """The :class:`StudySettings` of parsed ``formtwin study`` options (``--quick`` first, then
    the sizes given, then the tracker's flags)."""
    values: dict[str, Any] = dict(QUICK) if args.quick else {}
    for key, attr in (("n_products", "products"), ("n_realisations", "realisations"),
                      ("n_repetitions", "repetitions"), ("window", "window"),
                      ("paper_repetitions", "paper_repetitions")):
        if getattr(args, attr) is not None:
            values[key] = getattr(args, attr)
    if "n_products" in values and "window" not in values:
        values["window"] = min(500, values["n_products"] // 2)
    if args.series:
        values["series"] = tuple(int(s) for s in args.series.split(","))
    tracker = tracker_config(args, QUICK_TRACKER if args.quick else None)
    return StudySettings(seed=args.seed, workers=args.workers, scheduler=args.scheduler,
                         tracker=tracker, **values)


def physics_source(args: argparse.Namespace, spec: Any) -> tuple[Any, str]:
    """The study's physics data source and its label: the FE dataset of ``--fe-data``
    (checked against the metamodel's spec), else the ``--physics`` model, which must be
    able to run this spec (else ``ValueError`` naming what is missing)."""
    from formtwin.defaults import physics_model
    from formtwin.study.fe_data import DatasetSimulator, check_physics

    if args.fe_data:
        from formtwin.dataset import DoeDataset

        data = DoeDataset.load(args.fe_data)
        same = (data.spec.run_inputs.names == spec.run_inputs.names
                and data.spec.output_names == spec.output_names
                and data.spec.n_t == spec.n_t and np.allclose(data.spec.time, spec.time))
        if not same:
            raise ValueError(f"--fe-data {args.fe_data}: its spec {data.spec.name!r} has "
                             f"other inputs, outputs or curve grid than the metamodel's "
                             f"{spec.name!r}")
        return DatasetSimulator(data), f"FE dataset {args.fe_data} (thin-plate RBF)"
    try:
        physics = physics_model(args.physics, spec)
    except (KeyError, ValueError) as exc:
        raise ValueError(f"study: the {args.physics} model cannot run spec {spec.name!r} "
                         f"(missing {exc}); pass --fe-data with the spec's own FE dataset "
                         "(formtwin doe import)") from None
    check_physics(physics, spec, f"the {args.physics} model")
    return physics, args.physics


def run(args: argparse.Namespace) -> int:
    """Run ``formtwin study``: the metamodel, the study and its report; returns the exit code."""
    from formtwin.defaults import bundled_metamodel, default_metamodel
    from formtwin.study.report import write_report
    from formtwin.study.run import run_study
    from formtwin.study.sensor_report import load_sensor_figures
    from formtwin.tracker.intervals import find_calibration

    settings = settings_from_args(args)
    out = Path(args.out)
    metamodel, mm_path = default_metamodel(out / "model", args.physics, args.metamodel)
    physics, label = physics_source(args, metamodel.spec)
    runs = label if args.fe_data else f"{label} model"
    print(f"study into {out}: {settings.n_realisations} datasets x {settings.n_products} "
          f"products ({runs} runs, cached), then {settings.n_filter_runs} "
          f"filter runs with N = {settings.tracker.n_particles} (progress bars on a "
          "terminal; -v logs the steps)",
          flush=True)
    result = run_study(settings, out, metamodel, mm_path, physics,
                       progress=sys.stderr.isatty())
    calibrated = settings.tracker.intervals in ("calibrated", "calibrated_fit")
    calibration = find_calibration(metamodel).describe() if calibrated else ""
    if calibration.startswith("uncalibrated"):
        print(f"WARNING: {calibration}; the report's intervals are the particle cloud's")
    # the bundled file by its name in the package: a report names no path of this machine
    shown = f"formtwin/data/{mm_path.name} (bundled)" \
        if mm_path == bundled_metamodel(args.physics) else str(mm_path)
    report = write_report(result, metamodel.spec, out, sources={
        "metamodel": f"{shown} (fit {metamodel.fit_id or 'without id'})",
        "physics model": f"{label} ({physics.version})"}, calibration=calibration,
        sensors=load_sensor_figures(args.sensor_figures), sensor_source=args.sensor_figures)
    print(f"study done in {result.timings['total_s']:.0f} s; report: {report}")
    print(f"markdown: {out / 'report.md'}; numbers: {out / 'nrmse.csv'}")
    return 0
