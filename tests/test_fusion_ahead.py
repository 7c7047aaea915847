"""A state variable's value known before its product's curve (formtwin.tracker.ahead): the
conditioned transition is the transition times the value's likelihood, the posterior is
that of fusing the value after the step, with more effective particles; the value is
logged, checked and saved like any fused value, and refused where it cannot enter the step.
"""

from __future__ import annotations

import functools
import math
from typing import Any

import numpy as np
import pytest

from formtwin.defaults import analytic_model
from formtwin.tracker import FusionError, Tracker, TrackerConfig, build_tracker
from formtwin.tracker.ahead import conditioned


def _tracker(n: int = 200, seed: int = 3, **kw: object) -> Tracker:
    config = TrackerConfig(n_particles=n, n_mc=1000, estimate_deviation=False, seed=seed,
                           sensors=("gauge", "camera"), **kw)  # type: ignore[arg-type]
    if kw:
        return build_tracker(analytic_model(), config)
    model, measurement = _model_and_likelihood()
    return Tracker(model, measurement, config)


@functools.cache
def _model_and_likelihood() -> tuple[Any, Any]:
    """The stand-in model and the default config's measurement model (built once)."""
    tr = build_tracker(analytic_model(), TrackerConfig(n_particles=10, n_mc=1000,
                                                       estimate_deviation=False))
    return tr.model, tr.measurement


def _line(n: int, seed: int = 5) -> tuple[np.ndarray, np.ndarray]:
    """Curves (n, n_t) of a run drawn by eq. 4-5 and the gauge's values (n,) mm."""
    model = analytic_model()
    spec = model.spec
    rng = np.random.default_rng(seed)
    st = spec.state
    x = np.empty((n, len(st)))
    x[0] = st.mu_mid
    for i in range(1, n):
        x[i] = (1 - st.rho) * st.mu_mid + st.rho * x[i - 1] \
            + np.sqrt(1 - st.rho**2) * st.sigma * rng.standard_normal(len(st))
    theta = 0.5 * (spec.inputs.lo + spec.inputs.hi)[len(st):]
    curves = model.predict_curves(np.hstack([x, np.tile(theta, (n, 1))]))
    gauge = x[:, st.index["thickness"]] + spec.sensor("gauge").noise * rng.standard_normal(n)
    return curves, gauge


def test_conditioned_transition_times_likelihood_is_the_identity() -> None:
    """N(x; a + b p, s^2) N(y; x, r^2) = N(y; a + b p, s^2 + r^2) N(x; a' + b' p, s'^2)
    for every parent p and state x: the weight of :func:`fuse_ahead` times the conditioned
    transition is the transition times the likelihood."""
    rng = np.random.default_rng(0)
    drift = (rng.normal(size=4), rng.uniform(0.2, 1.0, 4), rng.uniform(0.1, 2.0, 4))
    y, r2 = 0.7, 0.3**2
    a2, b2, s2 = conditioned(drift, {2: (y, r2)})
    for k in (0, 1, 3):  # the other columns are untouched
        assert (a2[k], b2[k], s2[k]) == (drift[0][k], drift[1][k], drift[2][k])
    a, b, s = (v[2] for v in drift)

    def logn(v: np.ndarray | float, m: np.ndarray | float, var: float) -> np.ndarray:
        return -0.5 * (np.asarray(v) - m) ** 2 / var - 0.5 * math.log(2 * math.pi * var)

    p, x = rng.normal(size=50), rng.normal(size=50)
    left = logn(x, a + b * p, s**2) + logn(y, x, r2)
    right = logn(y, a + b * p, s**2 + r2) + logn(x, a2[2] + b2[2] * p, s2[2] ** 2)
    np.testing.assert_allclose(left, right, rtol=1e-12, atol=1e-12)
    assert conditioned(drift, {}) is drift


def test_value_ahead_gives_the_posterior_of_fusing_it_after() -> None:
    """Both orders target the same posterior: over 8 seeds (N = 1000, 4 products with the
    gauge) the mean posterior means of every state variable agree within 4.5 standard
    errors of the seeds' spread (a filter's Monte Carlo error is larger than its last
    cloud's std / sqrt(ESS)), and the thickness is the gauge's to within its noise."""
    curves, gauge = _line(5)
    means: dict[str, list[np.ndarray]] = {"ahead": [], "after": []}
    for seed in range(8):
        for order, out in means.items():
            tr = _tracker(1000, seed=seed)
            tr.step(curves[0])
            for k in range(1, 5):
                if order == "ahead":
                    tr.fuse(k, "gauge", float(gauge[k]))
                tr.step(curves[k])
                if order == "after":
                    tr.fuse(k, "gauge", float(gauge[k]))
            out.append(tr.posterior().mean[:len(tr.spec.state)])
    a, b = np.array(means["ahead"]), np.array(means["after"])
    se = np.sqrt((a.var(axis=0, ddof=1) + b.var(axis=0, ddof=1)) / len(a))
    assert np.all(np.abs(a.mean(axis=0) - b.mean(axis=0)) <= 4.5 * se)
    th = analytic_model().spec.state.index["thickness"]
    assert abs(a[:, th].mean() - gauge[4]) < analytic_model().spec.sensor("gauge").noise


