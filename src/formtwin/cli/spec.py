"""``formtwin spec``: show and check process definitions."""

from __future__ import annotations

import argparse
from typing import Any

from formtwin.spec import format_table, load_spec


def register(sub: Any) -> None:
    p = sub.add_parser("spec", help="show or check a process definition (TOML)")
    ssub = p.add_subparsers(dest="spec_command", required=True, metavar="ACTION")
    show = ssub.add_parser("show", help="print a spec as a table (default: the demonstrator)")
    show.add_argument("path", nargs="?", help="spec file (default: bundled demonstrator)")
    show.set_defaults(run=_show)


def _show(args: argparse.Namespace) -> int:
    print(format_table(load_spec(args.path)))
    return 0
