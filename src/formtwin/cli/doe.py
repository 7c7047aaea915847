"""``formtwin doe``: run a design of experiments, or import a user's FE results."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

import numpy as np

from formtwin.dataset import import_csv
from formtwin.spec import load_spec


def register(sub: Any) -> None:
    """Add the ``doe`` commands to the subparsers ``sub``."""
    p = sub.add_parser("doe", help="designs of experiments and DOE datasets")
    dsub = p.add_subparsers(dest="doe_command", required=True, metavar="ACTION")
    run = dsub.add_parser("run", help="run the paper's design (2^10 corners + Latin "
                          "hypercube) over a process model; resumes an interrupted run")
    run.add_argument("--out", required=True, help="dataset file (HDF5) to write or resume")
    run.add_argument("--physics", choices=("bending", "analytic", "calculix"),
                     default="bending", help="process model (default: %(default)s; "
                     "calculix needs ccx)")
    run.add_argument("--spec", help="process spec TOML (default: the demonstrator)")
    run.add_argument("--lhs", type=int, default=None, help="Latin-hypercube points "
                     "(default: 5000, formtwin.doe.LHS_POINTS)")
    run.add_argument("--no-corners", action="store_true", help="leave out the 2^d corners")
    run.add_argument("--seed", type=int, default=0, help="design seed (default: %(default)s)")
    run.add_argument("--workers", type=int, help="local worker processes (default: all cores)")
    run.add_argument("--chunk", type=int, help="runs per task (default: automatic)")
    run.add_argument("--scheduler", help="Dask scheduler address tcp://HOST:PORT")
    run.set_defaults(run=_run)
    imp = dsub.add_parser("import", help="import FE results from CSV (one row per run)")
    imp.add_argument("csv", help="CSV: input columns, angle_stage1, angle_stage2, [status], "
                     "F@<ms> curve columns")
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


def _import(args: argparse.Namespace) -> int:
    data = import_csv(args.csv, load_spec(args.spec), args.model_version)
    data.save(args.out)
    print(f"{args.out}: {data.n} runs imported, {int(data.ok.sum())} ok")
    return 0
