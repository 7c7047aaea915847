"""Benchmark of the monitoring (EWMA, CUSUM and model-mismatch charts): detection delay
for known changes and false alarms in control.

Run ``python benchmarks/bench_monitoring.py`` (heavy, ~15 min: run it when
the machine is free). Model: the metamodel of the bundled physics DOE
(:func:`formtwin._bench.bundled_metamodel`, what a fresh clone gets); tracker: the default
:class:`~formtwin.tracker.TrackerConfig` (its likelihood) with N = ``--particles``, the
line's state means ``mu`` known (the spec's mid-range), no deviation on the curves and
none estimated (``--deviation``: every run's curves distorted by the deviation model with
its theta_d drawn once per run, as in the paper's series 6 and on a line, and the tracker
estimating it, as the service does; ``--name monitoring_deviation`` keeps its JSON apart),
``K_MC`` from 10^4 curves. Every curve gets measurement
noise as the likelihood assumes it, ``N(0, Sigma)``
(:func:`~formtwin.monitoring.calibrate.measurement_noise`). The tracked series (posterior
means, predicted angles, health statistics) are cached in ``benchmarks/.cache/monitoring``
by their settings and a hash of the code that makes the estimates, so chart designs
(``--k``, ``--arl0``, ``--widen-margin``, ...) are compared on the same estimates.

1. Calibration: :func:`~formtwin.monitoring.calibrate.calibrate_series` on ``--calib-runs``
   simulated in-control runs of ``--calib-products`` products (AR(2) models of the state
   posterior means about mu, of the predicted angles about a Phase-I level, health
   references (the calibration lines' pooled values; ``--health-per-line``: each line's
   own Phase-I values) and AR models of their normal scores, whose levels follow the line
   once charting (``--health-level``, 0: fixed); limits for the design's
   ARL0 per chart, widened where the calibration runs would have crossed them).
2. False alarms: ``--ic-runs`` fresh in-control runs (other seeds, other machine
   parameters) of ``--ic-products`` products; every alarm counts.
   ``false_alarms_per_10k_products`` = alarms / charted products * 10^4 (charted: after
   warm-up and Phase I), with its exact Poisson 95 % interval.
3. Changes (:mod:`formtwin.monitoring.scenarios`), the change at product ``--at`` (after
   warm-up and Phase I), each run ``--after`` products after it:

   * ``step``: a 2-sigma step in the mean of one state variable (up and down in turn,
     ``--reps`` runs per variable), every variable in turn;
     ``detection_delay_median_products`` is the median over all variables and runs of
     ``first alarm index - at + 1`` (alarms before ``at`` are counted, not taken as
     detections); a run without an alarm counts as ``after + 1`` (``detected_share`` and
     ``within_30_share`` say how many were seen, per variable too);
   * ``drift``: the mean of one variable moving by ``--drift`` sigma per product
     (``--drift-reps`` runs per variable);
   * ``batch``: a new material batch, the four material means each stepping by
     ``--batch`` sigma with random signs (2 x ``--drift-reps`` runs).
4. A mismatch that persists (:class:`~formtwin.monitoring.scenarios.Fault`): a force-sensor
   fault from product ``--at`` to the run's end ``--fault-products`` later (gain +-10 %,
   zero offset +-2 N; ``--fault-reps`` runs each, in control otherwise): the delay to the
   first alarm and to the first mismatch alarm, and ``signalled_share``: the share of the
   50-product windows after the fault with a mismatch alarm (1: signalled throughout).
5. Alarm episodes (:mod:`~formtwin.monitoring.episodes`, as the service stores and publishes
   alarms): per fault run the signals (the service's alarm rows until 0.1.0.dev12) and the
   episodes raised per 1000 products after the fault; in control the episodes per 10^4
   charted products beside the false alarms (signals). The figures above count signals
   (every one in control, the first after a change) and do not depend on the episodes.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import time
from dataclasses import asdict, replace
from pathlib import Path
from typing import Any

import numpy as np
from scipy.stats import chi2

import formtwin
from formtwin._bench import CACHE, bundled_metamodel, write_result
from formtwin._threads import single_blas_thread
from formtwin.estimates import Estimates
from formtwin.measurement import MeasurementModel, ProcessModel
from formtwin.monitoring.bound import curve_jacobian, glr_delays, steady_filter, step_in_filter
from formtwin.monitoring.calibrate import (
    ChartDesign,
    calibrate_series,
    in_control_runs,
    measurement_noise,
    series,
)
from formtwin.monitoring.episodes import Episode, Episodes, clear_after
from formtwin.monitoring.glr import residual_response, step_response
from formtwin.monitoring.monitor import Alarm, Monitor, MonitorConfig
from formtwin.monitoring.scenarios import Change, Fault, changed_run
from formtwin.tracker import Tracker, TrackerConfig
from formtwin.tracker.build import build_measurement

Series = dict[str, np.ndarray]
#: prefix of the true states in a cached run
TRUE = "true_"
#: the persistent mismatches: force-sensor (gain, offset N)
FAULTS = ((0.1, 0.0), (-0.1, 0.0), (0.0, 2.0), (0.0, -2.0))
#: window (products) of the share of a fault's run that is signalled
WINDOW = 50


class Runs:
    """Tracked series by name, computed once and cached as ``.npz``."""

    def __init__(self, folder: Path, key: dict[str, Any]) -> None:
        self.folder = folder / hashlib.sha256(json.dumps(key, sort_keys=True).encode()
                                              ).hexdigest()[:12]
        self.folder.mkdir(parents=True, exist_ok=True)
        (self.folder / "key.json").write_text(json.dumps(key, indent=1))

    def get(self, name: str, make: Any) -> tuple[Series, Series]:
        """The series of run ``name`` and its true states (by state name), from the cache or
        ``make()`` (``(x, estimates)``)."""
        path = self.folder / f"{name}.npz"
        if path.exists():
            with np.load(path, allow_pickle=False) as f:
                out = {k: f[k] for k in f.files}
        else:
            x, est = make()
            out = {k: np.asarray(v, dtype=np.float64) for k, v in series(est).items()}
            out.update({TRUE + n: x[:, j] for j, n in enumerate(est.names[: x.shape[1]])})
            np.savez(path, **out)  # type: ignore[arg-type]
        return ({k: v for k, v in out.items() if not k.startswith(TRUE)},
                {k[len(TRUE):]: v for k, v in out.items() if k.startswith(TRUE)})


def chart(config: MonitorConfig, s: Series) -> list[Alarm]:
    """Chart a run's series; all alarms."""
    mon = Monitor(config)
    n = len(next(iter(s.values())))
    return [a for i in range(n)
            for a in mon.update_values({k: float(v[i]) for k, v in s.items()}, i)]


