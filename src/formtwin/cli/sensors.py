"""``formtwin sensors``: which sensor pays, by the linear-Gaussian bound of each sensor set
(:mod:`formtwin.study.sensor_bound`)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np

ASSUMPTIONS = ("linear-Gaussian bound: curve and angles linearised about each line's mu "
               "and theta (central differences of half a sigma, nominal setting), the "
               "paper's likelihood covariance K_MC/4, theta and mu known, the metamodel "
               "exact (series 1); a tracker can only be worse")


def register(sub: Any) -> None:
    """Add ``sensors`` to the subparsers ``sub``."""
    p = sub.add_parser("sensors", help="which sensor pays: the linear-Gaussian bound of "
                       "the final angle's and each state's error per sensor set")
    p.add_argument("--out", default="out/sensors",
                   help="folder of the table (sensors.json) and the metamodel cache "
                   "(default: %(default)s)")
    p.add_argument("--metamodel", help="metamodel file (default: fit or reuse the "
                   "embedded default in OUT/model)")
    p.add_argument("--realisations", type=int, default=5,
                   help="lines (mu, theta drawn as the study draws them) (default: 5)")
    p.add_argument("--seed", type=int, default=0, help="the study's seed (default: 0)")
    p.add_argument("--noise-factors", default="0.25,0.5,1,2",
                   help="each sensor's noise times these (default: %(default)s)")
    p.add_argument("--n-mc", type=int, default=10_000,
                   help="Monte-Carlo curves of K_MC (default: %(default)s)")
    p.set_defaults(run=run)


def candidate_sets(sensors: list[Any], factors: list[float]
                   ) -> dict[str, tuple[list[Any], dict[str, float]]]:
    """Sensor sets by name: the curve alone, each sensor at each noise factor, all at
    their spec noise: ``name -> (sensors, noise by name)``."""
    out: dict[str, tuple[list[Any], dict[str, float]]] = {"curve": ([], {})}
    for s in sensors:
        for f in factors:
            sd = s.noise * f / (1e-3 if s.unit == "um" else 1.0)
            out[f"{s.name}_{sd:g}{s.unit}"] = ([s], {s.name: s.noise * f})
    if len(sensors) > 1:
        out["all"] = (list(sensors), {})
    return out


def run(args: argparse.Namespace) -> int:
    """Compute and print the table; write ``OUT/sensors.json``."""
    from formtwin.defaults import default_metamodel
    from formtwin.production import draw_production_run
    from formtwin.spec.sensors import line_sensors
    from formtwin.study.sensor_bound import linearise, sensor_rows, set_bound

    out = Path(args.out)
    model, _ = default_metamodel(out / "model", "bending", args.metamodel)
    spec = model.spec
    factors = [float(v) for v in args.noise_factors.split(",")]
    sets = candidate_sets(list(line_sensors(spec)), factors)
    final: dict[str, list[float]] = {n: [] for n in sets}
    states: dict[str, list[list[float]]] = {n: [] for n in sets}
    for k in range(args.realisations):
        run_ = draw_production_run(spec, 1, np.random.default_rng(
            np.random.SeedSequence([args.seed, k])))
        lin = linearise(model, run_.mu, run_.theta, args.seed, args.n_mc)
        for name, (chosen, noise) in sets.items():
            b = set_bound(lin, sensor_rows(lin, chosen, spec.state.names, noise))
            final[name].append(b.final)
            states[name].append(b.states.tolist())
    names, output = spec.state.names, spec.output_names[-1]  # the last: the final output
    head = f"{'sensor set':<22}{output[:12]:>12}  " + "".join(f"{n[:10]:>11}" for n in names)
    print(f"bound over {args.realisations} lines (seed {args.seed}): posterior std over "
          f"the in-run std ({output}) and over sigma (states)")
    print(head)
    print("-" * len(head))
    table = {}
    for name in sets:
        st = np.mean(states[name], axis=0)
        table[name] = {"final": float(np.mean(final[name])), "final_per_line": final[name],
                       "states": dict(zip(names, st.tolist(), strict=True))}
        print(f"{name:<22}{np.mean(final[name]):>12.3f}  " + "".join(f"{v:>11.3f}" for v in st))
    print(f"assumptions: {ASSUMPTIONS}")
    out.mkdir(parents=True, exist_ok=True)
    (out / "sensors.json").write_text(json.dumps(
        {"bound": table, "output": output, "assumptions": ASSUMPTIONS, "seed": args.seed,
         "realisations": args.realisations}, indent=2) + "\n", encoding="utf-8")
    print(f"-> {out / 'sensors.json'}")
    return 0
