"""The GLR chart for a level change of an autoregressive quantity: its statistic against the
definition, its signatures, its threshold against simulated run lengths, and in a monitor."""

from __future__ import annotations

import json

import numpy as np
import pytest

from formtwin.monitoring.calibrate import ChartDesign, calibrate_series
from formtwin.monitoring.glr import (
    Glr,
    GlrState,
    glr_h,
    glr_statistics,
    level_signature,
    response_signature,
    step_response,
)
from formtwin.monitoring.incontrol import InControl, fit_in_control
from formtwin.monitoring.monitor import Monitor, MonitorConfig


def _brute_force(sig: tuple[float, ...], window: int, z: np.ndarray) -> np.ndarray:
    """max over change times of (sum s_j z_{tau+j})^2 / (2 sum s_j^2), straight from the
    definition (no restarts)."""
    s = np.array([sig[min(j, len(sig) - 1)] for j in range(window)])
    out = []
    for n in range(z.size):
        best = 0.0
        for age in range(min(n + 1, window)):
            tau = n - age
            num = float(np.dot(s[: age + 1], z[tau: n + 1]))
            best = max(best, num * num / (2.0 * float(np.sum(s[: age + 1] ** 2))))
        out.append(best)
    return np.array(out)


def test_glr_statistic_is_the_likelihood_ratio_of_its_definition() -> None:
    rng = np.random.default_rng(3)
    sig, window = (1.0, 0.4, 0.25), 30
    z = rng.standard_normal(80)
    z[50:] += 0.8  # a change, so that large values are compared too
    ref = _brute_force(sig, window, z)
    chart, state, got = Glr(sig, h=1e9, window=window), GlrState(), []
    for v in z:
        state, s = chart.update(state, float(v))
        got.append(s.statistic)
    assert np.allclose(got, ref, rtol=1e-12)
    assert np.allclose(glr_statistics(sig, window, z[None, :])[0], ref, rtol=1e-12)
    clipped = Glr(sig, h=1e9, window=window, clip=1.5)
    state, got = GlrState(), []
    for v in z:
        state, s = clipped.update(state, float(v))
        got.append(s.statistic)
    ref_clip = _brute_force(sig, window, np.clip(z, -1.5, 1.5))
    assert np.allclose(got, ref_clip, rtol=1e-12) and not np.allclose(ref_clip, ref)
    assert np.allclose(glr_statistics(sig, window, z[None, :], clip=1.5)[0], ref_clip)


def test_glr_signals_the_side_and_restarts() -> None:
    chart = Glr((1.0, 0.5), h=8.0, window=20)
    state, sides = GlrState(), []
    for v in [0.0] * 5 + [-3.0] * 5:
        state, s = chart.update(state, v)
        sides.append(s.side)
    # n products of -3 since the (re)start: (3 + 1.5 (n - 1))^2 / (2 (1 + 0.25 (n - 1)))
    # = 4.5, 8.1: the second signals, the chart restarts and signals again two later
    assert sides == [""] * 6 + ["low", "", "low", ""] and state.i == 1


def test_level_signature_of_ar_models() -> None:
    assert level_signature((0.8,)) == pytest.approx((1.0, 0.2))
    assert level_signature((0.6, 0.3)) == pytest.approx((1.0, 0.4, 0.1))
    assert level_signature(()) == (1.0,)
    with pytest.raises(ValueError, match="signature"):
        Glr((0.0, 0.0), h=5.0)


def test_response_signature_of_an_exponentially_smoothed_state() -> None:
    """Estimates that follow the state by exponential smoothing ``y_i = (1 - a) y_{i-1} +
    a x_i`` respond to a unit step with ``g_j = 1 - (1 - a)^(j + 1)``; through the
    estimate's AR(2) model the residual signature is ``g_j - phi_1 g_{j-1} - phi_2
    g_{j-2}``. For estimates equal to the state it is the level signature."""
    rng = np.random.default_rng(0)
    x = np.zeros(20_000)
    for i in range(1, x.size):
        x[i] = 0.9 * x[i - 1] + rng.standard_normal()
    a = 0.4
    y = np.zeros_like(x)
    for i in range(1, x.size):
        y[i] = (1 - a) * y[i - 1] + a * x[i]
    y += 0.05 * rng.standard_normal(x.size)  # a little estimation noise
    q = fit_in_control([y], order=2, mean=0.0)
    got = step_response([y], [x], 0.0, 0.0, length=12)
    assert got == pytest.approx(1.0 - (1.0 - a) ** (np.arange(12) + 1.0), abs=0.01)
    sig = np.array(response_signature(got, q.phi))
    g = np.concatenate([[0.0, 0.0], 1.0 - (1.0 - a) ** (np.arange(12) + 1.0)])
    expect = g[2:] - q.phi[0] * g[1:-1] - q.phi[1] * g[:-2]
    assert sig == pytest.approx(expect / np.max(np.abs(expect)), abs=0.02)
    q_x = fit_in_control([x], order=2, mean=0.0)
    same = response_signature(step_response([x], [x], 0.0, 0.0, length=5), q_x.phi)
    assert same == pytest.approx((*level_signature(q_x.phi), same[-1], same[-1]), abs=1e-9)


