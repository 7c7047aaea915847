"""``formtwin plot``: figures of the process pieces."""

from __future__ import annotations

import argparse
from typing import Any

import numpy as np

from formtwin.figures import plot_deviation
from formtwin.spec import load_spec


def register(sub: Any) -> None:
    """Add the ``plot`` commands to the subparsers ``sub``."""
    p = sub.add_parser("plot", help="draw figures of the model pieces")
    psub = p.add_subparsers(dest="plot_command", required=True, metavar="FIGURE")
    dev = psub.add_parser("deviation", help="effect of each deviation knot (paper Fig. 1)")
    dev.add_argument("--metamodel", help="metamodel file whose centre curve is shown "
                     "(default: the analytic stand-in at the centre of the box)")
    dev.add_argument("--out", default="deviation.png", help="output image (default: %(default)s)")
    dev.set_defaults(run=_deviation)
    for name, help_ in (("bending", "tools and deformed flap of the bending model (centre)"),
                        ("sensitivity", "bending model: each Table-1 input from min to max")):
        fig = psub.add_parser(name, help=help_)
        fig.add_argument("--out", default=f"{name}.png", help="output image (default: %(default)s)")
        fig.set_defaults(run=_physics_figure)


def _deviation(args: argparse.Namespace) -> int:
    if args.metamodel:
        from formtwin.metamodel import Metamodel

        mm = Metamodel.load(args.metamodel)
        spec = mm.spec
        curve = mm.predict_curves(0.5 * (spec.inputs.lo + spec.inputs.hi)[None, :])[0]
    else:
        from formtwin.physics.analytic import AnalyticBending

        spec = load_spec()
        centre = np.r_[spec.state.mu_mid, 0.5 * (spec.params.lo + spec.params.hi)]
        curve = AnalyticBending(spec).run(centre).curve
    print(f"wrote {plot_deviation(spec, curve, args.out)}")
    return 0


def _physics_figure(args: argparse.Namespace) -> int:
    from formtwin.physics.bending import BendingModel
    from formtwin.physics.plots import plot_bending, plot_sensitivity

    model = BendingModel()
    if args.plot_command == "bending":
        path = plot_bending(model, model.centre(), args.out)
    else:
        path = plot_sensitivity(model, args.out)
    print(f"wrote {path}")
    return 0
