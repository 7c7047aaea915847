"""The tables of the physics notes (docs/notes/physics-*.md): sensitivity, mesh convergence
and smoothness in ``u``.

One core, the default :class:`~formtwin.physics.bending.BendingModel`:

* ``sensitivity``: every run input at its minimum and maximum, the others at the centre of
  Table 1 (``BendingModel.centre``): peak and mean force, angle after stage 1 and final
  angle at both ends;
* ``convergence``: peak force, force at t = -30 ms, both angles and CPU seconds per run at
  the centre for several element and layer counts and contact points per element;
* ``smoothness``: the final angle over the actuator's range of ``u`` (41 settings):
  its std about a cubic in ``u`` (``u_scatter_deg``: what no smooth model can follow) and the
  smallest and largest gain ``d angle / d u`` between neighbouring settings.

Run: ``python benchmarks/bench_physics_tables.py [--only sensitivity|convergence|smoothness]``;
prints the Markdown rows and writes ``benchmarks/results/bench_physics_tables.json``.
"""

from __future__ import annotations

import argparse
import time
from typing import Any

import numpy as np

from formtwin._bench import write_result
from formtwin.physics.bending import VERSION, BendingModel

MESHES = ((16, 15, None), (24, 15, None), (32, 15, None), (48, 15, None), (64, 15, None),
          (32, 31, None), (32, 15, 1), (32, 15, 2), (64, 15, 1), (64, 15, 2))


def sensitivity() -> list[dict[str, Any]]:
    """One-at-a-time extremes of every run input."""
    m = BendingModel()
    box, c = m.spec.run_inputs, m.centre()
    rows = []
    for name in box.names:
        runs = []
        for v in (box[name].lo, box[name].hi):
            x = c.copy()
            x[box.index[name]] = v
            runs.append(m.run(x))
        lo, hi = runs
        rows.append({"input": name, "peak_n": [lo.curve.max(), hi.curve.max()],
                     "mean_n": [lo.curve.mean(), hi.curve.mean()],
                     "angle1_deg": [lo.angles[0], hi.angles[0]],
                     "angle2_deg": [lo.angles[1], hi.angles[1]]})
        print(f"| {name} | peak {lo.curve.max():.0f} -> {hi.curve.max():.0f} N, mean "
              f"{100 * (hi.curve.mean() / lo.curve.mean() - 1):+.0f} % | {lo.angles[0]:.2f} -> "
              f"{hi.angles[0]:.2f} | {lo.angles[1]:.2f} -> {hi.angles[1]:.2f} |", flush=True)
    return rows


def convergence() -> list[dict[str, Any]]:
    """Centre run for each mesh of :data:`MESHES` ``(elements, layers, contact points per
    element or None for the default)``."""
    rows = []
    for n_el, n_lay, n_cp in MESHES:
        kw = {} if n_cp is None else {"contact_points": n_cp}
        m = BendingModel(n_elements=n_el, n_layers=n_lay, **kw)
        x = m.centre()
        m.run(x)  # compile / load the cache
        tic = time.process_time()
        r = m.run(x)
        cpu = time.process_time() - tic
        k = int(np.argmin(np.abs(np.asarray(m.spec.time) + 0.03)))
        cp = m.disc.contact_points
        rows.append({"elements": n_el, "layers": n_lay, "contact_points": cp,
                     "peak_n": r.curve.max(), "force_m30ms_n": r.curve[k],
                     "angle1_deg": r.angles[0], "angle2_deg": r.angles[1], "cpu_s": cpu})
        print(f"| {n_el} | {n_lay} | {cp} | {r.curve.max():.1f} | {r.curve[k]:.2f} | "
              f"{r.angles[0]:.3f} | {r.angles[1]:.3f} | {cpu:.2f} |", flush=True)
    return rows


def smoothness() -> dict[str, Any]:
    """The final angle over ``u`` at the centre: scatter about a cubic, gain range."""
    m = BendingModel()
    j = m.spec.run_inputs.index["stage2_depth"]
    lo, hi = m.spec.run_inputs["stage2_depth"].lo, m.spec.run_inputs["stage2_depth"].hi
    us = np.linspace(lo, hi, 41)
    a = []
    for u in us:
        x = m.centre()
        x[j] = u
        a.append(m.run(x).angles[1])
    angle = np.array(a)
    gain = np.diff(angle) / np.diff(us)
    out = {"u_scatter_deg": float(np.std(angle - np.polyval(np.polyfit(us, angle, 3), us))),
           "gain_min_deg_per_mm": float(gain.min()), "gain_max_deg_per_mm": float(gain.max()),
           "angle2_range_deg": [float(angle[0]), float(angle[-1])]}
    print(out, flush=True)
    return out


def main() -> None:
    """Run the selected tables and save them."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--only", choices=("sensitivity", "convergence", "smoothness"))
    args = ap.parse_args()
    figures: dict[str, Any] = {"physics_version": VERSION}
    for name, fn in (("sensitivity", sensitivity), ("convergence", convergence),
                     ("smoothness", smoothness)):
        if args.only in (None, name):
            figures[name] = fn()
    write_result("physics_tables", figures)


if __name__ == "__main__":
    main()
