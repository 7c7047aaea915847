"""Set a monitor up: in-control models from a simulated in-control run of the tracker, and
chart limits for a wanted in-control average run length.

The in-control spread of a *posterior mean* is not the process sigma of the spec: the filter
shrinks poorly observed variables towards their prior and adds its own Monte-Carlo noise,
and the estimates are autocorrelated. So the in-control model of every quantity is fitted to
estimates of a simulated in-control production (the same model, measurement model and
tracker settings as the line, machine parameters drawn from their bounds): an AR(p) model
about the spec's mean for state variables, about a Phase-I level for the angles (their
level depends on the machine parameters); and the health statistics' reference is their
distribution in that run.

Limits: each chart kind is designed for an in-control ARL of independent N(0, 1) scores
(:class:`ChartDesign`: the CUSUMs ``arl0_per_chart``, the EWMAs ``arl0_ewma``, the
mismatch CUSUMs ``arl0_mismatch``); the whole monitor then raises about ``sum 1 / ARL0``
false alarms per product if the scores are as Gaussian and independent as assumed. Where
charting the calibration runs shows they are not, :func:`widen` raises that chart's
limit. The benchmark (``benchmarks/bench_monitoring.py``) counts the real rate.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray
from scipy.special import ndtri

from formtwin.estimates import Estimates
from formtwin.measurement import MeasurementModel, ProcessModel
from formtwin.monitoring.charts import Cusum, Ewma, cusum_h, ewma_L
from formtwin.monitoring.glr import (
    Glr,
    glr_h,
    level_signature,
    response_signature,
    step_response,
)
from formtwin.monitoring.incontrol import InControl, Reference, fit_in_control
from formtwin.monitoring.monitor import ANGLES, HEALTH, Monitor, MonitorConfig
from formtwin.tracker import Tracker, TrackerConfig

FloatArray = NDArray[np.float64]
log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ChartDesign:
    """Chart parameters; limits follow from ``arl0_per_chart``.

    Attributes
    ----------
    lam : EWMA smoothing.
    k : CUSUM reference value (sigma units of the residual: half the residual shift it is
        tuned for; 0.5: the lasting residual shift of a 2-sigma step in a state mean is
        0.6-1.0 residual sigma, docs/explanation/monitoring.md).
    k_mismatch : reference of the one-sided mismatch CUSUM on the health scores.
    arl0_per_chart : in-control ARL of each quantity's CUSUM (two-sided), the charts that
        detect a step; the family of all charts signals about ``sum 1 / ARL0`` per product.
    arl0_ewma : in-control ARL of each quantity's EWMA (slower to see the lasting shift
        than the CUSUM, so given little of the false-alarm budget).
    arl0_mismatch : in-control ARL of each health statistic's mismatch CUSUM.
    arl0_shewhart : in-control ARL of the single-product limit on ``|z|`` that joins each
        CUSUM (combined Shewhart-CUSUM); ``None`` (default): none. (It sees the jump of a
        step at once, but the residuals' extreme tails beyond the calibration sample make
        it raise false alarms; see docs/explanation/monitoring.md.)
    order : AR order of the in-control models.
    tails : standardise residuals through their in-control distribution (heavy tails).
    health_ar : chart the health scores' AR residuals (they are autocorrelated) instead of
        the scores.
    angle_cusum : a CUSUM on the predicted angles too (their level comes from Phase I, so
        a CUSUM tuned for small shifts alarms on the Phase-I error); default: EWMA only.
    health_phase1 : the scores' level from Phase I (it depends on the machine parameters,
        but the first products are still the filter's transient) instead of the pooled
        in-control level.
    health_per_line : each line's health statistics scored against its own Phase-I values
        (frozen at its end) instead of the calibration lines' pooled sample; the scores' AR
        models are fitted on the calibration lines scored the same way (each against its
        own Phase I), about their pooled level. Off by default: on bending-2.4's held-out
        runs it raised more false alarms than the pooled references
        (docs/explanation/monitoring.md).
    health_level : the health scores' levels follow the line once charting (an EWMA with
        this weight, :attr:`~formtwin.monitoring.monitor.MonitorConfig.health_level`: 0.01,
        a time constant of 100 products; chosen on bench_monitoring's seed-2026 runs,
        docs/explanation/monitoring.md), paused from a mismatch alarm until its chart has been quiet
        for 100 products (a persistent mismatch stays signalled); ``None``: the
        calibration lines' level throughout.
    glr : a GLR chart for a level change on each state variable
        (:mod:`~formtwin.monitoring.glr`: matched to the spike-then-shift signature a step
        in the mean leaves in the AR residuals).
    arl0_glr : in-control ARL of each state variable's GLR chart.
    glr_window : the GLR's window of candidate change times (products).
    glr_clip : the GLR sees each score clipped to +-this (Huber's bounded influence): the
        particle filter's estimates jump now and then by several residual sigmas for a
        product or a few (its particles thin out), which an unclipped GLR takes for the
        jump a step makes (docs/explanation/monitoring.md); ``None``: unclipped.
    state_cusum : the CUSUM on the state variables (off: the GLR detects the step).
    widen_margin : raise a chart's limit where charting the calibration runs would have
        come closer than this factor to it (:func:`widen`); ``None``: off.
    warmup, phase1 : see :class:`~formtwin.monitoring.monitor.MonitorConfig`.
    """

    lam: float = 0.2
    k: float = 0.5
    k_mismatch: float = 1.0
    arl0_per_chart: float = 5.0e5
    arl0_ewma: float = 1.0e7
    arl0_mismatch: float = 1.0e7
    arl0_shewhart: float | None = None
    order: int = 2
    tails: bool = True
    health_ar: bool = True
    health_phase1: bool = False
    health_per_line: bool = False
    health_level: float | None = 0.01
    angle_cusum: bool = False
    glr: bool = True
    arl0_glr: float = 1.0e5
    glr_window: int = 200
    glr_clip: float | None = 3.0
    state_cusum: bool = True
    widen_margin: float | None = 1.2
    warmup: int = 50
    phase1: int = 100

    def charts(self) -> tuple[Ewma, Cusum, Cusum]:
        """EWMA, CUSUM and mismatch CUSUM with their limits."""
        return (Ewma(self.lam, ewma_L(self.lam, self.arl0_ewma)),
                Cusum(self.k, cusum_h(self.k, self.arl0_per_chart)),
                Cusum(self.k_mismatch, cusum_h(self.k_mismatch, self.arl0_mismatch,
                                               two_sided=False), "high"))


def simulate_in_control(model: ProcessModel, measurement: MeasurementModel,
                        config: TrackerConfig, n: int, runs: int, seed: int,
                        noise: bool = True) -> list[Estimates]:
    """Estimates of ``runs`` simulated in-control runs of ``n`` products, each drawn as the
    tracker assumes the process (:meth:`~formtwin.tracker.BendingSSM.simulate`: the
    config's mu, sigma, rho; machine parameters uniform in their bounds) and tracked with
    ``config`` (its seed varied per run).

    ``noise``: the curves get measurement noise as the likelihood assumes it (see
    :func:`measurement_noise`). Without it every curve fits better and the posterior means
    spread less than on real curves: charts calibrated that way alarm on ~20 % of the
    products of a real in-control stream (measured by the service).
    """
    return [est for _, est in in_control_runs(model, measurement, config, n, runs, seed, noise)]


def in_control_runs(model: ProcessModel, measurement: MeasurementModel,
                    config: TrackerConfig, n: int, runs: int, seed: int, noise: bool = True
                    ) -> list[tuple[FloatArray, Estimates]]:
    """:func:`simulate_in_control` with each run's true states (n, 7) (the same draws):
    ``(x, estimates)`` per run."""
    out = []
    for r, ss in enumerate(np.random.SeedSequence(seed).spawn(runs)):
        tracker = Tracker(model, measurement, replace(config, seed=config.seed + 1000 + r))
        rng = np.random.default_rng(ss)
        run, curves = tracker.ssm.simulate(n, rng)
        if noise:
            curves = curves + measurement_noise(measurement, curves.shape[0], rng)
        out.append((run.x, tracker.run(curves)))
    return out


def measurement_noise(measurement: MeasurementModel, n: int, rng: np.random.Generator
                      ) -> FloatArray:
    """``n`` draws (n, n_t) N of ``N(0, Sigma)``, the likelihood's covariance
    (:meth:`~formtwin.measurement.MeasurementModel.covariance`: measurement uncertainty,
    sensor noise and, for the calibrated likelihood, the metamodel's residual covariance)."""
    w, v = np.linalg.eigh(measurement.covariance())
    root = v * np.sqrt(np.clip(w, 0.0, None))  # Sigma = root @ root.T
    out: FloatArray = rng.standard_normal((n, root.shape[0])) @ root.T
    return out


def series(est: Estimates) -> dict[str, FloatArray]:
    """The monitored values of a run by name, each (n,)."""
    out = {n: est.mean[:, j] for j, n in enumerate(est.names)}
    out.update({a: est.angles_mean[:, j] for j, a in enumerate(est.output_names)})
    out.update(loglik=est.loglik, ess=est.ess)
    if est.fit_log10_p is not None:
        out["fit"] = est.fit_log10_p
    return out


def calibrate(runs: Sequence[Estimates], state_names: Sequence[str], mu: FloatArray,
              design: ChartDesign | None = None, truths: Sequence[FloatArray] | None = None
              ) -> MonitorConfig:
    """A monitor for a line whose state means are ``mu`` (7,), from in-control ``runs``
    (see :func:`calibrate_series`)."""
    outputs = runs[0].output_names if runs else ANGLES
    return calibrate_series([series(r) for r in runs], state_names, mu, design, truths,
                            outputs)


def calibrate_series(runs: Sequence[Mapping[str, FloatArray]], state_names: Sequence[str],
                     mu: FloatArray, design: ChartDesign | None = None,
                     truths: Sequence[FloatArray] | None = None,
                     outputs: Sequence[str] = ANGLES) -> MonitorConfig:
    """A monitor for a line whose state means are ``mu`` (7,), from the :func:`series` of
    in-control runs; ``outputs`` the names of the predicted outputs (``spec.output_names``).

    State variables get an AR model about ``mu`` (the in-control mean is the spec's or the
    user's); the angles about a Phase-I level; the health statistics a reference from the
    runs. The first ``design.warmup`` products of each run are left out.

    ``truths``: the runs' true states (n_r, 7) (simulated runs): each state variable's GLR
    chart is then matched to how its estimate responds to a step of the state
    (:func:`~formtwin.monitoring.glr.step_response`); without them, to a step of the
    estimate itself (:func:`~formtwin.monitoring.glr.level_signature`). A variable whose
    signature has (almost) no lasting part gets no GLR chart when the scores are clipped:
    its statistic is then bounded near ``clip^2 / 2`` and no limit has the design's ARL.
    """
    d = ChartDesign() if design is None else design
    if d.phase1 < 2:
        raise ValueError(f"phase1 = {d.phase1}: the angles' level needs phase1 >= 2")
    values = [{k: np.asarray(v)[d.warmup:] for k, v in r.items()} for r in runs]
    quantities: dict[str, InControl] = {}
    for j, name in enumerate(state_names):
        quantities[name] = fit_in_control([v[name] for v in values], d.order,
                                          mean=float(mu[j]), tails=d.tails)
    for name in (a for a in outputs if all(a in v for v in values)):
        quantities[name] = fit_in_control([v[name] for v in values], d.order, mean=None,
                                          keep_mean=False, tails=d.tails)
    pooled = {name: np.concatenate([v[name] for v in values]) for name in HEALTH
              if all(name in v for v in values)}
    health = {name: Reference(tuple(pooled[name]), bad) for name, bad in HEALTH.items()
              if name in pooled and np.isfinite(pooled[name]).sum() >= 20}
    if d.health_per_line and d.health_phase1:
        raise ValueError("health_per_line and health_phase1: the scores' level cannot come "
                         "from Phase I when Phase I sets their reference")
    models = {}
    if d.health_ar:  # the scores' level depends on the run (machine parameters): Phase I
        for name, ref in health.items():
            scores = [line_scores(v[name], ref, d.phase1) if d.health_per_line else
                      np.array([ref.normal_score(float(x)) for x in v[name]]) for v in values]
            models[name] = fit_in_control(scores, d.order, mean=None,
                                          keep_mean=not d.health_phase1, tails=d.tails)
    ewma, cusum, mismatch = d.charts()
    shewhart = (None if d.arl0_shewhart is None
                else float(ndtri(1.0 - 0.5 / d.arl0_shewhart)))
    cusum_on = [n for n in quantities if (n in state_names and d.state_cusum)
                or (n in outputs and d.angle_cusum)]
    glr = {}
    for j, n in enumerate(state_names if d.glr else ()):
        q = quantities[n]
        sig = (level_signature(q.phi) if truths is None else response_signature(step_response(
            [v[n] for v in values], [np.asarray(x)[d.warmup:, j] for x in truths],
            float(mu[j]), float(mu[j])), q.phi))
        try:
            h = glr_h(sig, d.glr_window, d.arl0_glr, d.glr_clip)
        except ValueError as exc:  # e.g. no lasting shift: clipped, the statistic is bounded
            log.info("no GLR chart for %s: %s", n, exc)
            continue
        glr[n] = Glr(sig, h, d.glr_window, d.glr_clip)
    config = MonitorConfig(quantities, health, models, ewma, cusum, mismatch, d.warmup,
                           d.phase1, tuple(cusum_on), shewhart, glr=glr,
                           health_per_line=d.health_per_line, health_level=d.health_level)
    return config if d.widen_margin is None else widen(config, runs, d.widen_margin)


def line_scores(values: FloatArray, pooled: Reference, phase1: int) -> FloatArray:
    """Normal scores of a line's health statistic after its first ``phase1`` values
    (after the warm-up), against those values as the reference (``pooled``'s orientation;
    ``pooled`` itself where they have fewer than 20 finite values), as a monitor with
    ``health_per_line`` scores them.

    >>> pooled = Reference(tuple(range(100)), "low")
    >>> z = line_scores(np.r_[np.arange(50.0), 10.0, -1.0], pooled, 50)
    >>> [round(float(v), 2) for v in z]  # 10: 0.21 of its Phase I lower; -1: below all
    [0.81, 2.33]
    """
    ref = pooled.of_line(values[:phase1])
    return np.array([ref.normal_score(float(x)) for x in values[phase1:]])


def widen(config: MonitorConfig, runs: Sequence[Mapping[str, FloatArray]], margin: float,
          rounds: int = 10) -> MonitorConfig:
    """``config`` with the limit of every chart raised (:attr:`MonitorConfig.widen`) until
    charting the in-control ``runs`` keeps its statistic below limit / ``margin`` (at most
    ``rounds`` times).

    The Gaussian design assumes independent N(0, 1) scores; an estimate's excursion that
    lasts several products (an extreme but in-control state, where the filter's particles
    thin out) breaks that, and no per-product tail model covers it. Where the simulated
    in-control runs would have crossed the design's limits, that chart's limit is raised by
    what it needed; the other charts of the quantity keep theirs (a CUSUM keeps its
    reference value ``k``, tuned to the shift it is for). Below its limit a chart's
    statistic does not depend on the limit, so the factor needed is exact; a chart that
    alarmed restarted, hiding how far it would have gone: its limit is doubled (at least)
    and the round repeated.
    """
    for _ in range(rounds):
        worst: dict[tuple[str, str], float] = {}
        for run in runs:
            mon = Monitor(config)
            n = len(next(iter(run.values())))
            for i in range(n):
                mon.update_values({k: float(v[i]) for k, v in run.items()}, i)
                for name, charts in mon.last.items():
                    for chart, (stat, lim) in charts.items():
                        key = (name, chart)
                        worst[key] = max(worst.get(key, 0.0), abs(stat) / lim)
        factors = {n: dict(d) for n, d in config.widen.items()}
        changed = False
        for (name, chart), r in worst.items():
            f = factors.get(name, {}).get(chart, 1.0)
            # below its limit the statistic's path does not depend on the limit: exact
            new = f * max(2.0, r * margin) if r > 1.0 else max(1.0, f * r * margin)
            if abs(new - f) > 1e-9 * f and (new > f or f > 1.0):
                factors.setdefault(name, {})[chart] = new
                changed = True
        if not changed:
            break
        config = replace(config, widen={n: d for n, d in factors.items() if d})
    return config


__all__ = ["ChartDesign", "calibrate", "calibrate_series", "in_control_runs", "line_scores",
           "measurement_noise", "series", "simulate_in_control", "widen"]