def episodes(config: MonitorConfig, s: Series) -> list[Episode]:
    """Chart a run's series with alarm episodes; every episode (its last state), in the
    order raised."""
    mon = Monitor(config)
    eps = Episodes(clear_after(mon))
    n = len(next(iter(s.values())))
    out: dict[tuple[str, str, int], Episode] = {}
    for i in range(n):
        for c in eps.update(i, mon.update_values({k: float(v[i]) for k, v in s.items()}, i)):
            out[(c.episode.variable, c.episode.chart, c.episode.first)] = c.episode
    return list(out.values())


def changed(model: ProcessModel, mm: MeasurementModel, tcfg: TrackerConfig, change: Change,
            n: int, seed: int, noise: bool = True, fault: Fault | None = None
            ) -> tuple[np.ndarray, Estimates]:
    """Track one production run with ``change``, its curves with measurement noise (and,
    when the tracker estimates the deviation, distorted by it, theta_d drawn) and then
    ``fault``: its true states (n, 7) and estimates."""
    rng = np.random.default_rng(seed)
    tracker = Tracker(model, mm, replace(tcfg, seed=seed))
    dev = tcfg.estimate_deviation
    run = changed_run(model.spec, n, np.asarray(tcfg.mu), rng, change, deviation=dev)
    curves = model.predict_curves(run.inputs)
    if dev:
        curves = tracker.ssm.deviation.apply(curves, np.tile(run.theta_d, (n, 1)))
    if noise:
        curves = curves + measurement_noise(mm, n, rng)
    if fault is not None:
        curves = fault.apply(curves)
    return run.x, tracker.run(curves)


