"""Model health: does the service say when its model does not explain the curves, and only then?

Figures (``benchmarks/results/bench_health.json``):

* ``mismatch_detect_products``: products until the first ``model_mismatch`` (rule k of m,
  :class:`formtwin.service.health.HealthRule`), the larger of two mismatches, each over
  ``--seeds`` streams: an analytic stream (the closed-form stand-in, production run with
  deviation, 2 N sensor noise) on the bundled physics metamodel, and a physics stream (the
  bending model, through ``g``) on the analytic model. Target <= 10.
Both run the service's own :class:`~formtwin.service.health.ModelHealth` (the k-of-m rule
and its explain check) on the tracker's estimates, without a broker.

* ``false_mismatch_per_10k``: model-mismatch episodes per 10 000 products of *matched*
  streams on the bundled physics metamodel, the larger of the paper's series 1 (metamodel
  data, mu known, no deviation) and series 6 (physics data through ``g``, deviation
  estimated, mu assumed mid-range; the metamodel error is real). ``--products`` each
  (default 10 000). Target <= 1.
* ``dead_sensor_rejected``: share of dead-sensor strokes (zero, noise only, flat, clipped at
  30/50/80 % of the peak, peak shifted out of the window) rejected by the plausibility
  checks derived from the metamodel; ``valid_rejected`` the share of real curves rejected.

Besides, the distribution of the fit under matched conditions: quantiles of the distance
and the share of ``no_fit``/``degraded`` products per series. The physics curves of series
6 are computed once and cached in ``benchmarks/.cache`` (about 0.1 s per product).

Run ``python benchmarks/bench_health.py`` (heavy)
(``--products 500`` for a quick look; ``--learn-residuals``: every tracker with the line's
residual moment learned online, written as ``bench_health_learn_residuals.json``).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

import numpy as np

from formtwin._bench import CACHE, bundled_metamodel, write_result
from formtwin._threads import single_blas_thread
from formtwin.defaults import analytic_model, physics_model
from formtwin.deviation import DeviationModel
from formtwin.doe import run_design
from formtwin.estimates import Estimates
from formtwin.production import draw_production_run
from formtwin.service.health import HealthRule, ModelHealth
from formtwin.service.plausibility import Plausibility
from formtwin.service.runtime import explainer
from formtwin.service.store import Store
from formtwin.tracker import TrackerConfig, build_tracker


def run_service_health(model: Any, config: TrackerConfig, curves: np.ndarray,
                       rule: HealthRule, folder: Path) -> tuple[Estimates, list[int], int]:
    """Track the finite curves and feed the service's :class:`ModelHealth` (with its
    explain check) as ``formtwin serve`` does; the estimates, the products (1-based) at
    which an episode opens, and the number of vetoed openings (model explains the curves)."""
    ok = np.all(np.isfinite(curves), axis=1)
    tracker = build_tracker(model, config)
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"health_{time.time_ns()}.sqlite"
    store = Store(path)
    health = ModelHealth(store, rule, explain=explainer(tracker))
    items, opened, vetoed = [], [], 0
    try:
        with single_blas_thread():
            for i, c in enumerate(curves[ok]):
                e = tracker.step(c)
                items.append(e)
                entry = health.observe(e.to_dict(), c)
                vetoed += "explained" in entry
                if entry["event"] == "opened":
                    opened.append(i + 1)
    finally:
        store.close()
        for f in folder.glob(path.name + "*"):
            f.unlink()
    return Estimates.stack(items, tracker.names), opened, vetoed


def physics_curves(spec: Any, run: Any, name: str) -> np.ndarray:
    """The bending model's curves of a production run (cached per model version), through
    ``g``."""
    CACHE.mkdir(parents=True, exist_ok=True)
    sim = physics_model("bending", spec)
    data = run_design(sim, run.run_inputs, CACHE / f"{name}_{sim.version}.h5", progress=True)
    curves = np.where(data.ok[:, None], data.curves, np.nan)
    return DeviationModel.from_spec(spec).apply(
        np.nan_to_num(curves), np.tile(run.theta_d, (len(curves), 1))) + \
        np.where(data.ok[:, None], 0.0, np.nan)


def summary(est: Estimates) -> dict[str, float]:
    """Distribution of the fit of a run."""
    assert est.fit_distance2 is not None and est.health is not None
    d2 = est.fit_distance2
    return {"distance2_median": float(np.median(d2)), "distance2_p99": float(np.quantile(
        d2, 0.99)), "distance2_max": float(d2.max()),
        "no_fit_share": float(np.mean(est.health == "no_fit")),
        "degraded_share": float(np.mean(est.health == "degraded")),
        "ess_median": float(np.median(est.ess))}


def dead_sensor_cases(curves: np.ndarray, time_s: np.ndarray, rng: np.random.Generator
                      ) -> dict[str, np.ndarray]:
    """Dead-sensor strokes made from real curves ``(n, n_t)``."""
    n, n_t = curves.shape
    peak = curves.max(axis=1, keepdims=True)
    shift = int(round(0.03 / float(time_s[1] - time_s[0])))
    return {
        "zero": np.zeros((n, n_t)),
        "noise_only": 2.0 * rng.standard_normal((n, n_t)),
        "flat": np.tile(0.3 * peak, (1, n_t)),
        "clipped_30": np.minimum(curves, 0.3 * peak),
        "clipped_50": np.minimum(curves, 0.5 * peak),
        "clipped_80": np.minimum(curves, 0.8 * peak),
        "peak_late": np.roll(curves, shift, axis=1),
        "peak_early": np.roll(curves, -2 * shift, axis=1),
    }


def main() -> None:
    """Measure and write ``bench_health.json``."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--products", type=int, default=10_000, help="matched products per series")
    ap.add_argument("--particles", type=int, default=500, help="N")
    ap.add_argument("--seeds", type=int, default=3, help="streams per mismatch case")
    ap.add_argument("--detect-products", type=int, default=60,
                    help="products per mismatch stream")
    ap.add_argument("--learn-residuals", action="store_true",
                    help="trackers with learn_residuals (bench_health_learn_residuals.json)")
    args = ap.parse_args()
    opts = {"learn_residuals": args.learn_residuals}
    t0 = time.perf_counter()
    mm, _, info = bundled_metamodel()
    am = analytic_model(mm.spec)
    spec = mm.spec
    rule = HealthRule()
    base = TrackerConfig(n_particles=args.particles, **opts)
    figures: dict[str, Any] = {}
    # -- matched streams: series 1 and 6 -------------------------------------------------
    n = args.products
    rng = np.random.default_rng(np.random.SeedSequence([16, 1]))
    run1 = draw_production_run(spec, n, rng, deviation=False)
    tmp = CACHE / "health_stores"
    est1, ep1, veto1 = run_service_health(
        mm, TrackerConfig(n_particles=args.particles, estimate_deviation=False,
                          mu=tuple(run1.mu), **opts), mm.predict_curves(run1.inputs), rule, tmp)
    rng = np.random.default_rng(np.random.SeedSequence([16, 6]))
    run6 = draw_production_run(spec, n, rng)
    fe6 = physics_curves(spec, run6, f"health_series6_{n}")
    est6, ep6, veto6 = run_service_health(mm, base, fe6, rule, tmp)
    figures["false_mismatch_per_10k"] = max(len(ep1) / len(est1), len(ep6) / len(est6)) * 1e4
    figures["false_mismatch_series1"] = len(ep1)
    figures["false_mismatch_series6"] = len(ep6)
    figures["explained_by_model_series1"] = veto1
    figures["explained_by_model_series6"] = veto6
    figures["products_series1"] = len(est1)
    figures["products_series6"] = len(est6)
    for name, est in (("series1", est1), ("series6", est6)):
        for k, v in summary(est).items():
            figures[f"{name}_{k}"] = round(v, 4)
    # -- mismatched streams ----------------------------------------------------------------
    m = args.detect_products
    detect: dict[str, list[int | None]] = {"analytic_on_physics_mm": [],
                                           "physics_on_analytic": []}
    noise = np.random.default_rng(7)
    for seed in range(args.seeds):
        r = draw_production_run(spec, m, np.random.default_rng([16, 100, seed]))
        z = DeviationModel.from_spec(spec).apply(am.predict_curves(r.inputs),
                                                 np.tile(r.theta_d, (m, 1)))
        z = z + 2.0 * noise.standard_normal(z.shape)
        first = run_service_health(mm, base, z, rule, tmp)[1]
        detect["analytic_on_physics_mm"].append(first[0] if first else None)
        y = fe6[seed * m:(seed + 1) * m]
        first = run_service_health(am, base, y, rule, tmp)[1]
        detect["physics_on_analytic"].append(first[0] if first else None)
    worst = [v for vs in detect.values() for v in vs]
    figures["mismatch_detect_products"] = None if None in worst else max(
        v for v in worst if v is not None)
    for k, vs in detect.items():
        figures[f"detect_{k}"] = vs
    # -- dead sensors ----------------------------------------------------------------------
    plaus = Plausibility.from_model(mm)
    real = np.vstack([mm.predict_curves(run1.inputs[:500]), fe6[:500][np.all(
        np.isfinite(fe6[:500]), axis=1)]])
    cases = dead_sensor_cases(real, spec.time, np.random.default_rng(3))
    rejected, total = 0, 0
    for name, cs in cases.items():
        reasons = [plaus.check(c) for c in cs]
        got = sum(e is not None for e in reasons)
        figures[f"dead_{name}_rejected"] = round(got / len(cs), 4)
        rejected, total = rejected + got, total + len(cs)
    figures["dead_sensor_rejected"] = round(rejected / total, 4)
    figures["valid_rejected"] = round(float(np.mean([plaus.check(c) is not None
                                                     for c in real])), 4)
    figures["plausibility"] = plaus.describe()
    figures["rule"] = f"k = {rule.k} of m = {rule.m} products no_fit"
    figures["particles"] = args.particles
    figures["learn_residuals"] = args.learn_residuals
    figures["wall_s"] = round(time.perf_counter() - t0, 1)
    write_result("health_learn_residuals" if args.learn_residuals else "health", figures,
                 model=info)


if __name__ == "__main__":
    main()
