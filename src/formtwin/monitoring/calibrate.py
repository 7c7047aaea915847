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

Limits: every chart is designed for the same in-control ARL of its standardised residual,
``arl0_per_chart``. With ``c`` charts the whole monitor then raises about ``c / arl0`` false
alarms per product, if the residuals are as Gaussian and independent as assumed; the
benchmark (``benchmarks/bench_monitoring.py``) counts the real rate.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from formtwin.estimates import Estimates
from formtwin.measurement import MeasurementModel, ProcessModel
from formtwin.monitoring.charts import Cusum, Ewma, cusum_h, ewma_L
from formtwin.monitoring.incontrol import InControl, Reference, fit_in_control
from formtwin.monitoring.monitor import ANGLES, HEALTH, MonitorConfig
from formtwin.tracker import Tracker, TrackerConfig

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class ChartDesign:
    """Chart parameters; limits follow from ``arl0_per_chart``.

    Attributes
    ----------
    lam : EWMA smoothing.
    k : CUSUM reference value (sigma units of the residual: half the residual shift it is
        tuned for).
    k_mismatch : reference of the one-sided mismatch CUSUM on the health scores.
    arl0_per_chart : in-control ARL of each chart (two-sided ones counted two-sided).
    order : AR order of the in-control models.
    tails : standardise residuals through their in-control distribution (heavy tails).
    health_ar : chart the health scores' AR residuals (they are autocorrelated) instead of
        the scores.
    health_phase1 : the scores' level from Phase I (it depends on the machine parameters,
        but the first products are still the filter's transient) instead of the pooled
        in-control level.
    warmup, phase1 : see :class:`~formtwin.monitoring.monitor.MonitorConfig`.
    """

    lam: float = 0.2
    k: float = 1.0
    k_mismatch: float = 1.0
    arl0_per_chart: float = 1.0e6
    order: int = 2
    tails: bool = True
    health_ar: bool = True
    health_phase1: bool = False
    warmup: int = 50
    phase1: int = 100

    def charts(self) -> tuple[Ewma, Cusum, Cusum]:
        """EWMA, CUSUM and mismatch CUSUM with their limits."""
        a = self.arl0_per_chart
        return (Ewma(self.lam, ewma_L(self.lam, a)), Cusum(self.k, cusum_h(self.k, a)),
                Cusum(self.k_mismatch, cusum_h(self.k_mismatch, a, two_sided=False), "high"))


def simulate_in_control(model: ProcessModel, measurement: MeasurementModel,
                        config: TrackerConfig, n: int, runs: int, seed: int
                        ) -> list[Estimates]:
    """Estimates of ``runs`` simulated in-control runs of ``n`` products, each drawn as the
    tracker assumes the process (:meth:`~formtwin.tracker.BendingSSM.simulate`: the
    config's mu, sigma, rho; machine parameters uniform in their bounds) and tracked with
    ``config`` (its seed varied per run)."""
    out = []
    for r, ss in enumerate(np.random.SeedSequence(seed).spawn(runs)):
        tracker = Tracker(model, measurement, replace(config, seed=config.seed + 1000 + r))
        _, curves = tracker.ssm.simulate(n, np.random.default_rng(ss))
        out.append(tracker.run(curves))
    return out


def series(est: Estimates) -> dict[str, FloatArray]:
    """The monitored values of a run by name, each (n,)."""
    out = {n: est.mean[:, j] for j, n in enumerate(est.names)}
    out.update({a: est.angles_mean[:, j] for j, a in enumerate(ANGLES)})
    out.update(loglik=est.loglik, ess=est.ess)
    if est.fit_log10_p is not None:
        out["fit"] = est.fit_log10_p
    return out


def calibrate(runs: Sequence[Estimates], state_names: Sequence[str], mu: FloatArray,
              design: ChartDesign | None = None) -> MonitorConfig:
    """A monitor for a line whose state means are ``mu`` (7,), from in-control ``runs``
    (see :func:`calibrate_series`)."""
    return calibrate_series([series(r) for r in runs], state_names, mu, design)


def calibrate_series(runs: Sequence[Mapping[str, FloatArray]], state_names: Sequence[str],
                     mu: FloatArray, design: ChartDesign | None = None) -> MonitorConfig:
    """A monitor for a line whose state means are ``mu`` (7,), from the :func:`series` of
    in-control runs.

    State variables get an AR model about ``mu`` (the in-control mean is the spec's or the
    user's); the angles about a Phase-I level; the health statistics a reference from the
    runs. The first ``design.warmup`` products of each run are left out.
    """
    d = ChartDesign() if design is None else design
    if d.phase1 < 2:
        raise ValueError(f"phase1 = {d.phase1}: the angles' level needs phase1 >= 2")
    values = [{k: np.asarray(v)[d.warmup:] for k, v in r.items()} for r in runs]
    quantities: dict[str, InControl] = {}
    for j, name in enumerate(state_names):
        quantities[name] = fit_in_control([v[name] for v in values], d.order,
                                          mean=float(mu[j]), tails=d.tails)
    for name in ANGLES:
        quantities[name] = fit_in_control([v[name] for v in values], d.order, mean=None,
                                          keep_mean=False, tails=d.tails)
    pooled = {name: np.concatenate([v[name] for v in values]) for name in HEALTH
              if all(name in v for v in values)}
    health = {name: Reference(tuple(pooled[name]), bad) for name, bad in HEALTH.items()
              if name in pooled and np.isfinite(pooled[name]).sum() >= 20}
    models = {}
    if d.health_ar:  # the scores' level depends on the run (machine parameters): Phase I
        for name, ref in health.items():
            scores = [np.array([ref.normal_score(float(x)) for x in v[name]]) for v in values]
            models[name] = fit_in_control(scores, d.order, mean=None,
                                          keep_mean=not d.health_phase1, tails=d.tails)
    ewma, cusum, mismatch = d.charts()
    return MonitorConfig(quantities, health, models, ewma, cusum, mismatch, d.warmup,
                         d.phase1)


__all__ = ["ChartDesign", "calibrate", "calibrate_series", "series", "simulate_in_control"]