def estimates_code() -> str:
    """Hash of the package's source outside what charts, serves or studies (monitoring,
    service, cli, study, control, physics: the DOE's hash covers the latter) and of its data
    files' JSON (the interval calibration): what makes the estimates (a cached series is
    stale when it changes)."""
    h = hashlib.sha256()
    pkg = Path(formtwin.__file__).parent
    skip = ("monitoring", "service", "cli", "study", "control", "physics", "figures.py")
    for f in sorted(pkg.rglob("*.py")):
        if f.relative_to(pkg).parts[0] not in skip:
            h.update(f.read_bytes())
    for f in sorted((pkg / "data").glob("*.json")):
        h.update(f.read_bytes())
    return h.hexdigest()[:16]


def delay(alarms: list[Alarm], at: int, n: int) -> tuple[int, int, str]:
    """(delay, false alarms before ``at``, first alarm's variable) of one changed run."""
    after = [a for a in alarms if a.index >= at]
    first = after[0] if after else None
    return (first.index - at + 1 if first else n - at + 1, sum(a.index < at for a in alarms),
            first.variable if first else "")


def persistence(alarms: list[Alarm], eps: list[Episode], at: int, n: int) -> dict[str, Any]:
    """Of one fault's run: products to the first alarm and to the first mismatch alarm
    (``None``: none), the share of the :data:`WINDOW`-product windows from ``at`` to ``n``
    with a mismatch alarm, the signals and episodes raised from ``at`` on per 1000
    products, and per chart its episodes, signals and longest gap between signals
    (``by_chart``)."""
    mis = [a.index for a in alarms if a.chart == "mismatch" and a.index >= at]
    first = [a.index for a in alarms if a.index >= at]
    wins = range(at, n, WINDOW)
    by_chart: dict[str, list[int]] = {}  # episodes, signals, longest gap between signals
    for key in sorted({f"{a.variable}/{a.chart}" for a in alarms if a.index >= at}):
        idx = [a.index for a in alarms if a.index >= at and f"{a.variable}/{a.chart}" == key]
        by_chart[key] = [sum(e.first >= at and f"{e.variable}/{e.chart}" == key for e in eps),
                         len(idx), int(np.max(np.diff(idx), initial=0))]
    return {"first_alarm": first[0] - at + 1 if first else None,
            "first_mismatch": mis[0] - at + 1 if mis else None,
            "signalled_share": round(sum(any(w <= i < w + WINDOW for i in mis) for w in wins)
                                     / len(wins), 3),
            "alarms_before": sum(a.index < at for a in alarms),
            "signals_per_1000": round(sum(a.index >= at for a in alarms) / (n - at) * 1e3, 1),
            "episodes_per_1000": round(sum(e.first >= at for e in eps) / (n - at) * 1e3, 1),
            "by_chart": by_chart}


def summary(d: list[int], horizon: int, target: int = 30) -> dict[str, Any]:
    """Median, mean, detected share (``horizon + 1`` = not detected) and share detected
    within ``target`` products of delays."""
    a = np.asarray(d)
    return {"median": float(np.median(a)), "mean": round(float(a.mean()), 1),
            "detected_share": round(float(np.mean(a <= horizon)), 3),
            f"within_{target}_share": round(float(np.mean(a <= target)), 3)}


