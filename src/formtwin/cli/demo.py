"""``formtwin demo``: the main job of ``make demo`` — the paper's study on the embedded default."""

from __future__ import annotations

import argparse
from typing import Any

from formtwin.cli import study
from formtwin.cli.spec import format_table
from formtwin.spec import load_spec


def register(sub: Any) -> None:
    """Add the ``demo`` command to the subparsers ``sub``."""
    p = sub.add_parser("demo", help="run the paper's study on the embedded default model "
                       "and write its report (the main job)")
    p.add_argument("--out", default="out/demo", help="output folder (default: %(default)s)")
    p.add_argument("--quick", action="store_true", help="the smoke-test size of the study")
    p.set_defaults(run=_demo)


def _demo(args: argparse.Namespace) -> int:
    from formtwin.defaults import bundled_doe

    print(format_table(load_spec()), end="\n\n")
    physics = "bending" if bundled_doe("bending").exists() else "analytic"
    if physics == "analytic":
        print("No DOE of the bending model is bundled: the study runs on the analytic "
              "stand-in (formtwin.physics.analytic), not on the physics model.")
    ns = study.build_namespace(out=args.out, quick=args.quick, physics=physics)
    return study.run(ns)
