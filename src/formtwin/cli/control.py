"""``formtwin control-study``: the final angle in closed loop (no control, run-to-run EWMA,
feedforward from the estimates: open, with feedback, with the angles in the filter; oracle)
with the physics model as the plant."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from formtwin.cli.options import add_tracker_options, tracker_config

#: TrackerConfig fields the study sets itself (series 6: deviation estimated, mu mid-range)
FIXED = ("estimate_deviation", "mu", "learn_mu", "seed", "mu_known")


def register(sub: Any) -> None:
    """Add the ``control-study`` command to the subparsers ``sub``."""
    p = sub.add_parser("control-study", help="closed-loop study of the final angle: fixed u, "
                       "run-to-run EWMA, feedforward, oracle (physics model as the plant)")
    p.add_argument("--out", default="out/control", help="folder (default: %(default)s)")
    p.add_argument("--metamodel", help="metamodel file (default: fitted from the bundled DOE)")
    p.add_argument("--products", type=int, default=1000, help="products per dataset")
    p.add_argument("--datasets", type=int, default=6, help="datasets, each scored with the "
                   "controllers' weights chosen on the others (default: %(default)s)")
    p.add_argument("--burn-in", type=int, default=100, help="first products not scored")
    p.add_argument("--target", type=float, help="final angle wanted, deg (default: the "
                   "metamodel's at the mid-range state and nominal setting)")
    p.add_argument("--max-step", type=float, default=0.25,
                   help="largest change of u per product, share of its range")
    p.add_argument("--delay", type=int, default=1,
                   help="products between a product and the use of its measured angle by "
                   "the run-to-run controller (default: %(default)s)")
    p.add_argument("--trim-lam", type=float, help="EWMA weight of the feedforward's trim "
                   "(default: tuned)")
    p.add_argument("--ff-weight", type=float, help="share of the posterior's "
                   "product-to-product change the fixed-weight feedforward trusts, 0-1 "
                   "(default: tuned; the feedforward learns its share on the line)")
    p.add_argument("--ff-rho", type=float, help="persistence of the last product's deviation "
                   "in the feedforward's trim, 0-1 (default: tuned)")
    p.add_argument("--no-angle-filter", action="store_true",
                   help="skip the feedforward with the measured angles in the filter")
    p.add_argument("--angle-sd", type=float, help="sd of the measured angle's likelihood, "
                   "deg (default: the metamodel's held-out error of the final angle)")
    p.add_argument("--seed", type=int, default=0, help="master seed")
    p.add_argument("--sensor-study", action="store_true",
                   help="the study with the line's real sensors instead: the EWMA and the "
                   "trim read the camera's angle with noise (--camera-noise), the feedforward "
                   "chooses on the curve's and on the curve-and-gauge posterior, its "
                   "prediction corrected by the camera's values "
                   "(sensors_study.json in --out)")
    p.add_argument("--camera-noise", default="0,0.1,0.2",
                   help="camera noise sds with --sensor-study, deg, comma-separated "
                   "(default: %(default)s)")
    p.add_argument("--workers", type=int, help="physics worker processes (1: in this process)")
    add_tracker_options(p, exclude=FIXED)
    p.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    """Run the study and print its summary; returns the exit code."""
    from dataclasses import replace

    from formtwin.defaults import default_metamodel, physics_model
    from formtwin.study.control import ControlStudySettings
    from formtwin.study.control_run import run_control_study

    out = Path(args.out)
    metamodel, _ = default_metamodel(out / "model", "bending", args.metamodel)
    physics = physics_model("bending", metamodel.spec)
    tracker = replace(tracker_config(args), estimate_deviation=True, mu=None, learn_mu=False)
    settings = ControlStudySettings(
        products=args.products, datasets=args.datasets, burn_in=args.burn_in,
        tracker=tracker, target=args.target, max_step=args.max_step, r2r_delay=args.delay,
        trim_lam=args.trim_lam, ff_weight=args.ff_weight, ff_rho=args.ff_rho,
        angle_in_filter=not args.no_angle_filter,
        angle_sd=args.angle_sd, seed=args.seed, workers=args.workers)
    print(f"control study into {out}: {settings.datasets} datasets x {settings.products} "
          f"products, N = {tracker.n_particles}", flush=True)
    if args.sensor_study:
        return _run_sensors(args, metamodel, physics, settings, out)
    s = run_control_study(metamodel, physics, settings, out)
    for c in ("fixed", "ewma", "feedforward", "feedforward_fixed", "feedforward_full",
              "feedforward_open", "trim_only", "feedforward_angle", "oracle"):
        if c not in s:
            continue
        v = s[c]
        print(f"  {c:16s} mean error {v['mean_error_deg']:+.3f} deg, std {v['std_deg']:.3f} "
              f"deg, within +-0.5 deg {v['within_band_share']:.1%}")
    print(f"  std ratio feedforward / fixed {s['angle2_std_ratio_ff_vs_fixed']}, "
          f"/ EWMA {s['angle2_std_ratio_ff_vs_ewma']}, / oracle "
          f"{s['angle2_std_ratio_ff_vs_oracle']} (weight learned on the line, trim weight "
          f"{s['ff_lam']}, rho {s['ff_rho']}); within datasets (median) "
          f"{s['within_dataset_std_ratio_ff_vs_fixed']['median']}, "
          f"{s['within_dataset_std_ratio_ff_vs_ewma']['median']}, "
          f"{s['within_dataset_std_ratio_ff_vs_oracle']['median']}")
    print(f"  what the estimates know of the final angle: correlation with the plant's "
          f"{s['estimate_level_corr']} (levels), {s['estimate_change_corr']} (changes)")
    print(f"  -> {out / 'control_study.json'}, {out / 'control_study.png'}")
    return 0


def _run_sensors(args: argparse.Namespace, metamodel: Any, physics: Any, settings: Any,
                 out: Path) -> int:
    """``--sensor-study``: the closed-loop study with the camera's noise and the gauge."""
    import json

    from formtwin.study.control_sensors import SensorControlSettings, run_sensor_control

    try:
        noises = tuple(float(v) for v in str(args.camera_noise).split(","))
    except ValueError:
        print(f"error: --camera-noise {args.camera_noise!r}: expected numbers, e.g. 0,0.1,0.2")
        return 2
    s = run_sensor_control(metamodel, physics, SensorControlSettings(
        base=settings, camera_noises=noises), out)
    for name in ("curve", "gauge"):
        for sd in noises:
            v = s[name][f"{sd:g}"]
            print(f"  {name:5s} camera {sd:g} deg: feedforward / EWMA std within a line "
                  f"(median) predictive {v['predictive']['ff_vs_ewma']['median']}, "
                  f"combined {v['ff_vs_ewma']['median']}; EWMA std {v['ewma_std_deg']} deg")
        if "fused" in s[name]:
            f = s[name]["fused"]
            print(f"  {name:5s} camera {f['camera_deg']:g} deg fused into the posterior: "
                  f"{f['ff_vs_ewma']['median']} (linear limit "
                  f"{f['reference_limit']['ff_vs_ewma_median']})")
    (out / "sensors_study.json").write_text(json.dumps(s, indent=2) + "\n")
    print(f"  -> {out / 'sensors_study.json'}")
    return 0
