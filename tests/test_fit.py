"""The absolute goodness of fit (formtwin.tracker.fit): its reference distribution, its
calibration under the measurement model, and the health of tracker estimates."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.stats import chi2, kstest
from scipy.stats import f as fdist

from formtwin.defaults import AnalyticModel
from formtwin.measurement import MeasurementModel
from formtwin.production import draw_production_run
from formtwin.tracker import Estimates, FitRule, TrackerConfig, build_tracker
from formtwin.tracker.fit import assess, distance_logsf


def _mm(nu: float = math.inf) -> MeasurementModel:
    q, _ = np.linalg.qr(np.random.default_rng(0).standard_normal((6, 3)))
    return MeasurementModel(basis=q, lam=np.array([9.0, 4.0, 2.0]), s2=0.5, nu=nu)


def test_covariance_is_the_one_mahalanobis2_uses() -> None:
    mm = _mm()
    d = np.random.default_rng(1).standard_normal((5, 6))
    ref = np.einsum("ij,ij->i", d, np.linalg.solve(mm.covariance(), d.T).T)
    assert np.allclose(mm.mahalanobis2(np.zeros((5, 6)), d), ref)


def test_tail_matches_scipy_and_continues_beyond_its_underflow() -> None:
    mm = MeasurementModel(basis=np.eye(101)[:, :3], lam=np.ones(3) * 2, s2=1.0)
    x = np.array([50.0, 150.0, 900.0])
    assert np.allclose(distance_logsf(x, mm), chi2.logsf(x, 101))
    # beyond scipy's underflow: finite, decreasing, and continuous with the exact tail
    far = distance_logsf(np.array([1e4, 1e5, 1e6]), mm)
    assert np.all(np.isfinite(far)) and np.all(np.diff(far) < 0)
    x0 = 1400.0  # still finite in scipy
    exact = float(chi2.logsf(x0, 101))
    a, h = 50.5, 0.5 * x0
    approx = (a - 1) * math.log(h) - h - math.lgamma(a) - math.log1p(-(a - 1) / h)
    assert abs(approx - exact) < 0.01 * abs(exact)
    t = _mm(nu=5.0)
    assert np.allclose(distance_logsf(np.array([3.0, 30.0]), t),
                       fdist.logsf(np.array([3.0, 30.0]) / 6, 6, 5.0))


def test_distance_is_chi2_when_the_curve_comes_from_the_predictive() -> None:
    """Truth and particles from the same cloud, curve = truth + N(0, Sigma): the distance
    of the curve from the predictive follows chi2(n_t) (KS test, 400 draws)."""
    mm = _mm()
    rng = np.random.default_rng(2)
    ls = np.linalg.cholesky(mm.covariance())
    spread = np.diag([3.0, 1.0, 0.5, 0.2, 2.0, 1.0])
    d2 = []
    for _ in range(400):
        cloud = rng.standard_normal((1000, 6)) @ spread
        truth = rng.standard_normal(6) @ spread
        y = truth + ls @ rng.standard_normal(6)
        fit = assess(y - cloud, np.full(1000, 1e-3), ess=500.0, measurement=mm)
        d2.append(fit.distance2)
    assert kstest(d2, chi2(6).cdf).pvalue > 0.01
    assert 0.002 < np.mean(np.array(d2) > chi2.ppf(0.99, 6)) < 0.03


def test_health_rules() -> None:
    mm = _mm()
    r = np.zeros((50, 6))
    v = np.full(50, 0.02)
    assert assess(r, v, 25.0, mm).health == "ok"
    assert assess(r, v, 0.4, mm).health == "degraded"  # ESS share 0.008 < 0.01
    assert assess(r + 100.0, v, 25.0, mm).health == "no_fit"
    col = assess(r, v, 25.0, mm, collapsed=True)
    assert col.health == "no_fit" and col.quantile == 1.0 and math.isinf(col.distance2)
    # between the warning and the failure quantile
    sig = np.linalg.cholesky(mm.covariance())
    e = sig @ np.full(6, 1.0)
    e *= math.sqrt(chi2.ppf(0.995, 6) / (e @ np.linalg.solve(mm.covariance(), e)))
    mid = assess(r + e, v, 25.0, mm)
    assert mid.health == "degraded" and mid.quantile == pytest.approx(0.995, abs=1e-6)
    assert assess(r + e, v, 25.0, mm, rule=FitRule(p_fail=1e-2, p_warn=0.1)).health == "no_fit"
    with pytest.raises(ValueError, match="p_fail"):
        FitRule(p_fail=0.1, p_warn=0.01)


def test_tracker_estimates_carry_fit_and_health(model: AnalyticModel) -> None:
    spec = model.spec
    run = draw_production_run(spec, 60, np.random.default_rng(3), deviation=False)
    cfg = TrackerConfig(n_particles=200, estimate_deviation=False, mu=tuple(run.mu), n_mc=2000)
    curves = model.predict_curves(run.inputs)
    est = build_tracker(model, cfg).run(curves)
    assert isinstance(est, Estimates)
    assert "no_fit" not in set(est.health)  # degraded only by a low ESS share
    assert np.all((est.health == "ok") | (est.ess_share < 0.01))
    assert np.all(est.fit_quantile < 0.99) and np.all(est.fit_distance2 < chi2.ppf(0.99, 101))
    cols = est.columns()
    assert {"health", "fit_distance2", "fit_quantile", "fit_log10_p", "ess_share"} <= set(cols)
    # a curve of another process (twice the force, shifted) is not explained
    tr = build_tracker(model, cfg)
    e = tr.step(2.0 * curves[0] + 50.0)
    d = e.to_dict()
    assert d["health"] == "no_fit" and d["fit"]["quantile"] == 1.0
    assert d["fit"]["log10_p"] < -100 and d["fit"]["dof"] == 101


def test_whitened_residuals_give_the_same_distance() -> None:
    """The tracker hands the goodness of fit its likelihood's whitened residuals and their
    variances (no (n_t, n_t) covariance per product): the distance is the one of the raw
    residuals under the full predictive covariance, to rounding (conditioning ~1e3)."""
    from formtwin.tracker.discrepancy import Discrepancy

    rng = np.random.default_rng(5)
    n_t = 30
    a = rng.standard_normal((n_t, 2 * n_t))
    b = rng.standard_normal((n_t, n_t // 2))
    d = Discrepancy.from_covariances(a @ a.T / n_t + 0.1 * np.eye(n_t), b @ b.T / n_t,
                                     np.array([0.0, 0.5, 1.0]))
    mm = MeasurementModel(basis=np.eye(n_t)[:, :3], lam=np.ones(3), s2=1.0)
    w = np.array([0.2, 0.3, 0.5])
    r = rng.standard_normal((400, n_t)) + rng.standard_normal(n_t)
    r[7] = np.nan  # a particle without a likelihood
    v = rng.random(400)
    full = assess(r, v, 50.0, mm, covariance=d.predictive_cov(None, w))
    white = assess(d.whiten(r), v, 50.0, mm, covariance=d.predictive_var(None, w))
    assert np.isfinite(full.distance2) and full.distance2 > 0
    assert white.distance2 == pytest.approx(full.distance2, rel=1e-9)
    assert white.health == full.health and white.log10_p == pytest.approx(full.log10_p,
                                                                         rel=1e-9)


def test_rows_without_a_likelihood_or_weight_are_left_out() -> None:
    """A row with NaN or inf, or with predictive weight 0, gives the distance of the
    cloud without it, bit for bit (N <= MAX_SPREAD: every row is in the spread); a
    cloud of such rows only is ``no_fit``."""
    rng = np.random.default_rng(8)
    n_t = 12
    mm = MeasurementModel(basis=np.eye(n_t)[:, :2], lam=np.array([2.0, 1.0]), s2=0.5)
    r = rng.standard_normal((60, n_t)) + 0.3
    v = rng.random(60) + 0.1
    clean = assess(np.delete(r, [5, 9, 20], axis=0), np.delete(v, [5, 9, 20]), 30.0, mm)
    bad_r, bad_v = r.copy(), v.copy()
    bad_r[5, 3], bad_r[9, 0], bad_v[20] = np.nan, np.inf, 0.0
    got = assess(bad_r, bad_v, 30.0, mm)
    assert got.distance2 == clean.distance2 and got.health == clean.health
    nothing = assess(np.full((4, n_t), np.nan), np.ones(4), 4.0, mm)
    assert nothing.health == "no_fit" and nothing.distance2 == math.inf


def test_one_distance_in_scalars_is_the_array_tail() -> None:
    """The step's scalar tail (``_distance_logsf1``) is :func:`distance_logsf` of one value,
    across scipy's range, beyond its underflow, and for inf, NaN and the Student-t."""
    from formtwin.tracker.fit import _distance_logsf1

    for mm in (MeasurementModel(basis=np.eye(101)[:, :3], lam=np.ones(3) * 2, s2=1.0),
               _mm(nu=5.0)):
        for m2 in (0.0, 3.0, 50.0, 150.0, 900.0, 1e4, 1e6, math.inf, math.nan):
            want = float(distance_logsf(np.array([m2]), mm)[0])
            got = _distance_logsf1(m2, mm)
            assert got == pytest.approx(want, rel=1e-13, abs=0.0) or got == want
