"""The sensor benchmark's figures of control and of the default study's state intervals,
called by ``bench_sensors.py`` and runnable alone (then merged into
``benchmarks/results/bench_sensors.json``, its other figures kept).

1. ``ff_vs_ewma_within_curve`` (target <= 0.80) and ``ff_vs_ewma_within_gauge`` (<= 0.65):
   the closed-loop study with the line's real sensors
   (:mod:`formtwin.study.control_sensors`: the physics model as the plant under series-6
   conditions, 5 datasets x 1000 products, N = 500, the first 5 plants of
   ``bench_control.py``; ``--datasets`` changes the 5):
   the feedforward's final-angle std over the run-to-run EWMA's, within each dataset, median
   over the datasets, both reading the camera's angle with 0.2 deg noise one product late.
   The feedforward is :class:`~formtwin.control.Predictive` on the fused posterior: the
   camera's values fused into the particles and correcting the posterior's predicted angle
   through the discrepancy learned from them (nothing tuned on the datasets);
   ``curve``: the curve and the camera, ``gauge``: with the 0.5 um strip gauge fused too.
   ``ff_vs_ewma_reference_limit``: the least ratio a feedforward linear in the posterior's
   predicted angle could reach on the same lines (the best coefficients known, without
   learning them); ``ff_vs_ewma_bound``: the linear-Gaussian bound (theta and mu known, an
   exact model); ``ff_vs_ewma_combined``: the earlier controller
   (:class:`~formtwin.control.Combined`, weights chosen on the other datasets).
   ``sensor_control`` holds every camera noise (0, 0.1, 0.2 deg), per dataset, the stds and
   the weights chosen.
2. ``state_coverage90_min`` (target >= 0.80): the default study (``formtwin study``'s
   settings: calibrated intervals, repetition 0) of series 1, 3, 4 and 5 on the sensor
   benchmark's datasets: how often each state's reported 90 % interval holds the truth
   over the last ``window`` products, mean over the 7 states and the datasets, the least
   over the series (``state_coverage90`` per series); ``state_coverage90_min_per_state``
   the least single state's (mean over datasets) and which.
3. ``study_s`` (target <= 600, with ``--only study``): the default ``make demo`` study
   (``formtwin demo``: ``formtwin study`` of the bending model, its default settings) in an
   emptied folder, as its ``timings.json`` records it (pseudo-data from the physics model,
   K_MC builds, the filter runs, scoring; the bundled metamodel loaded);
   ``study_wall_s`` adds writing the report; the load average before and after.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from formtwin._bench import CACHE, ROOT, bundled_metamodel, write_result
from formtwin.defaults import default_metamodel, physics_model
from formtwin.study.control import ControlStudySettings
from formtwin.study.control_sensors import SensorControlSettings, run_sensor_control
from formtwin.study.run import StudySettings, run_study

#: the series of ``state_coverage90_min`` (the target's: model right or g(MM) modelled, mu
#: known or assumed, physics data)
COVERAGE_SERIES = (1, 3, 4, 5)


def control_figures(smoke: bool = False, out: Path = CACHE / "control", datasets: int = 5
                    ) -> dict[str, Any]:
    """Figure 1 of the module doc with ``datasets`` datasets (``smoke``: 2 datasets x 150
    products in a folder of their own)."""
    if smoke:
        out = out.with_name(out.name + "_smoke")
    t0 = time.perf_counter()
    metamodel, _ = default_metamodel(out / "model", "bending")
    physics = physics_model("bending", metamodel.spec)
    base = ControlStudySettings(products=150 if smoke else 1000, datasets=2 if smoke else datasets,
                                burn_in=30 if smoke else 100, workers=2)
    # the camera of 0.2 deg; the earlier controller at the weights its tuning chose
    # there (bench_sensors.json of 2026-11-28, 2 datasets: lam 0.02-0.05, rho 0)
    s = run_sensor_control(metamodel, physics, SensorControlSettings(
        base=base, camera_noises=(0.2,), grid=((0.02, 0.0),)), out)
    return {"ff_vs_ewma_within_curve": s["curve"]["fused"]["ff_vs_ewma"]["median"],
            "ff_vs_ewma_within_gauge": s["gauge"]["fused"]["ff_vs_ewma"]["median"],
            "ff_vs_ewma_bound": control_bound(s),
            "ff_vs_ewma_reference_limit": {
                n: s[n]["fused"]["reference_limit"]["ff_vs_ewma_median"] for n in s
                if isinstance(s[n], dict) and "fused" in s[n]},
            "ff_vs_ewma_combined": {n: s[n]["0.2"]["ff_vs_ewma"]["median"] for n in s
                                    if isinstance(s[n], dict) and "0.2" in s[n]},
            "ff_vs_ewma_predictive_unfused": {
                n: s[n]["0.2"]["predictive"]["ff_vs_ewma"]["median"] for n in s
                if isinstance(s[n], dict) and "0.2" in s[n]},
            "sensor_control": {**s, "wall_s": round(time.perf_counter() - t0, 1)}}


def control_bound(s: dict[str, Any]) -> dict[str, Any]:
    """The least feedforward / EWMA std ratio the information allows, camera 0.2 deg: a
    feedforward that cancels its prediction of each product's final angle leaves the
    prediction's error, at least ``b`` times the angle's in-run std (fixed ``u``'s std
    within a line), ``b`` the linear-Gaussian bound of ``formtwin sensors``
    (``bound_s1_final`` of ``bench_sensors.json``: theta and mu known, metamodel exact, no
    deviation: the study's lines know less), over the EWMA's measured std."""
    path = ROOT / "benchmarks" / "results" / "bench_sensors.json"
    bound = json.loads(path.read_text()).get("figures", {}).get("bound_s1_final", {}) \
        if path.exists() else {}
    out: dict[str, Any] = {}
    for name, key in (("curve", "curve"), ("gauge", "gauge_0.5um")):
        if key in bound:
            out[name] = round(bound[key] * s["fixed_std_deg"] / s[name]["0.2"]["ewma_std_deg"],
                              4)
    return out


def coverage_figures(settings: StudySettings, out: Path, metamodel: Any, metamodel_path: Path
                     ) -> dict[str, Any]:
    """Figure 2 of the module doc: the study of ``settings`` (its sizes, seed, tracker) run
    for :data:`COVERAGE_SERIES` in ``out`` (its cached runs reused)."""
    import dataclasses

    s = dataclasses.replace(settings, series=COVERAGE_SERIES)
    study = run_study(s, out, metamodel, metamodel_path,
                      physics_model("bending", metamodel.spec))
    nx = len(metamodel.spec.state)
    rows = [n - 1 for n in COVERAGE_SERIES]  # the study's arrays are indexed by series - 1
    cov = np.nanmean(study.coverage[rows, :, 0, :nx], axis=1)  # (4, 7) mean over datasets
    per = {str(n): round(float(np.mean(c)), 4) for n, c in zip(COVERAGE_SERIES, cov,
                                                               strict=True)}
    i, j = np.unravel_index(int(np.nanargmin(cov)), cov.shape)
    return {"state_coverage90_min": min(per.values()), "state_coverage90_default": per,
            "state_coverage90_min_per_state": {
                "value": round(float(cov[i, j]), 4), "series": COVERAGE_SERIES[int(i)],
                "state": metamodel.spec.state.names[int(j)]},
            "state_coverage90_default_per_state": {
                str(n): dict(zip(metamodel.spec.state.names, np.round(c, 3).tolist(),
                                 strict=True)) for n, c in zip(COVERAGE_SERIES, cov,
                                                               strict=True)}}


def sensor_control_figures(settings: StudySettings, out: Path, metamodel: Any,
                           metamodel_path: Path, smoke: bool) -> dict[str, Any]:
    """Both figures (``bench_sensors.py``'s call): the coverage on its study's datasets in
    its folder ``out``, the control study in its own."""
    return {**coverage_figures(settings, out, metamodel, metamodel_path),
            **control_figures(smoke)}


def study_figures(out: Path = CACHE / "demo_study") -> dict[str, Any]:
    """Figure 3 of the module doc, in the folder ``out`` (its data and runs removed
    first)."""
    import os
    import shutil

    from formtwin.cli import study

    for sub in ("data", "runs", "measurement"):
        shutil.rmtree(out / sub, ignore_errors=True)
    (out / "timings.json").unlink(missing_ok=True)
    load0 = [round(v, 2) for v in os.getloadavg()]
    t0 = time.perf_counter()
    ns = study.build_namespace(out=str(out), physics="bending")
    if study.run(ns) != 0:
        raise RuntimeError("the default study failed")
    wall = time.perf_counter() - t0
    t = json.loads((out / "timings.json").read_text())
    return {"study_s": round(float(t["total_s"]), 1), "study_wall_s": round(wall, 1),
            "study_timings": {k: round(v, 1) if isinstance(v, float) else v
                              for k, v in t.items()},
            "study_load_avg_1_5_15min": {"before": load0,
                                         "after": [round(v, 2) for v in os.getloadavg()]}}


def main() -> None:
    """Compute the figures alone and merge them into ``bench_sensors.json``."""
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--out", default="benchmarks/.cache/sensors",
                   help="the sensor benchmark's folder (its study's cached runs reused)")
    p.add_argument("--quick", action="store_true", help="smoke test")
    p.add_argument("--only", choices=("control", "coverage", "study"),
                   help="one of the figures (study: only with --only)")
    p.add_argument("--datasets", type=int, default=5, help="datasets of the control study")
    args = p.parse_args()
    out = Path(args.out)
    figures: dict[str, Any] = {}
    if args.only == "study":
        figures.update(study_figures())
    if args.only in (None, "coverage"):
        mm, mm_path, _ = bundled_metamodel(out / "model")
        sizes: dict[str, Any] = {"n_products": 200, "n_realisations": 2, "window": 100} \
            if args.quick else {}
        settings = StudySettings(n_repetitions=1, paper_repetitions=0, **sizes)
        figures.update(coverage_figures(settings, out, mm, mm_path))
    if args.only in (None, "control"):
        figures.update(control_figures(args.quick, datasets=args.datasets))
    print(json.dumps(figures, indent=1))
    if args.quick:
        return
    path = ROOT / "benchmarks" / "results" / "bench_sensors.json"
    old = json.loads(path.read_text()) if path.exists() else {"figures": {}}
    model = old.get("model")
    write_result("sensors", {**old["figures"], **figures},
                 **({"model": model} if model is not None else {}))
    apart = measured_apart(old.get("figures_measured_apart"), list(figures),
                           "python benchmarks/_sensor_control.py " + " ".join(sys.argv[1:]))
    doc = json.loads(path.read_text())
    path.write_text(json.dumps({**doc, "figures_measured_apart": apart}, indent=2) + "\n",
                    encoding="utf-8")


def measured_apart(old: Any, keys: list[str], command: str) -> list[dict[str, Any]]:
    """The entries of ``figures_measured_apart`` (the keys of ``bench_sensors.json``
    measured by another command than ``bench_sensors.py``, each with its command, commit
    and date): the ``old`` entries (one dict or a list) less ``keys``, and ``keys``
    measured now by ``command``."""
    entries = [old] if isinstance(old, dict) else list(old or [])
    out = []
    for e in entries:
        rest = [k for k in e.get("keys", []) if k not in keys]
        if rest:
            out.append({**e, "keys": rest})
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, text=True,
                            capture_output=True, check=False).stdout.strip()
    out.append({"keys": keys, "command": command, "commit": commit,
                "date": datetime.now(UTC).isoformat(timespec="seconds")})
    return out


if __name__ == "__main__":
    main()
