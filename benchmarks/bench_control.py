"""Benchmark: the closed-loop control study of the final angle.

Run ``python benchmarks/bench_control.py`` (heavy: 3 physics
runs per product, 1000 products x 5 datasets and a tuning one, cached per physics model
version; ``--plant-only`` runs only the plants' physics into the cache, so that the
controllers' part, ~7 min, can run later; ``make control-study`` runs the same study through
the command line into the same folder, whose per-dataset results this script reuses).
Plant: the physics model (bending) under series-6 conditions; model: the metamodel of the
bundled physics DOE (what a fresh clone gets, fitted into the study folder). See
:mod:`formtwin.study.control` and ``docs/explanation/control.md``.

Figures (``benchmarks/results/bench_control.json``): per controller (fixed, ewma,
feedforward: the weight learned on the line, the service's default; feedforward_fixed: the
best fixed weight; feedforward_full, trim_only, feedforward_open, oracle) the mean error,
std, RMSE and share within +-0.5 deg of the final angle over the scored products;
``angle2_std_ratio_ff_vs_fixed`` (target <= 0.5), ``angle2_std_ratio_ff_vs_oracle``
(<= 1.5), ``angle2_std_ratio_ff_vs_ewma`` (<= 0.8) of the feedforward (``_fffixed_``: the
fixed weight's), pooled and within datasets (``within_dataset_std_ratio_*``); the weights
chosen (by the mean within-dataset ratio to fixed u, leave one dataset out); the
feedforward's interval coverage and prediction error; the plant interpolation's largest
error at the feedforward's own settings.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from formtwin._bench import CACHE, write_result
from formtwin.defaults import default_metamodel, physics_model
from formtwin.study.control import ControlStudySettings
from formtwin.study.control_run import build_plants, run_control_study


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--out", default=str(CACHE / "control"))
    p.add_argument("--products", type=int, default=1000)
    p.add_argument("--datasets", type=int, default=6,
                   help="datasets, each scored with the weights chosen on the others")
    p.add_argument("--workers", type=int, default=2,
                   help="physics worker processes, and datasets tracked at once")
    p.add_argument("--no-angle-filter", action="store_true",
                   help="skip the feedforward with the measured angles in the filter (one "
                   "tracker pass per dataset less)")
    p.add_argument("--plant-only", action="store_true",
                   help="only run (or complete) the plants' physics into the cache, no "
                   "controllers and no result (the long part: ~30 min)")
    args = p.parse_args()
    out = Path(args.out)
    metamodel, mm_path = default_metamodel(out / "model", "bending")
    physics = physics_model("bending", metamodel.spec)
    settings = ControlStudySettings(products=args.products, datasets=args.datasets,
                                    workers=args.workers,
                                    angle_in_filter=not args.no_angle_filter)
    t0 = time.perf_counter()
    if args.plant_only:
        n = build_plants(metamodel, physics, settings, out)
        print(f"plants of {n} datasets in {out} ({time.perf_counter() - t0:.0f} s)")
        return
    figures = run_control_study(metamodel, physics, settings, out)
    figures["wall_s"] = round(time.perf_counter() - t0, 1)
    model = {"name": "metamodel of the bundled physics DOE", "physics": "bending",
             "physics_version": metamodel.model_version, "metamodel_file": str(mm_path)}
    write_result("control", figures, model=model)


if __name__ == "__main__":
    main()
