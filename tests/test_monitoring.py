"""Monitoring: chart statistics against closed forms and published run lengths, in-control
models, state restore, and a step in a state mean detected through the tracker."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from formtwin.defaults import AnalyticModel
from formtwin.measurement import MeasurementModel
from formtwin.monitoring.calibrate import (
    ChartDesign,
    calibrate,
    in_control_runs,
    measurement_noise,
    series,
    simulate_in_control,
    widen,
)
from formtwin.monitoring.charts import (
    Cusum,
    CusumState,
    Ewma,
    EwmaState,
    cusum_arl_siegmund,
    cusum_arl_two_sided,
    cusum_h,
    ewma_arl,
    ewma_L,
    ewma_limit,
)
from formtwin.monitoring.glr import level_signature
from formtwin.monitoring.incontrol import InControl, Reference, fit_in_control
from formtwin.monitoring.monitor import Alarm, Monitor, MonitorConfig
from formtwin.monitoring.scenarios import Change, Fault, changed_run
from formtwin.spec import ProcessSpec
from formtwin.tracker import Tracker, TrackerConfig


# ----------------------------------------------------------------------------- EWMA
def test_ewma_limits_are_the_closed_form_and_match_the_spread_of_the_statistic() -> None:
    lam, reps, steps = 0.2, 4000, 25
    chart = Ewma(lam, L=50.0)  # wide: never signals; limit / L = std of Z_i
    rng = np.random.default_rng(11)
    z = np.empty((reps, steps))
    limits = np.empty(steps)
    for r in range(reps):
        s = EwmaState()
        for i, x in enumerate(rng.standard_normal(steps)):
            s, sig = chart.update(s, float(x))
            z[r, i], limits[i] = sig.statistic, sig.limit / chart.L
    i = np.arange(1, steps + 1)
    closed = np.sqrt(lam / (2 - lam) * (1 - (1 - lam) ** (2 * i)))  # Montgomery eq. 9.25
    np.testing.assert_allclose(limits, closed, rtol=1e-12)
    assert limits[0] == pytest.approx(lam)  # first limit: L lam
    assert ewma_limit(10_000, lam, 3.0) == pytest.approx(3 * math.sqrt(lam / (2 - lam)))
    # empirical std of Z_i over 4000 replications (relative s.e. ~1.1 %): within 5 %
    np.testing.assert_allclose(z.std(axis=0), closed, rtol=0.05)


def test_ewma_arl_markov_chain_reproduces_lucas_saccucci() -> None:
    # Lucas & Saccucci (1990), Table 3: lam = 0.10, L = 2.814 -> ARL 500 in control,
    # 10.3 for a 1-sigma shift; lam = 0.05, L = 2.615 -> 500
    assert ewma_arl(0.10, 2.814) == pytest.approx(500, rel=0.01)
    assert ewma_arl(0.10, 2.814, shift=1.0) == pytest.approx(10.3, abs=0.1)
    assert ewma_arl(0.05, 2.615) == pytest.approx(500, rel=0.01)
    assert ewma_L(0.10, 500.0) == pytest.approx(2.814, abs=0.003)


# ----------------------------------------------------------------------------- CUSUM
def _run_lengths(chart: Cusum, n: int, rng: np.random.Generator, shift: float = 0.0
                 ) -> np.ndarray:
    out = np.empty(n)
    for r in range(n):
        s, t = CusumState(), 0
        while True:
            t += 1
            s, sig = chart.update(s, shift + float(rng.standard_normal()))
            if sig.side:
                out[r] = t
                break
    return out


def test_cusum_arl_on_iid_normal_data_matches_siegmund() -> None:
    """One-sided CUSUM k = 0.5, h = 4: Siegmund's approximation 338.1 (Montgomery's table
    of exact values: 336). 1500 run lengths (their std is about their mean, so the
    estimate's relative s.e. is ~2.6 %); tolerance 10 % (about 4 s.e., plus the ~1 % error
    of the approximation). Seeded."""
    expected = cusum_arl_siegmund(0.5, 4.0)
    assert expected == pytest.approx(338.1, abs=0.1)
    rl = _run_lengths(Cusum(0.5, 4.0, sides="high"), 1500, np.random.default_rng(5))
    assert rl.mean() == pytest.approx(expected, rel=0.10)
    # a 1-sigma shift: Siegmund 8.38 (table: 8.38); run lengths vary little, 5 %
    rl1 = _run_lengths(Cusum(0.5, 4.0, sides="high"), 1500, np.random.default_rng(6), 1.0)
    assert rl1.mean() == pytest.approx(cusum_arl_siegmund(0.5, 4.0, 1.0), rel=0.05)


def test_two_sided_cusum_halves_the_arl_and_h_inverts_it() -> None:
    assert cusum_arl_two_sided(0.5, 5.0) == pytest.approx(cusum_arl_siegmund(0.5, 5.0) / 2)
    assert cusum_arl_two_sided(0.5, 5.0) == pytest.approx(465, rel=0.02)  # Montgomery
    h = cusum_h(1.0, 1e5)
    assert cusum_arl_two_sided(1.0, h) == pytest.approx(1e5, rel=1e-6)
    rl = _run_lengths(Cusum(0.5, 5.0), 400, np.random.default_rng(8))
    assert rl.mean() == pytest.approx(469, rel=0.15)  # 400 runs: s.e. 5 %, 3 s.e.


def test_cusum_h_for_a_large_reference_value() -> None:
    """k = 2.5 (a mismatch CUSUM that sees only large shifts): no overflow in Siegmund's
    formula while h is searched, and h inverts the ARL."""
    h = cusum_h(2.5, 1e7, two_sided=False)
    assert cusum_arl_siegmund(2.5, h) == pytest.approx(1e7, rel=1e-6)


def test_chart_parameters_are_checked() -> None:
    with pytest.raises(ValueError, match="lam"):
        Ewma(lam=0.0)
    with pytest.raises(ValueError, match="sides"):
        Cusum(sides="up")
    with pytest.raises(ValueError, match="sigma"):
        InControl(mean=0.0, sigma=0.0)


# ----------------------------------------------------------------- in-control models
def test_ar2_fit_recovers_the_coefficients_and_whitens() -> None:
    rng = np.random.default_rng(3)
    e = rng.standard_normal(30_000)
    y = np.zeros_like(e)
    for i in range(2, e.size):
        y[i] = 1.1 * y[i - 1] - 0.2 * y[i - 2] + 0.5 * e[i]
    ic = fit_in_control([10.0 + y[:15_000], 10.0 + y[15_000:]], order=2, mean=10.0)
    assert ic.phi == pytest.approx((1.1, -0.2), abs=0.02)
    assert ic.sigma == pytest.approx(0.5, rel=0.02)
    z = [ic.score(10.0 + y[i], list(10.0 + y[i - 2:i]), 10.0) for i in range(2, 2000)]
    assert np.std(z) == pytest.approx(1.0, abs=0.05)
    assert abs(np.corrcoef(z[1:], z[:-1])[0, 1]) < 0.06


def test_reference_normal_scores() -> None:
    ref = Reference(tuple(np.linspace(0.0, 1.0, 1001)), bad="low")
    assert ref.normal_score(0.5) == pytest.approx(0.0, abs=0.01)
    assert ref.normal_score(0.1) == pytest.approx(1.2816, abs=0.01)  # low is bad
    worst = ref.normal_score(-5.0)
    assert worst == ref.normal_score(float("nan")) == ref.normal_score(-math.inf)
    assert worst == pytest.approx(3.29, abs=0.01)  # clipped at 1 - 1/(2n)
    assert Reference(ref.sample, bad="high").normal_score(0.9) == pytest.approx(1.2816,
                                                                               abs=0.01)


def test_heavy_tailed_residuals_get_normal_scores() -> None:
    """Student-t (3 dof) residuals: through their in-control quantiles (fit_in_control with
    tails) fresh residuals score N(0, 1), with the Gaussian tail share beyond 3.09; the raw
    standardised residual would put 5x too many there."""
    rng = np.random.default_rng(4)
    ic = fit_in_control([rng.standard_t(3, 40_000)], order=0, mean=0.0, tails=True,
                        n_quantiles=2000)
    assert len(ic.quantiles) == 2000
    fresh = rng.standard_t(3, 40_000)
    z = np.array([ic.score(float(v), [], 0.0) for v in fresh])
    assert z.mean() == pytest.approx(0.0, abs=0.03) and z.std() == pytest.approx(1.0, abs=0.05)
    assert np.mean(z > 3.09) == pytest.approx(0.001, abs=0.0006)
    raw = fresh / ic.sigma
    assert np.mean(raw > 3.09) > 4 * 0.001
    assert ic.score(1e3, [], 0.0) > ic.score(1e2, [], 0.0) > 3.0  # large stays large
    assert InControl.from_dict(json.loads(json.dumps(ic.to_dict()))) == ic


# ------------------------------------------------------------------------ monitor
def _toy_config() -> MonitorConfig:
    q = {"a": InControl(mean=1.0, sigma=0.5, phi=(0.6,)), "b": InControl(mean=None, sigma=2.0)}
    return MonitorConfig(q, {"ess": Reference(tuple(range(1, 101)), "low")},
                         {"ess": InControl(mean=None, sigma=0.9, phi=(0.3,))},
                         Ewma(0.2, 2.5), Cusum(0.5, 3.0), Cusum(0.5, 3.0, "high"),
                         warmup=3, phase1=5)


def _toy_values(n: int) -> list[dict[str, float]]:
    rng = np.random.default_rng(1)
    return [{"a": 1.0 + 0.8 * rng.standard_normal(), "b": 7.0 + 2.0 * rng.standard_normal(),
             "ess": float(rng.integers(1, 100))} for _ in range(n)]


def test_monitor_restored_from_its_json_state_continues_identically() -> None:
    config, values = _toy_config(), _toy_values(300)
    whole = Monitor(config)
    a_whole = [a for i, v in enumerate(values) for a in whole.update_values(v, i)]
    assert len(a_whole) > 3  # the toy stream is out of control for "a": alarms to compare
    first = Monitor(config)
    a_first = [a for i, v in enumerate(values[:137]) for a in first.update_values(v, i)]
    config2 = MonitorConfig.from_json(config.to_json())
    second = Monitor(config2, json.loads(json.dumps(first.state())))
    a_second = [a for i, v in enumerate(values[137:], 137) for a in second.update_values(v, i)]
    assert a_first + a_second == a_whole
    assert second.state() == whole.state()
    assert whole.means["b"] == pytest.approx(np.mean([v["b"] for v in values[3:8]]))


def test_shewhart_limit_and_cusum_only_on_the_named_quantities() -> None:
    """A combined Shewhart-CUSUM on "a" only: one residual beyond the limit alarms at once
    (chart "shewhart"); "b" has its EWMA alone; the config survives JSON."""
    base = _toy_config()
    config = MonitorConfig(base.quantities, base.health, base.health_models, Ewma(0.2, 50.0),
                           Cusum(0.5, 50.0), base.mismatch, warmup=0, phase1=2,
                           cusum_on=("a",), shewhart=4.0)
    assert MonitorConfig.from_json(config.to_json()) == config
    mon = Monitor(config)
    quiet = {"a": 1.0, "b": 7.0, "ess": 50.0}
    for _ in range(4):
        assert mon.update_values(quiet) == ()
    assert set(mon.last["a"]) == {"ewma", "cusum", "shewhart"} and set(mon.last["b"]) == {"ewma"}
    (alarm,) = mon.update_values({**quiet, "a": 1.0 + 0.5 * 4.2})  # z = 4.2 > 4
    assert (alarm.variable, alarm.chart, alarm.side) == ("a", "shewhart", "high")
    assert alarm.statistic == pytest.approx(4.2)
    with pytest.raises(ValueError, match="cusum_on"):
        MonitorConfig(base.quantities, cusum_on=("zzz",))


def test_widen_lifts_limits_until_the_calibration_runs_stay_inside() -> None:
    """A calibration run where "a" leaves its in-control level for 40 products (an
    excursion that lasts, as when the filter loses its particles): the Gaussian design
    alarms on it; widen() raises the limits of a's charts until the run stays a margin
    inside them, and leaves the quiet quantity "b" alone."""
    q = {"a": InControl(mean=1.0, sigma=0.5), "b": InControl(mean=7.0, sigma=2.0)}
    config = MonitorConfig(q, ewma=Ewma(0.2, 3.5), cusum=Cusum(0.5, 8.0), warmup=0, phase1=0)
    rng = np.random.default_rng(12)
    a = 1.0 + 0.5 * rng.standard_normal(400)
    a[200:240] += 1.5
    run = {"a": a, "b": 7.0 + 2.0 * rng.standard_normal(400)}
    assert _alarms(config, run)
    wide = widen(config, [run], margin=1.2)
    assert min(wide.widen["a"].values()) > 1.2 and "b" not in wide.widen
    assert _alarms(wide, run) == []
    mon = Monitor(wide)
    worst = 0.0
    for i in range(400):
        mon.update_values({k: float(v[i]) for k, v in run.items()})
        worst = max([worst, *(abs(s) / lim for s, lim in mon.last.get("a", {}).values())])
    assert worst <= 1.0 / 1.2 + 1e-9
    assert MonitorConfig.from_json(wide.to_json()) == wide


def _alarms(config: MonitorConfig, run: dict[str, np.ndarray]) -> list[Alarm]:
    mon = Monitor(config)
    n = len(run["a"])
    return [a for i in range(n) for a in mon.update_values({k: float(v[i])
                                                            for k, v in run.items()})]


def test_measurement_noise_has_the_likelihood_covariance(spec: ProcessSpec,
                                                        model: AnalyticModel) -> None:
    mm = MeasurementModel.from_monte_carlo(model, mu=spec.state.mu_mid, n=2000,
                                           rng=np.random.default_rng(2))
    draws = measurement_noise(mm, 40_000, np.random.default_rng(3))
    cov = mm.covariance()
    # sample covariance of 40 000 draws: s.e. of an entry ~ sqrt(2 / 40 000) of its scale
    scale = np.sqrt(np.outer(np.diag(cov), np.diag(cov)))
    assert np.max(np.abs(np.cov(draws.T) - cov) / scale) < 0.04


def test_monitor_rejects_missing_values_and_foreign_state() -> None:
    mon = Monitor(_toy_config())
    with pytest.raises(ValueError, match="lack"):
        mon.update_values({"a": 1.0})
    st = mon.state()
    st["history"] = {"zzz": []}
    with pytest.raises(ValueError, match="watches"):
        Monitor(_toy_config(), st)


# ------------------------------------------------- step scenario through the tracker
@pytest.fixture(scope="module")
def line(spec: ProcessSpec, model: AnalyticModel
         ) -> tuple[AnalyticModel, MeasurementModel, TrackerConfig]:
    mm = MeasurementModel.from_monte_carlo(model, mu=spec.state.mu_mid, n=3000,
                                           rng=np.random.default_rng(0))
    cfg = TrackerConfig(n_particles=200, estimate_deviation=False,
                        mu=tuple(spec.state.mu_mid), seed=1)
    return model, mm, cfg


@pytest.fixture(scope="module")
def line_config(spec: ProcessSpec, line: tuple[AnalyticModel, MeasurementModel, TrackerConfig]
                ) -> MonitorConfig:
    """A monitor calibrated on 2 simulated in-control runs of 600 products (seed 5, warm-up
    30, Phase I 50) of ``line``; made once for the tests that watch a changed run with it."""
    model, mm, cfg = line
    return calibrate(simulate_in_control(model, mm, cfg, 600, 2, seed=5),
                     spec.state.names, spec.state.mu_mid, ChartDesign(warmup=30, phase1=50))


def test_step_in_a_state_mean_is_detected(spec: ProcessSpec, line: tuple[
        AnalyticModel, MeasurementModel, TrackerConfig], line_config: MonitorConfig) -> None:
    """Analytic stand-in, N = 200: a monitor calibrated on 2 simulated in-control runs
    (default design) sees a 3-sigma step in the punch end distance (the best observed
    state) within 30 products, and raises no alarm on the same run before the step. (A
    2-sigma step is borderline on this one run: the CUSUM reaches 5.4 of its 5.6 for an
    ARL0 of 2e5; benchmarks/bench_monitoring.py measures 2-sigma steps over many runs.)"""
    model, mm, cfg = line
    mu, config = spec.state.mu_mid, line_config
    at = 150
    change = Change("step", ("punch_end_distance",), at=at, size=3.0)
    rng = np.random.default_rng(77)
    run = changed_run(spec, at + 60, mu, rng, change)
    curves = model.predict_curves(run.inputs)
    est = Tracker(model, mm, cfg).run(curves + measurement_noise(mm, len(curves), rng))
    mon, vals = Monitor(config), series(est)
    alarms = [a for i in range(len(est))
              for a in mon.update_values({k: float(v[i]) for k, v in vals.items()}, i)]
    assert [a for a in alarms if a.index < at] == []
    first = min(a.index for a in alarms)
    assert first - at + 1 <= 30
    assert any(a.variable == "punch_end_distance" and a.side == "high" for a in alarms)


def test_changed_run_draws_the_deviation_only_when_asked(spec: ProcessSpec) -> None:
    """With ``deviation`` theta_d is drawn once in its bounds (not 0) and the same states and
    change follow; without it theta_d is 0 (g = identity)."""
    mu, change = spec.state.mu_mid, Change("step", ("thickness",), at=5, size=2.0)
    plain = changed_run(spec, 10, mu, np.random.default_rng(3), change)
    dev = changed_run(spec, 10, mu, np.random.default_rng(3), change, deviation=True)
    d = spec.deviation.group
    assert np.all(plain.theta_d == 0)
    assert np.all((dev.theta_d >= d.lo) & (dev.theta_d <= d.hi)) and np.any(dev.theta_d != 0)
    j = spec.state.names.index("thickness")
    for run in (plain, dev):  # the step is there in both
        assert run.x[5:, j].mean() - run.x[:5, j].mean() > spec.state.sigma[j]


def test_fault_changes_the_measured_curves_from_its_product_on() -> None:
    """A sensor fault leaves the curves before ``at`` alone and maps them exactly to
    ``(1 + gain) y + offset`` after; an impossible gain or a negative ``at`` is refused."""
    y = np.random.default_rng(1).normal(100.0, 10.0, (6, 4))
    out = Fault(at=2, gain=-0.1, offset=2.0).apply(y)
    np.testing.assert_array_equal(out[:2], y[:2])
    np.testing.assert_allclose(out[2:], 0.9 * y[2:] + 2.0)
    for bad in ({"at": -1}, {"at": 0, "gain": -1.0}):
        with pytest.raises(ValueError, match="fault"):
            Fault(**bad)  # type: ignore[arg-type]


def test_model_mismatch_raises_the_mismatch_alarm(spec: ProcessSpec, line: tuple[
        AnalyticModel, MeasurementModel, TrackerConfig], line_config: MonitorConfig) -> None:
    """Curves 10 % stronger than any the model makes from product 150 on (a deviation the
    tracker does not estimate): the health charts (log-evidence, ESS, absolute fit) raise a
    mismatch alarm within 10 products, and none before."""
    model, mm, cfg = line
    mu, config = spec.state.mu_mid, line_config
    assert set(config.health) == {"loglik", "ess", "fit"}
    at = 150
    rng = np.random.default_rng(78)
    run = changed_run(spec, at + 30, mu, rng, Change("none"))
    curves = model.predict_curves(run.inputs)
    curves = curves + measurement_noise(mm, len(curves), rng)
    curves[at:] *= 1.10
    est = Tracker(model, mm, cfg).run(curves)
    mon, vals = Monitor(config), series(est)
    alarms = [a for i in range(len(est))
              for a in mon.update_values({k: float(v[i]) for k, v in vals.items()}, i)]
    mismatch = [a for a in alarms if a.chart == "mismatch"]
    assert [a for a in alarms if a.index < at] == []
    assert mismatch and mismatch[0].index - at + 1 <= 10


def test_in_control_runs_give_the_same_draws_with_their_true_states(
        spec: ProcessSpec, line: tuple[AnalyticModel, MeasurementModel, TrackerConfig]) -> None:
    """in_control_runs is simulate_in_control with the true states: the same estimates, and
    states that stay in the design box and that the best observed estimate follows; a
    monitor calibrated with them matches each GLR chart to the estimates' response (not
    the level signature)."""
    model, mm, cfg = line
    est = simulate_in_control(model, mm, cfg, 300, 2, seed=9)
    runs = in_control_runs(model, mm, cfg, 300, 2, seed=9)
    names = spec.state.names
    for e, (x, e2) in zip(est, runs, strict=True):
        assert np.array_equal(e.mean, e2.mean) and x.shape == (300, len(names))
        assert np.all((x >= spec.state.lo) & (x <= spec.state.hi))
        j = names.index("punch_end_distance")
        assert np.corrcoef(x[50:, j], e.mean[50:, j])[0, 1] > 0.8
    design = ChartDesign(warmup=30, phase1=50, widen_margin=None)
    with_x = calibrate(est, names, spec.state.mu_mid, design, truths=[x for x, _ in runs])
    without = calibrate(est, names, spec.state.mu_mid, design)
    assert set(with_x.glr) == set(without.glr) == set(names)
    for n in names:
        assert without.glr[n].signature == level_signature(without.quantities[n].phi)
        assert len(with_x.glr[n].signature) > len(without.glr[n].signature)
        assert with_x.glr[n].signature != without.glr[n].signature


def _health_line(per_line: bool, level: float, drop_at: int, n: int = 1500,
                 seed: int = 3) -> tuple[list[Alarm], Monitor]:
    """A line whose ESS is N(level, 1) (pooled calibration lines: N(10, 1)), 3 lower from
    ``drop_at`` on, on a mismatch CUSUM (k 1, ARL0 1e7) with warm-up 20 and Phase I 100."""
    rng = np.random.default_rng(seed)
    pooled = Reference(tuple(10.0 + rng.standard_normal(5000)), "low")
    config = MonitorConfig({}, {"ess": pooled}, warmup=20, phase1=100,
                           mismatch=Cusum(1.0, cusum_h(1.0, 1e7, two_sided=False), "high"),
                           health_per_line=per_line)
    ess = level + rng.standard_normal(n) - 3.0 * (np.arange(n) >= drop_at)
    mon = Monitor(config)
    return [a for i, v in enumerate(ess) for a in mon.update_values({"ess": float(v)}, i)], mon


def test_health_references_from_the_lines_own_phase1() -> None:
    """A line whose filter health sits lower than every calibration line's (as the ESS with
    the deviation estimated, docs/explanation/monitoring.md): against the pooled reference the
    mismatch
    chart alarms as soon as it charts; against the line's own Phase-I values (frozen at its
    end) it does not in 1500 products, and a drop of 3 after product 1000 is seen within 10
    products, but not within 4: a reference of 100 values caps a score at
    Phi^-1(1 - 1/200) = 2.58, so the CUSUM (k 1) climbs at most 1.58 per product to its
    limit 7.24 (the pooled reference's 5000 values would allow 3.7). The other price: a
    drop inside Phase I is learned as the line's normal and never signalled."""
    pooled, _ = _health_line(False, 6.0, 10**9)
    assert pooled and pooled[0].index <= 125
    clean, mon = _health_line(True, 6.0, 10**9)
    assert clean == []
    assert len(mon.phase1_health["ess"]) == 100
    assert mon.references["ess"].sample[0] < 6.0 < mon.references["ess"].sample[-1]
    drop, _ = _health_line(True, 6.0, 1000)
    h = cusum_h(1.0, 1e7, two_sided=False)
    assert math.ceil(h / (2.5758 - 1.0)) == 5
    assert drop and 1004 <= drop[0].index <= 1009 and drop[0].chart == "mismatch"
    inside, _ = _health_line(True, 6.0, 60)  # from product 60: Phase I is products 20-119
    assert [a for a in inside if a.index >= 120] == []


def test_per_line_monitor_restored_mid_phase1_continues_identically() -> None:
    """The line's Phase-I health values are in the monitor's state: a monitor restored in
    Phase I or after it continues bit for bit (the references rebuilt from them)."""
    _, whole = _health_line(True, 6.0, 1000)
    rng = np.random.default_rng(3)
    pooled = Reference(tuple(10.0 + rng.standard_normal(5000)), "low")
    ess = 6.0 + rng.standard_normal(1500) - 3.0 * (np.arange(1500) >= 1000)
    config = whole.config
    assert MonitorConfig.from_json(config.to_json()).health_per_line
    assert whole.config.health["ess"] == pooled
    for cut in (80, 400):
        first = Monitor(config)
        a = [x for i, v in enumerate(ess[:cut]) for x in first.update_values({"ess": v}, i)]
        second = Monitor(MonitorConfig.from_json(config.to_json()),
                         json.loads(json.dumps(first.state())))
        a += [x for i, v in enumerate(ess[cut:], cut)
              for x in second.update_values({"ess": float(v)}, i)]
        assert a == _health_line(True, 6.0, 1000)[0]
        assert second.state() == whole.state()


def test_per_line_health_needs_the_scores_level() -> None:
    """With per-line references the health scores exist only after Phase I, so their AR
    models cannot take their level from it."""
    ref = Reference(tuple(np.linspace(0.0, 1.0, 50)), "low")
    with pytest.raises(ValueError, match="health_per_line"):
        MonitorConfig({}, {"ess": ref}, {"ess": InControl(None, 1.0, (0.5,))},
                      health_per_line=True)
    with pytest.raises(ValueError, match="health_per_line and health_phase1"):
        from formtwin.monitoring.calibrate import calibrate_series
        calibrate_series([{"ess": np.ones(300)}], [], np.zeros(0),
                         ChartDesign(health_phase1=True, health_per_line=True,
                                     widen_margin=None, glr=False))
