"""``formtwin doe``: run a design of experiments, or import a user's FE results."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

import numpy as np

from formtwin.dataset import curve_columns, export_design, import_csv
from formtwin.spec import load_spec


def register(sub: Any) -> None:
    """Add the ``doe`` commands to the subparsers ``sub``."""
    p = sub.add_parser("doe", help="designs of experiments and DOE datasets")
    dsub = p.add_subparsers(dest="doe_command", required=True, metavar="ACTION")
    run = dsub.add_parser("run", help="run the paper's design (the 2^d corners of the d "
                          "inputs of the spec + a Latin hypercube) over a built-in process "
                          "model; resumes an interrupted run")
    run.add_argument("--out", required=True, help="dataset file (HDF5) to write or resume")
    run.add_argument("--physics", choices=("bending", "analytic", "calculix"),
                     default="bending", help="process model (default: %(default)s; "
                     "calculix needs ccx)")
    run.add_argument("--spec", help="process spec TOML (default: the demonstrator)")
    run.add_argument("--lhs", type=int, default=None, help="Latin-hypercube points "
                     "(default: 5000, formtwin.doe.LHS_POINTS)")
    run.add_argument("--no-corners", action="store_true", help="leave out the 2^d corners")
    run.add_argument("--seed", type=int, default=0, help="design seed (default: %(default)s)")
    run.add_argument("--workers", type=int, help="local worker processes (default: all cores; "
                     "1: in this process)")
    run.add_argument("--chunk", type=int, help="runs per task (default: automatic)")
    run.add_argument("--scheduler", help="Dask scheduler address tcp://HOST:PORT")
    run.set_defaults(run=_run)
    des = dsub.add_parser("design", help="write the paper's design as a CSV of inputs (the "
                          "spec file's units) for an external FE code; bring its results "
                          "back with `doe import`")
    des.add_argument("--spec", help="process spec TOML (default: the demonstrator)")
    des.add_argument("--out", required=True, help="design CSV to write")
    des.add_argument("--lhs", type=int, default=None, help="Latin-hypercube points "
                     "(default: 5000, formtwin.doe.LHS_POINTS)")
    des.add_argument("--no-corners", action="store_true", help="leave out the 2^d corners")
    des.add_argument("--seed", type=int, default=0, help="design seed (default: %(default)s)")
    des.set_defaults(run=_design)
    imp = dsub.add_parser("import", help="import FE results from CSV (one row per run)")
    imp.add_argument("csv", help="CSV: one column per input of the spec (its file's units), "
                     "one per output of the spec ([[output]] names), [status], and the curve "
                     "as F@<axis value> columns (the spec's [curve] unit); see "
                     "docs/reference/csv.md")
    imp.add_argument("--out", required=True, help="dataset file (HDF5) to write")
    imp.add_argument("--spec", help="process spec TOML (default: the demonstrator)")
    imp.add_argument("--model-version", default="imported", help="label of the FE model")
    imp.set_defaults(run=_import)


def _run(args: argparse.Namespace) -> int:
    from formtwin.defaults import physics_model
    from formtwin.doe import LHS_POINTS, latin_hypercube, paper_design, run_design

    spec = load_spec(args.spec)
    n_lhs = LHS_POINTS if args.lhs is None else args.lhs
    X = latin_hypercube(spec, n_lhs, args.seed) if args.no_corners else paper_design(
        spec, n_lhs, args.seed)
    executor = f"dask {args.scheduler}" if args.scheduler else "processes"
    data = run_design(physics_model(args.physics, spec), X, Path(args.out), executor=executor,
                      chunk_size=args.chunk, workers=args.workers, seed=args.seed,
                      progress=sys.stderr.isatty())
    print(f"{args.out}: {data.n} runs, {int(data.ok.sum())} ok, "
          f"{int((~data.ok).sum())} failed (model {data.model_version})")
    reasons, counts = np.unique(data.reason[~data.ok], return_counts=True)
    for r, c in zip(reasons, counts, strict=True):
        print(f"  {c:5d} x {r}")
    return 0


def _design(args: argparse.Namespace) -> int:
    from formtwin.doe import LHS_POINTS, latin_hypercube, paper_design

    spec = load_spec(args.spec)
    n_lhs = LHS_POINTS if args.lhs is None else args.lhs
    X = latin_hypercube(spec, n_lhs, args.seed) if args.no_corners else paper_design(
        spec, n_lhs, args.seed)
    export_design(spec, X, args.out)
    cols = curve_columns(spec)
    print(f"{args.out}: {len(X)} runs of {', '.join(spec.run_inputs.names)} "
          f"({spec.name}, the spec file's units)")
    print(f"results for `formtwin doe import`: these columns, then "
          f"{', '.join(spec.output_names)}, optional status, and the curve as "
          f"{cols[0]} .. {cols[-1]} ({len(cols)} columns, N; {spec.axis_label})")
    return 0


def _import(args: argparse.Namespace) -> int:
    data = import_csv(args.csv, load_spec(args.spec), args.model_version)
    data.save(args.out)
    print(f"{args.out}: {data.n} runs imported, {int(data.ok.sum())} ok")
    return 0