def poisson_interval(k: int, level: float = 0.95) -> tuple[float, float]:
    """Exact (Garwood) confidence interval of a Poisson mean from ``k`` events."""
    a = (1.0 - level) / 2.0
    lo = 0.0 if k == 0 else float(chi2.ppf(a, 2 * k)) / 2.0
    return lo, float(chi2.ppf(1.0 - a, 2 * k + 2)) / 2.0


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--particles", type=int, default=500)
    p.add_argument("--deviation", action="store_true")
    p.add_argument("--no-noise", action="store_true",
                   help="noise-free curves (the model's own, as the paper's pseudo-data)")
    p.add_argument("--calib-runs", type=int, default=12)
    p.add_argument("--calib-products", type=int, default=1500)
    p.add_argument("--ic-runs", type=int, default=25)
    p.add_argument("--ic-products", type=int, default=2000)
    p.add_argument("--reps", type=int, default=10, help="runs per variable and step sign")
    p.add_argument("--drift-reps", type=int, default=2,
                   help="runs per variable for the drift; 2 x this for the batch")
    p.add_argument("--at", type=int, default=250)
    p.add_argument("--after", type=int, default=150)
    p.add_argument("--drift", type=float, default=0.02)
    p.add_argument("--batch", type=float, default=1.0)
    p.add_argument("--fault-reps", type=int, default=2, help="runs per sensor fault")
    p.add_argument("--fault-products", type=int, default=750,
                   help="products after a sensor fault")
    d0 = ChartDesign()
    p.add_argument("--arl0", type=float, default=d0.arl0_per_chart, help="CUSUM ARL0")
    p.add_argument("--arl0-ewma", type=float, default=d0.arl0_ewma)
    p.add_argument("--arl0-mismatch", type=float, default=d0.arl0_mismatch)
    p.add_argument("--arl0-shewhart", type=float, default=d0.arl0_shewhart,
                   help="0: no Shewhart limit")
    p.add_argument("--widen-margin", type=float, default=d0.widen_margin, help="0: off")
    p.add_argument("--angle-cusum", action="store_true")
    p.add_argument("--lam", type=float, default=d0.lam)
    p.add_argument("--k", type=float, default=d0.k)
    p.add_argument("--no-tails", action="store_true")
    p.add_argument("--no-health-ar", action="store_true")
    p.add_argument("--health-phase1", action="store_true")
    p.add_argument("--health-per-line", action="store_true",
                   help="health scored against each line's own Phase-I values, not the "
                   "calibration lines' pooled values")
    p.add_argument("--health-level", type=float, default=d0.health_level or 0.0,
                   help="weight of the EWMA the health scores' levels follow (0: the "
                        "calibration lines' level throughout)")
    p.add_argument("--k-mismatch", type=float, default=d0.k_mismatch)
    p.add_argument("--no-glr", action="store_true")
    p.add_argument("--arl0-glr", type=float, default=d0.arl0_glr)
    p.add_argument("--glr-window", type=int, default=d0.glr_window)
    p.add_argument("--no-state-cusum", action="store_true")
    p.add_argument("--glr-clip", type=float, default=d0.glr_clip or 0.0, help="0: none")
    p.add_argument("--level-signature", action="store_true",
                   help="GLR matched to a step of the estimate, not of the state")
    p.add_argument("--seed", type=int, default=2026)
    p.add_argument("--track-only", action="store_true",
                   help="track (fill the cache) and stop")
    p.add_argument("--bound-only", action="store_true",
                   help="print the linear-Gaussian bound (no tracking) and stop")
    p.add_argument("--bound-draws", type=int, default=4,
                   help="machine-parameter draws of the linear-Gaussian bound")
    p.add_argument("--out", help="result folder (default benchmarks/results)")
    p.add_argument("--name", default="monitoring",
                   help="result file bench_NAME.json (default: %(default)s)")
    args = p.parse_args()
    model, _, info = bundled_metamodel()
    spec = model.spec
    mu = spec.state.mu_mid
    tcfg = TrackerConfig(n_particles=args.particles, estimate_deviation=args.deviation,
                         mu=tuple(mu), seed=args.seed)
    # the measurement model as every tracker gets it (the default likelihood: K_res too)
    mm = build_measurement(model, tcfg, np.random.default_rng(args.seed))
    design = ChartDesign(lam=args.lam, k=args.k, k_mismatch=args.k_mismatch,
                         arl0_per_chart=args.arl0, arl0_ewma=args.arl0_ewma,
                         arl0_mismatch=args.arl0_mismatch,
                         arl0_shewhart=args.arl0_shewhart or None,
                         widen_margin=args.widen_margin or None, angle_cusum=args.angle_cusum,
                         tails=not args.no_tails, health_ar=not args.no_health_ar,
                         health_phase1=args.health_phase1,
                         health_per_line=args.health_per_line,
                         health_level=args.health_level or None, glr=not args.no_glr,
                         arl0_glr=args.arl0_glr, glr_window=args.glr_window,
                         glr_clip=args.glr_clip or None,
                         state_cusum=not args.no_state_cusum)
    key = {"model": info["doe_sha256_16"], "metamodel": info["metamodel"],
           "tracker": tcfg.to_dict(), "code": estimates_code(),
           "noise": "none" if args.no_noise else "N(0, Sigma)",
           "seed": args.seed, "at": args.at, "after": args.after}
    if args.deviation:  # the changed runs' curves carry the deviation too
        key["curves"] = "g(theta_d), theta_d drawn per run"
    bound = linear_bound(model, mm, mu, design, args)
    if args.bound_only:
        print(json.dumps(bound, indent=1))
        return
    runs = Runs(CACHE / "monitoring", key)
    noise = not args.no_noise
    n = args.at + args.after
    t0 = time.perf_counter()
    with single_blas_thread():
        calib = [runs.get(f"calib{r}_{args.calib_products}", lambda r=r: in_control_runs(
            model, mm, replace(tcfg, seed=tcfg.seed + r), args.calib_products, 1,
            seed=args.seed + r, noise=noise)[0]) for r in range(args.calib_runs)]
        scenarios: dict[str, list[tuple[Change, Series, Series]]] = {}
        ic: list[tuple[Series, Series]] = []
        for kind, size in (("step", 2.0), ("ic", 0.0), ("drift", args.drift)):
            if kind == "ic":  # tracked between the steps and the drifts (cache order)
                ic = [runs.get(f"ic{r}_{args.ic_products}", lambda r=r: in_control_runs(
                    model, mm, replace(tcfg, seed=tcfg.seed + 5000 + r), args.ic_products, 1,
                    seed=args.seed + 10_000 + r, noise=noise)[0])
                    for r in range(args.ic_runs)]
                continue
            for j, name in enumerate(spec.state.names):
                scenarios[f"{kind}:{name}"] = []
                for r in range(args.reps if kind == "step" else args.drift_reps):
                    ch = Change(kind, (name,), args.at, size * (1 if r % 2 == 0 else -1))
                    seed = args.seed + 100_000 + 1000 * j + 100 * (kind == "drift") + r
                    scenarios[f"{kind}:{name}"].append((ch, *runs.get(
                        f"{kind}_{name}_{size}_{r}",
                        lambda ch=ch, seed=seed: changed(model, mm, tcfg, ch, n, seed, noise))))
        rng = np.random.default_rng(args.seed + 7)
        scenarios["batch"] = []
        for r in range(2 * args.drift_reps):
            ch = Change.batch(args.at, args.batch, rng)
            scenarios["batch"].append((ch, *runs.get(
                f"batch_{args.batch}_{r}", lambda ch=ch, r=r: changed(
                    model, mm, tcfg, ch, n, args.seed + 200_000 + r, noise))))
        n_fault = args.at + args.fault_products
        faults: dict[str, list[Series]] = {}
        for k, (g, o) in enumerate(FAULTS):
            fault = Fault(args.at, g, o)
            faults[f"gain{g:+g}_offset{o:+g}"] = [runs.get(
                f"fault_{g:+g}_{o:+g}_{r}_{n_fault}", lambda f=fault, s=args.seed + 300_000
                + 100 * k + r: changed(model, mm, tcfg, Change("none"), n_fault, s, noise, f))[0]
                for r in range(args.fault_reps)]
    if args.track_only:
        print(f"tracked into {runs.folder} in {time.perf_counter() - t0:.0f} s")
        return
    track_s = time.perf_counter() - t0
    names = spec.state.names
    truths = None if args.level_signature else [np.column_stack([t[k] for k in names])
                                                for _, t in calib]
    config = calibrate_series([e for e, _ in calib], names, mu, design, truths)
    figures = evaluate(config, [e for e, _ in ic], {k: [(ch, e) for ch, e, _ in v]
                                                     for k, v in scenarios.items()}, names, args)
    # the oracle: the same charts on the true states (what a perfect estimate allows)
    # (no clip: the true states do not jump as the particle filter's estimates do)
    t_config = calibrate_series([t for _, t in calib], names, mu, replace(design, glr_clip=None))
    oracle = evaluate(t_config, [t for _, t in ic], {k: [(ch, t) for ch, _, t in v]
                                                     for k, v in scenarios.items()}, names, args)
    response = {n: what_a_step_leaves(config, [e[n] for e, _ in calib], [t[n] for _, t in calib],
                                      float(mu[j]), float(spec.state.sigma[j]), n, design)
                for j, n in enumerate(names)}
    steps = figures.pop("step_2sigma")
    per_fault = {k: [persistence(chart(config, s), episodes(config, s), args.at, n_fault)
                     for s in v] for k, v in faults.items()}
    flat = [r for v in per_fault.values() for r in v]
    figures = {
        "detection_delay_median_products": steps["median"],
        "detection_delay_target": 30,
        **figures,
        "false_alarms_target": 1,
        "step_2sigma": steps,
        "persistent_mismatch": {
            "signalled_share_mean": round(float(np.mean([r["signalled_share"] for r in flat])), 3),
            "signalled_share_mean_detected": round(float(np.mean(
                [r["signalled_share"] for r in flat if r["first_mismatch"] is not None]
                or [np.nan])), 3),
            "detected": sum(r["first_mismatch"] is not None for r in flat), "runs": len(flat),
            "signals_per_1000_mean": round(float(np.mean([r["signals_per_1000"] for r in flat])),
                                           1),
            "episodes_per_1000_mean": round(float(np.mean([r["episodes_per_1000"]
                                                           for r in flat])), 1),
            "window": WINDOW, "products_after": args.fault_products, "per_fault": per_fault},
        "step_2sigma_in_the_estimates": response,
        "linearised_bound": bound,
        "oracle_true_states": {
            "detection_delay_median_products": oracle["step_2sigma"]["median"],
            **{k: v for k, v in oracle.items() if k != "charts"}},
        "settings": {"seed": args.seed, "particles": args.particles, "deviation": args.deviation,
                     "likelihood": tcfg.likelihood,
                     "noise": key["noise"],
                     "calib_runs": args.calib_runs, "calib_products": args.calib_products,
                     "ic_runs": args.ic_runs, "ic_products": args.ic_products,
                     "reps": args.reps, "drift_reps": args.drift_reps, "at": args.at,
                     "fault_reps": args.fault_reps,
                     "after": args.after,
                     "design": asdict(design), **figures.pop("charts"),
                     "oracle_charts": oracle["charts"]},
        "tracking_s": round(track_s, 1),
    }
    write_result(args.name, figures, directory=args.out, model=info)


