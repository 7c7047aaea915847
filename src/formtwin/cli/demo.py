"""``formtwin demo``: the main job of ``make demo``."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from formtwin.cli.plot import _deviation
from formtwin.spec import format_table, load_spec


def register(sub: Any) -> None:
    p = sub.add_parser("demo", help="run the main job (what exists so far) into a folder")
    p.add_argument("--out", default="out/demo", help="output folder (default: %(default)s)")
    p.set_defaults(run=_demo)


def _demo(args: argparse.Namespace) -> int:
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    print(format_table(load_spec()))
    _deviation(argparse.Namespace(metamodel=None, out=out / "deviation.png"))
    print("The paper's study (six simulation series) is not built yet; this demo shows the "
          "process spec and the deviation model only.")
    return 0
