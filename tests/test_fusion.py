"""Late sensor values fused by ancestor reweighting (formtwin.filters.lagged,
formtwin.tracker.fusion): against the exact posterior of a linear-Gaussian model (the
Kalman smoother's answer, here by conditioning the joint Gaussian of the whole path), out
of order, duplicates refused, the tracker untouched by bad values, state bytes bit for bit.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from formtwin.defaults import analytic_model
from formtwin.filters import SIR
from formtwin.filters.lagged import FixedLag, lagged, reweight
from formtwin.tracker import FusionError, Tracker, TrackerConfig, build_tracker

#: relative difference allowed between a final angle the step evaluated in its batch of
#: particles (kept for the interval and the camera) and the same angle evaluated again in
#: another batch: the analytic stand-in evaluates row by row in float64 (0 here); the
#: margin covers a BLAS whose blocking depends on the batch (a few ulps of ~100 deg terms)
TOL_ANGLE = 1e-12

# a 2-D AR(1) state x_t = A x_{t-1} + q_t, the curve y_t = x1 + x2 + r_t, a late sensor
# s_j = x1_j + e_j: the curve alone cannot tell x1 from x2, the sensor can
A = np.array([0.9, 0.7])
Q = np.array([0.4, 0.3]) ** 2  # transition variances
P0 = Q / (1.0 - A**2)  # stationary variances of x_0
R_CURVE = 0.5**2
R_SENSOR = 0.3**2
T = 8  # steps (products 0..7)


class LinearGaussian:
    """The model above as the filters see it (state (N, 2))."""

    def sample_initial(self, n: int, rng: np.random.Generator) -> np.ndarray:
        return np.sqrt(P0) * rng.standard_normal((n, 2))

    def sample_transition(self, x: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        return A * x + np.sqrt(Q) * rng.standard_normal(x.shape)

    def loglik(self, x: np.ndarray, y: float) -> np.ndarray:
        return -0.5 * (y - x[:, 0] - x[:, 1]) ** 2 / R_CURVE


def _prior_cov() -> np.ndarray:
    """Covariance (2(T+1), 2(T+1)) of the path x_{-1} (the initial draw), x_0..x_{T-1}."""
    n = T + 1
    C = np.zeros((2 * n, 2 * n))
    for c in range(2):
        for i in range(n):
            for j in range(n):
                C[2 * i + c, 2 * j + c] = P0[c] * A[c] ** abs(i - j)
    return C


def exact_posterior(ys: np.ndarray, late: list[tuple[int, float]]) -> tuple[np.ndarray,
                                                                             np.ndarray]:
    """Mean (2,) and covariance (2, 2) of x_{T-1} given the curves ``ys`` (T,) of products
    0..T-1 and the late sensor values ``(product, value)``: the joint Gaussian conditioned."""
    C = _prior_cov()
    rows, values, noise = [], [], []
    for t, y in enumerate(ys):
        h = np.zeros(C.shape[0])
        h[2 * (t + 1)] = h[2 * (t + 1) + 1] = 1.0
        rows.append(h), values.append(y), noise.append(R_CURVE)
    for j, s in late:
        h = np.zeros(C.shape[0])
        h[2 * (j + 1)] = 1.0
        rows.append(h), values.append(s), noise.append(R_SENSOR)
    H, z = np.array(rows), np.array(values)
    S = H @ C @ H.T + np.diag(noise)
    K = C @ H.T @ np.linalg.inv(S)
    mean = K @ z
    cov = C - K @ H @ C
    last = slice(2 * T, 2 * T + 2)
    return mean[last], cov[last, last]


def _run(n: int, depth: int, seed: int) -> tuple[SIR, np.ndarray, np.ndarray]:
    """A SIR filter on the lagged model after T curves drawn from the model; the truth."""
    rng = np.random.default_rng(1000 + seed)
    truth = np.empty((T, 2))
    x = np.sqrt(P0) * rng.standard_normal(2)
    for t in range(T):
        x = A * x + np.sqrt(Q) * rng.standard_normal(2)
        truth[t] = x
    ys = truth.sum(axis=1) + math.sqrt(R_CURVE) * rng.standard_normal(T)
    f = SIR(FixedLag(LinearGaussian(), d=2, width=2, depth=depth), n,
            np.random.default_rng(seed))
    for y in ys:
        f.step(float(y))
    return f, ys, truth


def _fuse(f: SIR, product: int, value: float, depth: int) -> None:
    assert f.x is not None
    x = lagged(f.x, 2, 2, f.t - 1 - product)
    f.logw, _ = reweight(f.logw, -0.5 * (value - x[:, 0]) ** 2 / R_SENSOR)


@pytest.mark.parametrize("lag", [1, 2, 3])
def test_late_value_matches_the_exact_posterior(lag: int) -> None:
    """The weighted mean of x_{T-1} after fusing s_{T-1-lag} is the exact posterior mean
    within 5 Monte-Carlo standard errors, sd_post / sqrt(ESS) with the ESS of the fused
    weights (N = 200 000: ~1e-3 of the posterior sd); and the late value moves the
    estimate by several such errors, so the test would fail without it."""
    n = 200_000
    f, ys, truth = _run(n, depth=3, seed=lag)
    j = T - 1 - lag
    s = float(truth[j, 0] + 0.8)  # a value off the truth, so that it moves the estimate
    before, _ = exact_posterior(ys, [])
    _fuse(f, j, s, 3)
    mean, cov = exact_posterior(ys, [(j, s)])
    assert f.x is not None
    w = np.exp(f.logw)
    est = w @ f.x[:, :2]
    ess = 1.0 / np.sum(w**2)
    se = np.sqrt(np.diag(cov) / ess)
    assert np.all(np.abs(est - mean) < 5 * se), (est, mean, se)
    assert np.max(np.abs(mean - before) / se) > 10  # the value matters
    var = w @ (f.x[:, :2] - est) ** 2
    np.testing.assert_allclose(var, np.diag(cov), rtol=0.1)


def test_out_of_order_values_match_the_exact_posterior() -> None:
    """Two late values fused newest first equal the exact posterior given both, and the
    weights do not depend on the order (to rounding)."""
    n = 200_000
    f, ys, truth = _run(n, depth=3, seed=7)
    g = SIR(f.model, n, np.random.default_rng(0))
    g.x, g.logw, g.t = f.x.copy(), f.logw.copy(), f.t  # type: ignore[union-attr]
    late = [(T - 1, float(truth[T - 1, 0] - 0.5)), (T - 4, float(truth[T - 4, 0] + 0.6))]
    for j, s in late:
        _fuse(f, j, s, 3)
    for j, s in reversed(late):
        _fuse(g, j, s, 3)
    np.testing.assert_allclose(f.logw, g.logw, rtol=1e-12, atol=1e-12)
    mean, cov = exact_posterior(ys, late)
    w = np.exp(f.logw)
    assert f.x is not None
    est = w @ f.x[:, :2]
    se = np.sqrt(np.diag(cov) / (1.0 / np.sum(w**2)))
    assert np.all(np.abs(est - mean) < 5 * se), (est, mean, se)


@pytest.mark.parametrize("lag", [1, 2, 3])
def test_late_value_then_more_steps_matches_the_exact_posterior(lag: int) -> None:
    """A late value fused in the middle of the run (after product 4, of product 4 - lag),
    then three more curves, each step resampling: the filter's x_{T-1} is the exact
    posterior given every curve and the value (the weights carry the value into the next
    step's resampling, the lag columns stay aligned with their particles)."""
    n = 200_000
    rng = np.random.default_rng(50 + lag)
    truth = np.empty((T, 2))
    x = np.sqrt(P0) * rng.standard_normal(2)
    for t in range(T):
        x = A * x + np.sqrt(Q) * rng.standard_normal(2)
        truth[t] = x
    ys = truth.sum(axis=1) + math.sqrt(R_CURVE) * rng.standard_normal(T)
    f = SIR(FixedLag(LinearGaussian(), d=2, width=2, depth=3), n, np.random.default_rng(lag))
    j = 4 - lag
    s = float(truth[j, 0] + 0.8)
    for t, y in enumerate(ys):
        f.step(float(y))
        if t == 4:
            _fuse(f, j, s, 3)
    mean, cov = exact_posterior(ys, [(j, s)])
    without, _ = exact_posterior(ys, [])
    assert f.x is not None
    w = np.exp(f.logw)
    est = w @ f.x[:, :2]
    se = np.sqrt(np.diag(cov) / (1.0 / np.sum(w**2)))
    assert np.all(np.abs(est - mean) < 5 * se), (est, mean, se)
    assert np.max(np.abs(mean - without) / se) > 5  # the value still matters at T - 1


def test_tracker_fuses_out_of_order_to_the_same_weights() -> None:
    """The tracker's gauge of the newest product and camera of the one before, fused in
    either order, give the same weights (to rounding) and the same evidence in total."""
    a, b = _tracker(camera_discrepancy=False), _tracker(camera_discrepancy=False)
    for c in _curves(3):
        a.step(c), b.step(c)
    ia = a.fuse(2, "gauge", 0.3) + a.fuse(1, "camera", 88.0)
    ib = b.fuse(1, "camera", 88.0) + b.fuse(2, "gauge", 0.3)
    np.testing.assert_allclose(a.filter.logw, b.filter.logw, rtol=0, atol=1e-12)
    assert ia == pytest.approx(ib, rel=1e-12)


def test_reweight_refuses_a_value_no_particle_explains() -> None:
    logw = np.log(np.full(3, 1 / 3))
    with pytest.raises(ValueError, match="no particle"):
        reweight(logw, np.array([-np.inf, np.nan, -np.inf]))


# ------------------------------------------------------------------ the tracker
def _tracker(sensors: tuple[str, ...] = ("gauge", "camera"), **kw: object) -> Tracker:
    model = analytic_model()
    config = TrackerConfig(n_particles=200, n_mc=1000, estimate_deviation=False, seed=3,
                           sensors=sensors, **kw)  # type: ignore[arg-type]
    return build_tracker(model, config)


def _curves(n: int) -> np.ndarray:
    model = analytic_model()
    spec = model.spec
    rng = np.random.default_rng(5)
    X = spec.inputs.lo + (spec.inputs.hi - spec.inputs.lo) * (0.4 + 0.2 * rng.random((n, 10)))
    return model.predict_curves(X)


def test_gauge_and_camera_reweight_the_ancestors() -> None:
    """The lag-1 columns hold each particle's parent (rows of the previous particles);
    the gauge reweights by the Gaussian of the current thickness, the camera by that of
    the parent's final angle, and the evidence is the normalising constant."""
    tr = _tracker()
    spec = tr.spec
    curves = _curves(3)
    tr.step(curves[0])
    prev = tr.particles.copy()  # type: ignore[union-attr]
    tr.step(curves[1])
    x = tr.particles
    assert x is not None and x.shape[1] == 18 + 10
    parents = x[:, 18:28]
    assert {tuple(r) for r in parents} <= {tuple(r) for r in prev[:, :10]}
    logw0 = tr.filter.logw.copy()
    th = x[:, spec.state.index["thickness"]]
    value, sd = float(th.mean() + th.std()), spec.sensor("gauge").noise
    inc = tr.fuse(1, "gauge", value)
    w = np.exp(logw0) * np.exp(-0.5 * ((value - th) / sd) ** 2) / (sd * math.sqrt(2 * math.pi))
    np.testing.assert_allclose(np.exp(tr.filter.logw), w / w.sum(), rtol=1e-9, atol=1e-300)
    assert inc == pytest.approx(math.log(w.sum()), rel=1e-10)
    logw1 = tr.filter.logw.copy()
    a = tr.ssm.predict_angles(parents, None)[:, 1]
    sd = math.sqrt(spec.sensor("camera").noise ** 2 + float(tr.ssm.angle_error()[1]))
    value = float(a.mean() - a.std())
    tr.fuse(0, "camera", value)
    w = np.exp(logw1) * np.exp(-0.5 * ((value - a) / sd) ** 2)
    np.testing.assert_allclose(np.exp(tr.filter.logw), w / w.sum(), rtol=1e-9, atol=1e-300)


def test_bad_values_are_named_and_leave_the_tracker_untouched() -> None:
    tr = _tracker()
    with pytest.raises(FusionError, match="not yet seen"):
        tr.fuse(0, "gauge", 0.3)
    curves = _curves(4)
    for c in curves:
        tr.step(c)
    tr.fuse(3, "gauge", 0.3)
    before = tr.state_bytes()
    for args, match in (((3, "gauge", 0.3001), "fused already"),
                        ((1, "camera", 88.0), "older than"),
                        ((4, "camera", 88.0), "not yet seen"),
                        ((3, "camera", math.nan), "finite"),
                        ((3, "camera", math.inf), "finite"),
                        ((3, "laser", 1.0), "laser"),
                        ((2.5, "camera", 88.0), "whole number")):
        with pytest.raises(FusionError, match=match):
            tr.fuse(*args)  # type: ignore[arg-type]
    with pytest.raises(FusionError, match="stage2_depth"):
        tr.fuse(2, "camera", 88.0, u=1.0)  # 1 mm: outside the control's bounds
    assert tr.state_bytes() == before


def test_state_bytes_round_trip_and_continue_bit_for_bit(tmp_path: object) -> None:
    """Fused weights, lag columns and the log of fused values survive bytes and
    checkpoints; the restored tracker continues exactly as the original."""
    tr = _tracker()
    curves = _curves(5)
    for c in curves[:3]:
        tr.step(c)
    tr.fuse(2, "gauge", 0.3)
    tr.fuse(1, "camera", 88.0)
    data = tr.state_bytes()
    again = Tracker.from_state_bytes(data, tr.model, tr.measurement)
    assert again.state_bytes() == data
    with pytest.raises(FusionError, match="fused already"):
        again.fuse(1, "camera", 88.1)
    path = tr.checkpoint(tmp_path / "t.npz")  # type: ignore[operator]
    restored = Tracker.restore(path, tr.model, tr.measurement)
    for t in (tr, again, restored):
        t.step(curves[3])
        t.fuse(2, "camera", 88.0)
        t.step(curves[4])
    assert again.state_bytes() == tr.state_bytes() == restored.state_bytes()


def test_no_sensor_value_changes_nothing() -> None:
    """With sensors configured but no value fused, the particles' own columns are those of
    a tracker without sensors, bit for bit (the lag columns draw no random numbers)."""
    a, b = _tracker(()), _tracker()
    for c in _curves(3):
        ea, eb = a.step(c), b.step(c)
        np.testing.assert_array_equal(ea.mean, eb.mean)
    assert a.particles is not None and b.particles is not None
    assert a.particles.shape[1] == 18
    np.testing.assert_array_equal(a.particles, b.particles[:, :18])


def test_config_names_unknown_sensors_and_a_short_lag() -> None:
    with pytest.raises(ValueError, match="'laser' is not a sensor"):
        _tracker(("laser",))
    with pytest.raises(ValueError, match="sensor_lag = 0, below"):
        _tracker(("camera",), sensor_lag=0)
    tr = _tracker(("camera",), sensor_lag=3)
    assert tr.ssm.lag_depth == 3
    assert TrackerConfig(sensors="gauge, camera").sensors == ("gauge", "camera")  # type: ignore[arg-type]
    assert TrackerConfig.from_dict(TrackerConfig(sensors=("gauge",)).to_dict()).sensors == (
        "gauge",)
    with pytest.raises(ValueError, match="given twice"):
        TrackerConfig(sensors=("gauge", "gauge"))


def test_posterior_carries_the_camera_calibrated_interval() -> None:
    """The posterior's final angle is the model's mapped by the discrepancy learned from
    the camera, its interval ACI on the fused camera values: the same numbers as a
    standalone discrepancy and calibrator fed the same model angles and values (the
    prior variance: the camera's 0.2 deg and the metamodel's error). A model 1 deg off is
    learned; the camera's likelihood uses the learned map; everything survives the state
    bytes; with ``camera_discrepancy=False`` the model's angle is used as it is."""
    from formtwin.tracker.angle_discrepancy import AngleDiscrepancy
    from formtwin.tracker.conformal import AdaptiveConformal

    tr = _tracker(("camera",))
    noise = 0.2**2 + float(tr.ssm.angle_error()[1])
    ref, disc = AdaptiveConformal(), AngleDiscrepancy(noise)
    rng = np.random.default_rng(0)
    prev = None
    for k, c in enumerate(_curves(30)):
        tr.step(c)
        if prev is not None:  # the camera value of the product before: the model + 1 deg
            value = prev + 1.0 + 0.2 * float(rng.standard_normal())
            if k == 29:  # the likelihood: the parents' angles through the learned map
                logw = tr.filter.logw.copy()
                assert tr.particles is not None
                a = tr.ssm.predict_angles(tr.ssm.lagged_inputs(tr.particles, 1), None)[:, 1]
                r0, b0, b1 = disc.coefficients()
                sd = max(math.sqrt(noise), math.sqrt(disc.variance()))
                w = np.exp(logw - 0.5 * ((value - r0 - b0 - b1 * (a - r0)) / sd) ** 2)
            tr.fuse(k - 1, "camera", value)
            if k == 29:
                np.testing.assert_allclose(np.exp(tr.filter.logw), w / w.sum(), rtol=1e-9,
                                           atol=1e-300)
            disc.update_product(k - 1, value)
            ref.update(k - 1, value)
        p = tr.posterior()  # a report: what issue_final issues, nothing recorded
        before = tr.state_bytes()
        assert tr.posterior().final_interval == p.final_interval
        assert tr.state_bytes() == before
        final, (lo_t, hi_t) = tr.issue_final()
        assert (final, lo_t, hi_t) == pytest.approx((p.final_mean, *p.final_interval),
                                                    rel=TOL_ANGLE)
        mean, var = disc.issue(k, float(p.angles_mean[1]))
        assert final == pytest.approx(mean, rel=TOL_ANGLE)
        lo, hi = ref.interval(k, mean, math.sqrt(var))
        assert (lo_t, hi_t) == pytest.approx((lo, hi), rel=TOL_ANGLE)
        prev = float(p.angles_mean[1])
    assert 0.7 < p.final_mean - prev < 1.3
    again = Tracker.from_state_bytes(tr.state_bytes(), tr.model, tr.measurement)
    assert again.fused == tr.fused
    assert again.state_bytes() == tr.state_bytes()
    plain = _tracker(("camera",), camera_discrepancy=False)
    plain.step(_curves(1)[0])
    p = plain.posterior()
    assert p.final_mean == p.angles_mean[1] and plain.fused.discrepancy is None
    gauge_only = _tracker(("gauge",))
    gauge_only.step(_curves(1)[0])
    p = gauge_only.posterior()
    assert math.isnan(p.final_mean) and all(math.isnan(v) for v in p.final_interval)


@pytest.mark.parametrize("kw", [{"filter": "move"}, {"filter": "guided_lin"},
                                {"learn_mu": True}, {"likelihood": "discrepancy"},
                                {"estimate_deviation": True}])
def test_lag_columns_with_every_particle_layout(kw: dict[str, object]) -> None:
    """Whatever else the particles carry (learned mu, the discrepancy's statistics, the
    parents' curves) and however they move, the lag block holds each particle's parent."""
    model = analytic_model()
    config = TrackerConfig(**{"n_particles": 100, "n_mc": 1000, "estimate_deviation": False,
                              "seed": 1, "sensors": ("gauge", "camera"), **kw})  # type: ignore[arg-type]
    tr = build_tracker(model, config)
    curves = _curves(3)
    tr.step(curves[0])
    prev = tr.particles.copy()  # type: ignore[union-attr]
    tr.step(curves[1])
    x = tr.particles
    assert x is not None
    lag = x[:, tr.ssm.lag_start:tr.ssm.lag_start + 10]
    assert {tuple(r) for r in lag} <= {tuple(r) for r in prev[:, :10]}
    tr.fuse(0, "camera", 88.0)
    tr.fuse(1, "gauge", 0.3)
    tr.step(curves[2])
    assert np.isfinite(tr.filter.logw).all()


def test_the_tracker_holds_the_sensors_of_its_config_in_its_order() -> None:
    """:func:`used_sensors` gives the config's sensors in the config's order (an unknown
    one named), and a tracker holds them (found once, at construction)."""
    from dataclasses import replace

    from formtwin.tracker.fusion import used_sensors

    spec = analytic_model().spec
    cfg = TrackerConfig(sensors=("camera", "gauge"))
    assert [s.name for s in used_sensors(spec, cfg)] == ["camera", "gauge"]
    assert [s.name for s in used_sensors(spec, replace(cfg, sensors=("gauge", "camera")))] \
        == ["gauge", "camera"]
    with pytest.raises(ValueError, match="'sonar' is not a sensor"):
        used_sensors(spec, replace(cfg, sensors=("sonar",)))
    tr = _tracker(("gauge",))
    assert tr.sensors == used_sensors(tr.spec, tr.config)
    assert [s.name for s in tr.sensors] == ["gauge"] and tr.finals is None
    assert [s.name for s in _tracker(()).sensors] == []