def test_glr_threshold_gives_the_wanted_average_run_length() -> None:
    """Up-crossings of the designed ``h`` on fresh independent N(0, 1) scores: the rate is
    1 / ARL0 within the design's stated accuracy (real ARL 1-1.5 times the design's;
    Poisson error of ~500 crossings about 5 %)."""
    sig, window, arl0 = (1.0, 0.3, 0.2), 60, 2000.0
    h = glr_h(sig, window, arl0)
    z = np.random.default_rng(11).standard_normal((500, 2060))
    g = glr_statistics(sig, window, z)[:, window:]
    arl = g[:, 1:].size / np.sum((g[:, 1:] > h) & (g[:, :-1] <= h))
    assert 0.8 * arl0 < arl < 2.0 * arl0
    assert glr_h(sig, window, 20 * arl0) > h + 2.0  # about log(20) higher


def test_monitor_with_glr_charts_round_trips_config_and_state() -> None:
    """A monitor with a GLR chart: its config through JSON, its state through JSON mid-run;
    both continue identically, and a level step of 3 residual sigmas (signature 1, 0.2) is
    signalled by the GLR on the high side."""
    q = InControl(mean=0.0, sigma=1.0, phi=(0.8,))
    config = MonitorConfig({"a": q}, warmup=0, phase1=0, cusum_on=(),
                           glr={"a": Glr(level_signature(q.phi), h=12.0, window=50)})
    rng = np.random.default_rng(5)
    y = np.zeros(400)
    for i in range(1, y.size):
        y[i] = 0.8 * y[i - 1] + rng.standard_normal()
    y[300:] += 3.0  # a level step of 3 process sigmas (1.8 of the AR(1)'s stationary spread)
    values = [{"a": float(v)} for v in y]
    whole = Monitor(config)
    a_whole = [a for i, v in enumerate(values) for a in whole.update_values(v, i)]
    first = Monitor(config)
    a_first = [a for i, v in enumerate(values[:211]) for a in first.update_values(v, i)]
    second = Monitor(MonitorConfig.from_json(config.to_json()),
                     json.loads(json.dumps(first.state())))
    a_second = [a for i, v in enumerate(values[211:], 211) for a in second.update_values(v, i)]
    assert a_first + a_second == a_whole
    glr = [a for a in a_whole if a.chart == "glr"]
    assert glr and all(a.index >= 300 for a in glr)
    # expected statistic (3 + 0.6 (n - 1))^2 / (2 (1 + 0.04 (n - 1))): 12.6 after 5 products
    assert glr[0].side == "high" and glr[0].index - 300 < 25
    assert "glr" in whole.last["a"]


def test_glr_clip_survives_the_stored_config() -> None:
    """The service stores its monitor config as JSON and reloads it on restart: a GLR chart
    designed for clipped scores must come back clipped (its threshold is for those)."""
    q = InControl(mean=0.0, sigma=1.0, phi=(0.8,))
    config = MonitorConfig({"a": q}, warmup=0, phase1=0, cusum_on=(),
                           glr={"a": Glr(level_signature(q.phi), h=12.0, window=50, clip=3.0)})
    back = MonitorConfig.from_json(config.to_json())
    assert back.glr["a"].clip == 3.0 and back == config


def test_a_bounded_statistic_gets_no_glr_chart() -> None:
    """A signature without a lasting part and clipped scores: the statistic cannot pass
    clip^2 / 2, so no threshold has the design's ARL; calibrate leaves such a variable
    without a GLR chart (its other charts stay) instead of failing."""
    with pytest.raises(ValueError, match="bounded"):
        glr_h((1.0, 0.0), 50, 1e5, clip=3.0)
    rng = np.random.default_rng(1)
    names = ("a", "b")
    runs = []
    for _ in range(2):
        walk = np.cumsum(rng.standard_normal(700))  # AR fit phi_1 + phi_2 ~ 1: no lasting
        ar = np.zeros(700)
        for i in range(1, 700):
            ar[i] = 0.7 * ar[i - 1] + rng.standard_normal()
        runs.append({"a": walk, "b": ar})
    config = calibrate_series(runs, names, np.zeros(2),
                              ChartDesign(warmup=10, phase1=20, widen_margin=None))
    lasting = {n: config.quantities[n].phi for n in names}
    assert 1.0 - sum(lasting["a"]) < 0.02 and set(config.glr) == {"b"}
    assert set(config.cusum_on or ()) == {"a", "b"}


def test_kernel_loaded_at_start_is_the_one_the_chart_uses() -> None:
    """:func:`load_kernel` (a service's start) gives the kernel the type signature of the
    chart's own calls: the first charted product loads or compiles nothing more."""
    from formtwin.monitoring.glr import _glr_step, load_kernel

    load_kernel()
    before = list(_glr_step.signatures)
    assert len(before) >= 1
    chart, state = Glr(level_signature((0.6,)), h=5.0, window=20), GlrState()
    for z in (0.3, -1.2, 2.5):
        state, _ = chart.update(state, z)
    assert list(_glr_step.signatures) == before