def test_value_ahead_keeps_more_effective_particles() -> None:
    """From the same cloud (30 products of a run), the weights that carry the curve and the
    gauge have a larger ESS when the value entered the step than when the bootstrap's
    predicted particles are reweighted by both (no resampling in between)."""
    curves, gauge = _line(31, seed=8)
    main = _tracker()
    main.step(curves[0])
    ess: dict[str, list[float]] = {"ahead": [], "after": []}
    for k in range(1, 31):
        data = main.state_bytes()
        a, b = (Tracker.from_state_bytes(data, main.model, main.measurement) for _ in "ab")
        a.filter.ess_threshold = b.filter.ess_threshold = 0.0  # keep the step's weights
        a.fuse(k, "gauge", float(gauge[k]))
        ess["ahead"].append(a.step(curves[k]).ess)
        b.step(curves[k])
        b.fuse(k, "gauge", float(gauge[k]))
        ess["after"].append(b.posterior().ess)
        main.fuse(k, "gauge", float(gauge[k]))
        main.step(curves[k])
    assert np.mean(ess["ahead"]) > 1.2 * np.mean(ess["after"])


def test_evidence_is_the_predictive_density_of_the_value() -> None:
    tr = _tracker()
    curves, gauge = _line(3)
    tr.step(curves[0]), tr.step(curves[1])
    x, logw = tr.particles, tr.filter.logw.copy()
    assert x is not None
    j = tr.spec.state.index["thickness"]
    a, b, s = (float(v[j]) for v in tr.ssm._drift)
    var = s**2 + tr.spec.sensor("gauge").noise ** 2
    dens = np.exp(-0.5 * (gauge[2] - a - b * x[:, j]) ** 2 / var) / math.sqrt(2 * math.pi * var)
    inc = tr.fuse(2, "gauge", float(gauge[2]))
    assert inc == pytest.approx(math.log(float(np.exp(logw) @ dens)), rel=1e-10)
    assert tr.fused.ahead == {"gauge": float(gauge[2])}
    tr.step(curves[2])
    assert tr.fused.ahead == {} and (2, "gauge") in tr.fused.done


def test_value_ahead_is_logged_saved_and_refused_twice(tmp_path: object) -> None:
    """A second value of the same product is refused before and after its step; the
    value waiting for its step survives state bytes and a failed step, and the restored
    tracker continues bit for bit."""
    tr = _tracker()
    curves, gauge = _line(4)
    tr.step(curves[0])
    tr.fuse(1, "gauge", float(gauge[1]))
    with pytest.raises(FusionError, match="fused already"):
        tr.fuse(1, "gauge", float(gauge[1]))
    data = tr.state_bytes()
    again = Tracker.from_state_bytes(data, tr.model, tr.measurement)
    assert again.state_bytes() == data and again.fused.ahead == tr.fused.ahead
    with pytest.raises(ValueError):
        tr.step(np.full(3, 1.0))  # a malformed curve: nothing changes
    assert tr.state_bytes() == data
    for t in (tr, again):
        t.step(curves[1])
        with pytest.raises(FusionError, match="fused already"):
            t.fuse(1, "gauge", float(gauge[1]))
        t.fuse(0, "camera", 88.0)
        t.step(curves[2])
    assert again.state_bytes() == tr.state_bytes()


@pytest.mark.parametrize(("kw", "match"), [
    ({"learn_mu": True}, "learned mu"),
    ({"filter": "guided"}, "filter 'guided'"),
])
def test_value_ahead_refused_where_it_cannot_enter_the_step(kw: dict[str, object],
                                                            match: str) -> None:
    tr = _tracker(**kw)
    curves, gauge = _line(2)
    tr.step(curves[0])
    before = tr.state_bytes()
    with pytest.raises(FusionError, match=match):
        tr.fuse(1, "gauge", float(gauge[1]))
    assert tr.state_bytes() == before
    tr.step(curves[1])
    tr.fuse(1, "gauge", float(gauge[1]))  # after its step: fused as any value
    assert (1, "gauge") in tr.fused.done


def test_only_the_next_products_state_variable() -> None:
    """Before the first step, two products ahead, and a model output ahead: not yet seen."""
    tr = _tracker()
    curves, _ = _line(2)
    with pytest.raises(FusionError, match="not yet seen"):
        tr.fuse(0, "gauge", 0.3)
    tr.step(curves[0])
    before = tr.state_bytes()
    for args in ((2, "gauge", 0.3), (1, "camera", 88.0)):
        with pytest.raises(FusionError, match="not yet seen"):
            tr.fuse(*args)  # type: ignore[arg-type]
    assert tr.state_bytes() == before


def test_value_ahead_enters_the_intervals_assumed_mu_term() -> None:
    """With mu assumed, the reported std adds the estimate's error from the mu offset
    (tracker/sandwich.py: the linearised filter's sensitivity ``G_mu``). A gauge value in
    the step is a measurement of thickness in that linearised step too: thickness's term
    falls to a few percent (it follows the gauge, not the assumed mu), yield stress's,
    which the gauge does not see, stays."""
    curves, gauge = _line(40)
    terms = {}
    for tag in ("curve", "gauge"):
        tr = _tracker()
        assert tr.sandwich is not None and tr.sandwich.mu_half.size
        got = []
        update = tr.sandwich.update

        def keep(*a: Any, update: Any = update, got: list[Any] = got) -> Any:
            var, avar = update(*a)
            got.append(var.copy())
            return var, avar

        tr.sandwich.update = keep  # type: ignore[method-assign]
        for k in range(40):
            if tag == "gauge" and k > 0:
                tr.fuse(k, "gauge", float(gauge[k]))
            tr.step(curves[k])
        terms[tag] = np.median(np.array(got)[10:], axis=0)
    j = analytic_model().spec.state.index["thickness"]
    assert terms["gauge"][j] < 0.05 * terms["curve"][j]
    assert 0.8 < terms["gauge"][0] / terms["curve"][0] < 1.25  # yield stress
