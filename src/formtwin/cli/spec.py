"""``formtwin spec``: show and check process definitions."""

from __future__ import annotations

import argparse
import math
from typing import Any

from formtwin.spec import ProcessSpec, load_spec


def register(sub: Any) -> None:
    """Add the ``spec`` commands to the subparsers ``sub``."""
    p = sub.add_parser("spec", help="show or check a process definition (TOML)")
    ssub = p.add_subparsers(dest="spec_command", required=True, metavar="ACTION")
    show = ssub.add_parser("show", help="print a spec as a table (default: the demonstrator)")
    show.add_argument("path", nargs="?", help="spec file (default: bundled demonstrator)")
    show.set_defaults(run=_show)


def _show(args: argparse.Namespace) -> int:
    print(format_table(load_spec(args.path)))
    return 0


def format_table(spec: ProcessSpec) -> str:
    """Table 1 of a spec, in the spec file's units, as fixed-width text."""
    head = f"{'group':<10}{'name':<22}{'unit':<12}{'min':>9}{'max':>9}" \
           f"{'mu_min':>9}{'mu_max':>9}{'sigma':>8}{'rho':>6}"
    lines = [f"{spec.name}: {spec.description}", head, "-" * len(head)]

    def cell(value: float, scale: float, width: int) -> str:
        return f"{'':>{width}}" if math.isnan(value) else f"{value / scale:>{width}.4g}"

    for group, vars_ in (("x", spec.state), ("theta", spec.params),
                         ("theta_d", spec.deviation.group)):
        for v in vars_:
            lines.append(f"{group:<10}{v.name:<22}{v.unit:<12}"
                         f"{cell(v.lo, v.scale, 9)}{cell(v.hi, v.scale, 9)}"
                         f"{cell(v.mu_min, v.scale, 9)}{cell(v.mu_max, v.scale, 9)}"
                         f"{cell(v.sigma, v.scale, 8)}{cell(v.rho, 1.0, 6)}")
    notes = [f"note ({v.name}): {v.note}" for v in spec.augmented if v.note]
    for v in spec.controls:
        lines.append(f"{'u':<10}{v.name:<22}{v.unit:<12}{cell(v.lo, v.scale, 9)}"
                     f"{cell(v.hi, v.scale, 9)}   nominal {v.nominal / v.scale:g}")
    for o in spec.outputs:
        lines.append(f"{'output':<10}{o.name:<22}{o.unit:<12}  {o.label}"
                     + ("" if o.uses_controls or not len(spec.controls) else
                        " (before the controls act)"))
    t, sc, unit = spec.time, spec.axis_scale, spec.axis_unit
    dev = spec.deviation
    knots = (f"deviation {', '.join(dev.kinds)} at knots "
             f"{', '.join(f'{k / sc:.4g}' for k in dev.knots)} {unit}" if dev.kinds
             else "no deviation model (g = identity)")
    noise = (f"sensor noise sd {spec.noise_sd:g} N" if spec.noise_sd > 0 else
             "sensor noise sd not given ([curve] noise_sd; the tracker then assumes 0 N)")
    lines += ["", f"force curve over {spec.axis}: {t.size} samples on [{t[0] / sc:g}, "
              f"{t[-1] / sc:g}] {unit}; {noise}", knots] + notes
    return "\n".join(lines)