def linear_bound(model: Any, mm: MeasurementModel, mu: np.ndarray, design: ChartDesign,
                 args: argparse.Namespace, sizes: tuple[float, ...] = (2.0, 2.5, 3.0)
                 ) -> dict[str, Any]:
    """What the curves allow (:mod:`formtwin.monitoring.bound`): the steady Kalman filter of
    the metamodel linearised at the line's mean (secant over +-0.5 sigma: the metamodel
    evaluates in float32, too coarse for small differences) with the benchmark's noise
    ``N(0, Sigma)``, for the machine parameters at mid-range and ``--bound-draws - 1``
    uniform draws; per state variable the share of a step its estimate shows after 30
    products, the expected GLR statistic after 30 products on the estimate's own residual
    and on all the innovations, and the delays of the GLR matched to the exact signature at
    the design's ``arl0_glr`` (500 simulated changes per variable and draw), for steps of
    ``sizes`` sigma."""
    spec = model.spec
    st, lo, hi = spec.state, spec.inputs.lo, spec.inputs.hi
    rng = np.random.default_rng(args.seed + 11)
    filters = []
    for draw in range(args.bound_draws):
        x0 = 0.5 * (lo + hi) if draw == 0 else lo + (hi - lo) * rng.random(lo.size)
        x0[: len(st)] = mu
        jac = curve_jacobian(model, x0, 0.5 * st.sigma)
        filters.append(steady_filter(jac, mm.covariance(), st.rho, st.sigma))
    out: dict[str, Any] = {"arl0_glr": design.arl0_glr, "draws": args.bound_draws}
    for size in sizes:
        per: dict[str, Any] = {}
        pooled = []
        for j, name in enumerate(st.names):
            resp = [step_in_filter(f, j, size * float(st.sigma[j]), design.glr_window)
                    for f in filters]
            d = np.concatenate([glr_delays(r.own, design.arl0_glr, design.glr_window,
                                           runs=500, horizon=args.after, seed=k)
                                for k, r in enumerate(resp)])
            pooled.append(d)
            per[name] = {**summary(list(d), args.after),
                         "share_lag30": round(float(np.mean([r.share[29] for r in resp])), 3),
                         "expected_glr_30": round(float(np.mean(
                             [r.expected_glr(30) for r in resp])), 2),
                         "expected_glr_30_all_innovations": round(float(np.mean(
                             [r.expected_glr(30, full=True) for r in resp])), 2)}
        out[f"step_{size}sigma"] = {**summary(list(np.concatenate(pooled)), args.after),
                                    "per_variable": per}
        print(f"linear-Gaussian bound, {size}-sigma step: median delay "
              f"{out[f'step_{size}sigma']['median']}, within 30 "
              f"{out[f'step_{size}sigma']['within_30_share']}")
    return out


def what_a_step_leaves(config: MonitorConfig, est: list[np.ndarray], true: list[np.ndarray],
                       mu: float, sigma: float, name: str, design: ChartDesign
                       ) -> dict[str, Any]:
    """How the estimates of state ``name`` respond to a step of the state, from the
    calibration runs (:func:`~formtwin.monitoring.glr.step_response`): the share of the
    step they show after 0, 5, 30 products; and for a 2-sigma step the expected GLR
    statistic at the change's true time after 10 and 30 products (half the noncentrality,
    ``sum_j s_j^2 / 2``, residual sigma units) and the products until it reaches the
    chart's limit ``h`` (``None``: not within the window)."""
    w = design.warmup
    g = step_response([e[w:] for e in est], [t[w:] for t in true], mu, mu, design.glr_window)
    q = config.quantities[name]
    llr = np.cumsum((residual_response(g, q.phi) * 2.0 * sigma / q.sigma) ** 2) / 2.0
    h = config.glr[name].h * config.widen.get(name, {}).get("glr", 1.0) if name in config.glr \
        else float("nan")
    reach = np.nonzero(llr >= h)[0]
    return {"share_of_step_lag0": round(float(g[0]), 3), "lag5": round(float(g[5]), 3),
            "lag30": round(float(g[30]), 3),
            "expected_glr_10": round(float(llr[9]), 2), "expected_glr_30": round(float(llr[29]), 2),
            "glr_h": round(h, 2),
            "products_to_reach_h": int(reach[0]) + 1 if reach.size else None}


def evaluate(config: MonitorConfig, ic_runs: list[Series],
             scenarios: dict[str, list[tuple[Change, Series]]], names: tuple[str, ...],
             args: argparse.Namespace) -> dict[str, Any]:
    """False alarms on ``ic_runs`` and delays on the changed runs of ``config``'s charts."""
    d = config.warmup + config.phase1
    ic_alarms = [a for s in ic_runs for a in chart(config, s)]
    ic_episodes = [e for s in ic_runs for e in episodes(config, s)]
    charted = len(ic_runs) * (args.ic_products - d)
    n = args.at + args.after
    results: dict[str, list[tuple[int, int, str]]] = {
        k: [delay(chart(config, s), ch.at, n) for ch, s in v] for k, v in scenarios.items()}
    false_changes = sum(f for v in results.values() for _, f, _ in v)

    def block(kind: str) -> dict[str, Any]:
        per = {name: [d for d, _, _ in results[f"{kind}:{name}"]] for name in names}
        return {**summary([d for v in per.values() for d in v], args.after),
                "per_variable": {k: summary(v, args.after) for k, v in per.items()},
                "first_alarm": {name: [v for _, _, v in results[f"{kind}:{name}"]]
                                for name in names}}

    by_chart: dict[str, int] = {}
    for a in ic_alarms:
        by_chart[f"{a.variable}/{a.chart}"] = by_chart.get(f"{a.variable}/{a.chart}", 0) + 1
    lo, hi = poisson_interval(len(ic_alarms))
    cusums = list(config.quantities) if config.cusum_on is None else config.cusum_on
    return {
        "false_alarms_per_10k_products": round(len(ic_alarms) / charted * 1e4, 3),
        "false_alarms_per_10k_products_95ci": [round(lo / charted * 1e4, 3),
                                               round(hi / charted * 1e4, 3)],
        "false_alarms_in_control": len(ic_alarms),
        "charted_products_in_control": charted,
        "false_alarms_by_chart": by_chart,
        "false_alarm_episodes_per_10k_products": round(len(ic_episodes) / charted * 1e4, 3),
        "false_alarm_episodes_in_control": len(ic_episodes),
        "false_alarms_before_changes": false_changes,
        "step_2sigma": block("step"),
        f"drift_{args.drift}sigma_per_product": block("drift"),
        f"batch_{args.batch}sigma": {
            **summary([d for d, _, _ in results["batch"]], args.after),
            "first_alarm": [v for _, _, v in results["batch"]]},
        "charts": {
            "charts": {"ewma": len(config.quantities), "cusum": len(cusums),
                       "glr": len(config.glr),
                       "shewhart": len(cusums) * (config.shewhart is not None),
                       "mismatch": len(config.health)},
            "ewma_L": round(config.ewma.L, 4), "cusum_h": round(config.cusum.h, 4),
            "mismatch_h": round(config.mismatch.h, 4),
            "glr_h": {k: round(g.h, 3) for k, g in config.glr.items()},
            "glr_signature": {k: [round(v, 4) for v in g.signature]
                              for k, g in config.glr.items()},
            "shewhart_limit": config.shewhart,
            "clear_after": clear_after(Monitor(config)),
            "widen": {k: {c: round(f, 3) for c, f in w.items()}
                      for k, w in config.widen.items()}},
    }


if __name__ == "__main__":
    main()
