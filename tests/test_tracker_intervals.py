"""The sandwich intervals (``TrackerConfig(intervals="sandwich")``): on a linear-Gaussian
model with a persistent measurement offset the recursion gives the Kalman estimate's mean
error and mean squared error in closed form; in the tracker only the reported std change."""

from __future__ import annotations

import numpy as np
import pytest
from filter_refs import interior_curves, kalman_filter

from formtwin.defaults import analytic_model
from formtwin.tracker import Tracker, TrackerConfig, build_tracker
from formtwin.tracker.sandwich import mu_step, sandwich_step


def _linear_model() -> dict[str, np.ndarray]:
    """A 3-variable AR(1)/random-walk state seen through 5 samples."""
    rng = np.random.default_rng(4)
    J = rng.standard_normal((5, 3))
    a = rng.standard_normal((5, 5))
    return {"F": np.array([0.8, 0.5, 1.0]), "Q": np.array([0.3, 0.2, 1e-3]), "J": J,
            "S": a @ a.T / 5 + 0.5 * np.eye(5), "P0": np.diag([1.0, 2.0, 3.0]),
            "delta": np.array([0.4, -0.3, 0.2, 0.5, -0.1])}


def test_sandwich_is_the_biased_kalman_estimates_error_in_closed_form() -> None:
    """Truth 0, no noise, curves = the fixed offset delta: the Kalman estimate is its
    error, and equals G delta; the filter's P is the sandwich's P_lin; with K_res =
    delta delta^T the reported covariance P + G K_res G^T is the estimate's mean squared
    error, checked against 20000 simulated runs."""
    lm = _linear_model()
    F, Q, J, S, P0, delta = (lm[k] for k in ("F", "Q", "J", "S", "P0", "delta"))
    n = 40
    kf = list(kalman_filter(np.diag(F), np.diag(Q), J, S, np.zeros(3), P0,
                            [delta] * n))
    G, P_prev, gains, Ps = np.zeros((3, 5)), P0, [], []
    for m, P, _ in kf:
        G = sandwich_step(G, P_prev, J, np.linalg.solve(S, J), F, Q)
        np.testing.assert_allclose(m, G @ delta, rtol=1e-10, atol=1e-12)
        Pp = np.diag(F) @ P_prev @ np.diag(F) + np.diag(Q)
        gains.append(Pp @ J.T @ np.linalg.inv(J @ Pp @ J.T + S))
        Ps.append(P)
        P_prev = P
    assert np.abs(G @ delta).max() > 0.05  # a bias the cloud's P does not contain
    # Monte Carlo: x_0 ~ N(0, P0), x_i = F x + N(0, Q), y_i = J x_i + delta + N(0, S)
    rng = np.random.default_rng(5)
    r = 20_000
    x = rng.standard_normal((r, 3)) * np.sqrt(np.diag(P0))
    est = np.zeros((r, 3))
    cs = np.linalg.cholesky(S)
    for K in gains:
        x = F * x + rng.standard_normal((r, 3)) * np.sqrt(Q)
        y = x @ J.T + delta + rng.standard_normal((r, 5)) @ cs.T
        pred = F * est
        est = pred + (y - pred @ J.T) @ K.T
    err = est - x
    mse = err.T @ err / r
    sandwich = Ps[-1] + G @ np.outer(delta, delta) @ G.T
    np.testing.assert_allclose(err.mean(axis=0), G @ delta,
                               atol=4 * float(np.sqrt(np.diag(Ps[-1]).max() / r)))
    np.testing.assert_allclose(mse, sandwich, atol=0.04 * float(np.abs(sandwich).max()))
    assert not np.allclose(mse, Ps[-1], atol=0.04 * float(np.abs(sandwich).max()))


def test_without_memory_one_step_is_the_classic_sandwich() -> None:
    """F = 0: G = P J^T S^-1 with P the one-product posterior, so G K G^T is
    P J^T S^-1 K S^-1 J P."""
    lm = _linear_model()
    J, S, Q = lm["J"], lm["S"], lm["Q"]
    G = sandwich_step(np.ones((3, 5)), lm["P0"], J, np.linalg.solve(S, J), np.zeros(3), Q)
    P = np.linalg.inv(np.diag(1 / Q) + J.T @ np.linalg.solve(S, J))
    K_res = np.diag(np.arange(1.0, 6.0))
    Si = np.linalg.inv(S)
    np.testing.assert_allclose(G @ K_res @ G.T, P @ J.T @ Si @ K_res @ Si @ J @ P,
                               rtol=1e-9)


def test_mu_term_is_the_kalman_estimates_error_under_a_wrong_prior_mean() -> None:
    """The filter assumes mu = 0 for the two AR(1) states, the line's is d: without noise
    the Kalman estimate's error is exactly -G_mu d; with noise and d ~ U(0.5, 1.5) per
    line (the assumption off the range's middle) its mean squared error is
    P + G_mu E[d d^T] G_mu^T (20000 simulated lines), not P."""
    lm = _linear_model()
    F, Q, J, S, P0 = (lm[k] for k in ("F", "Q", "J", "S", "P0"))
    nx, n = 2, 40
    d = np.array([0.7, -1.2])
    x_true = np.r_[d, 0.0]  # the constant parameter has no mean: its prior is not off
    kf = list(kalman_filter(np.diag(F), np.diag(Q), J, S, np.zeros(3), P0,
                            [J @ x_true] * n))
    G_mu, P_prev = np.eye(3, nx), P0
    SiJ = np.linalg.solve(S, J)
    for m, P, _ in kf:
        G_mu = mu_step(G_mu, P_prev, J, SiJ, F, Q)
        np.testing.assert_allclose(m - x_true, -G_mu @ d, rtol=1e-10, atol=1e-12)
        P_prev = P
    assert np.abs(G_mu @ d).max() > 0.05
    lo, hi = 0.5, 1.5
    second = np.eye(nx) * (hi - lo) ** 2 / 12.0 + np.full((nx, nx), 0.5 * (lo + hi)) ** 2
    rng = np.random.default_rng(6)
    r = 20_000
    mu = np.c_[rng.uniform(lo, hi, (r, nx)), np.zeros(r)]
    x = mu + rng.standard_normal((r, 3)) * np.sqrt(np.diag(P0))
    est = np.zeros((r, 3))
    cs = np.linalg.cholesky(S)
    P_prev = P0
    for _, P, _ in kf:
        Pp = np.diag(F) @ P_prev @ np.diag(F) + np.diag(Q)
        K = Pp @ J.T @ np.linalg.inv(J @ Pp @ J.T + S)
        x = mu + F * (x - mu) + rng.standard_normal((r, 3)) * np.sqrt(Q)
        y = x @ J.T + rng.standard_normal((r, 5)) @ cs.T
        pred = F * est
        est = pred + (y - pred @ J.T) @ K.T
        P_prev = P
    err = est - x
    mse = err.T @ err / r
    expected = P_prev + G_mu @ second @ G_mu.T
    np.testing.assert_allclose(mse, expected, atol=0.04 * float(np.abs(expected).max()))
    assert not np.allclose(mse, P_prev, atol=0.04 * float(np.abs(expected).max()))


def test_assumed_mu_widens_only_the_reported_std() -> None:
    """intervals="cloud_mu", mu_known=False (the default) against True on the same seed:
    particles, means, ESS,
    evidence and fit bit for bit; the std of the states and angles grow (theta's too,
    through its correlation with the state); a learned mu has no term."""
    model = analytic_model()
    curves = interior_curves(model, n=8)

    def run(**kw: object) -> tuple[Tracker, list]:
        cfg = TrackerConfig(n_particles=200, estimate_deviation=False, n_mc=500, seed=3,
                            intervals="cloud_mu", **kw)  # type: ignore[arg-type]
        tr = build_tracker(model, cfg)
        return tr, [tr.step(c) for c in curves]

    known, ek = run(mu_known=True)
    assumed, ea = run()
    assert known.sandwich is None and assumed.sandwich is not None
    np.testing.assert_array_equal(assumed.particles, known.particles)
    for a, b in zip(ek, ea, strict=True):
        for key in ("mean", "angles_mean"):
            np.testing.assert_array_equal(getattr(b, key), getattr(a, key))
        assert (b.ess, b.loglik, b.fit, b.health) == (a.ess, a.loglik, a.fit, a.health)
        assert np.all(b.std >= a.std) and np.all(b.angles_std >= a.angles_std)
    assert np.all(ea[-1].std[:7] > ek[-1].std[:7]) and np.all(ea[-1].angles_std > ek[-1].angles_std)
    np.testing.assert_array_equal(ea[-1].std[10:], 0.0)  # theta_d is not estimated
    learned, _ = run(learn_mu=True)
    assert learned.sandwich is None
    pure = build_tracker(model, TrackerConfig(n_particles=200, intervals="cloud"))
    assert pure.sandwich is None  # "cloud" is the particles' own std (eq. 14)


class _ModelWithError:
    """The analytic stand-in with a stated metamodel error ``K_res`` (its residuals)."""

    def __init__(self) -> None:
        from formtwin.metamodel import ResidualModel

        self._m = analytic_model()
        t = np.arange(self._m.spec.n_t)
        k_res = 4.0 * np.exp(-0.5 * ((t[:, None] - t[None, :]) / 6.0) ** 2)
        self.residuals = ResidualModel(k_res, np.zeros(len(k_res)), 0.01 * np.eye(2),
                                       np.zeros(2), k=5, n=100)
        self.fit_id, self.calibration = "0123456789abcdef", None

    def __getattr__(self, name: str) -> object:
        return getattr(self._m, name)


def _run(intervals: str, deviation: bool = False, mu_known: bool = True
         ) -> tuple[Tracker, list]:
    model = _ModelWithError()
    cfg = TrackerConfig(n_particles=200, estimate_deviation=deviation, n_mc=500, seed=3,
                        intervals=intervals, mu_known=mu_known)
    tr = build_tracker(model, cfg)  # type: ignore[arg-type]
    return tr, [tr.step(c) for c in interior_curves(model._m, n=8)]


@pytest.mark.parametrize("deviation", [False, True])
def test_sandwich_changes_only_the_reported_std(deviation: bool) -> None:
    """Same seed: particles, weights, means, angles, ESS, evidence, fit and health are
    bit for bit those of the cloud's intervals; the std only grow (gated: by a part)."""
    cloud, ec = _run("cloud", deviation)
    sand, es = _run("sandwich", deviation)
    gated, eg = _run("gated", deviation)
    for tr in (sand, gated):
        np.testing.assert_array_equal(tr.particles, cloud.particles)
        np.testing.assert_array_equal(tr.filter.logw, cloud.filter.logw)
        np.testing.assert_array_equal(tr.final_angle(np.zeros(3)), cloud.final_angle(np.zeros(3)))
    for a, b, c in zip(ec, es, eg, strict=True):
        for e in (b, c):
            for key in ("mean", "angles_mean"):
                np.testing.assert_array_equal(getattr(e, key), getattr(a, key))
            assert (e.ess, e.loglik, e.fit, e.health) == (a.ess, a.loglik, a.fit, a.health)
        assert np.all(b.std >= a.std) and np.all(b.angles_std >= a.angles_std)
        assert np.all(c.std >= a.std) and np.all(c.std <= b.std * (1 + 1e-12))
    assert np.any(es[-1].std[:7] > 1.05 * ec[-1].std[:7])
    assert np.any(es[-1].angles_std > ec[-1].angles_std)
    if not deviation:
        np.testing.assert_array_equal(es[-1].std[10:], 0.0)  # theta_d is not estimated


def test_sandwich_tracker_continues_bit_for_bit() -> None:
    """Restored from its state bytes (the sensitivity G and the last Jacobians in the
    model state) a tracker reports the same std as the original."""
    model = _ModelWithError()
    tr, _ = _run("sandwich", mu_known=False)  # G and G_mu
    back = Tracker.from_state_bytes(tr.state_bytes(), model, tr.measurement)  # type: ignore[arg-type]
    curves = interior_curves(model._m, n=6, seed=2)
    for c in curves:
        a, b = tr.step(c), back.step(c)
        np.testing.assert_array_equal(a.std, b.std)
        np.testing.assert_array_equal(a.angles_std, b.angles_std)
    with pytest.raises(ValueError, match="intervals"):
        TrackerConfig(intervals="wide")
    assert TrackerConfig.from_json(TrackerConfig(intervals="gated").to_json()).intervals == \
        "gated"


def test_calibrated_intervals_add_the_floors_of_the_metamodels_calibration(
        tmp_path: object, monkeypatch: pytest.MonkeyPatch) -> None:
    """std = sqrt(cloud std^2 + b^2) with the floors b of the calibration learned for this
    metamodel's fit id (its diag(K_res) to the sanity check's tolerance: the same fit on
    another BLAS); another fit's calibration, or one whose K_res is off, adds nothing."""
    import json
    from pathlib import Path

    from formtwin.tracker import intervals

    model = _ModelWithError()
    floors = np.linspace(0.01, 0.18, 18)
    signature = intervals.residual_signature(model)
    assert signature is not None
    cal = {"k_res_diag": list(signature * (1 + 4e-4)), "model_version": "test",
           "fit_id": model.fit_id,
           "no_deviation": {"floors": list(floors), "angle_floors": [0.2, 0.3]},
           "deviation": {"floors": list(2 * floors), "angle_floors": [0.4, 0.6]}}
    path = Path(str(tmp_path)) / "cal.json"
    path.write_text(json.dumps(cal))
    monkeypatch.setattr(intervals, "CALIBRATION_PATH", path)
    cloud, ec = _run("cloud", True)
    calib, ek = _run("calibrated", True)
    for a, b in zip(ec, ek, strict=True):
        np.testing.assert_array_equal(b.mean, a.mean)
        np.testing.assert_allclose(b.std, np.sqrt(a.std**2 + (2 * floors) ** 2), rtol=1e-12)
        np.testing.assert_allclose(b.angles_std, np.sqrt(a.angles_std**2 + [0.16, 0.36]),
                                   rtol=1e-12)
    assert {e.intervals for e in ek} == {"calibrated"} and ec[0].intervals == "cloud"
    for change in ({"fit_id": "fedcba9876543210"},  # another fit
                   {"k_res_diag": list(signature * 1.05)}):  # same id, other numbers
        path2 = Path(str(tmp_path)) / "other.json"
        path2.write_text(json.dumps(cal | change))
        monkeypatch.setattr(intervals, "CALIBRATION_PATH", path2)
        _, eo = _run("calibrated", True)
        np.testing.assert_array_equal(eo[-1].std, ec[-1].std)
        assert eo[-1].intervals == "uncalibrated"


def test_learned_floors_give_the_target_coverage_on_their_data() -> None:
    """Errors with a bias the std does not show: after the floors the 90 % intervals hold
    90 % of the errors (up to the quantile's interpolation), columns already covered get 0."""
    from formtwin.study.calibrate import learn_floors
    from formtwin.study.metrics import Z90

    rng = np.random.default_rng(0)
    std = np.c_[np.full(4000, 1.0), np.full(4000, 1.0)]
    err = np.c_[3.0 + rng.standard_normal(4000), 0.5 * rng.standard_normal(4000)]
    b = learn_floors(err, std)
    inside = np.abs(err) <= Z90 * np.sqrt(std**2 + b**2)
    assert inside[:, 0].mean() == pytest.approx(0.9, abs=1e-3)
    assert b[1] == 0.0 and b[0] > 1.0


@pytest.mark.parametrize("learn_residuals", [False, True])
def test_shipped_calibration_is_complete_and_learned_off_the_study_data(
        learn_residuals: bool) -> None:
    """The package's floors (one file per ``learn_residuals`` setting, learned with it):
    18 + 2 non-negative numbers per tracker configuration, constant and fit-gated, none for
    theta_d without the deviation model, learned on pseudo-data of another study seed."""
    import json

    from formtwin.study.calibrate import SEED
    from formtwin.study.run import StudySettings
    from formtwin.tracker.intervals import calibration_path, learned_for

    cal = json.loads(calibration_path(learn_residuals).read_text())
    assert learned_for(cal) is learn_residuals
    assert cal["settings"]["seed"] == SEED != StudySettings().seed
    assert len(cal["k_res_diag"]) == 101
    assert min(cal["k_res_diag"]) >= 0 and max(cal["k_res_diag"]) > 0
    for key in ("no_deviation", "deviation"):
        floors, angles = np.array(cal[key]["floors"]), np.array(cal[key]["angle_floors"])
        assert floors.shape == (18,) and angles.shape == (2,)
        assert np.all(floors >= 0) and np.all(angles >= 0) and np.all(np.isfinite(floors))
    np.testing.assert_array_equal(cal["no_deviation"]["floors"][10:], 0.0)
    gate = cal["fit_gate"]  # the default's fit gate, learned in the same calibration
    assert gate["d0"] > 0 and 0 < gate["ewma"] <= 1 and gate["runs"] > 0
    for key in ("no_deviation", "deviation"):
        floors = np.array(cal[key]["fit_floors"])
        assert floors.shape == (18,) and np.all(np.isfinite(floors)) and np.all(floors >= 0)
        assert cal[key]["fit_s_max"] > 0
    np.testing.assert_array_equal(cal["no_deviation"]["fit_floors"][10:], 0.0)


def _calibration_file(tmp_path: object, model: object, floors: np.ndarray) -> object:
    """A calibration for ``model`` with constant floors and fit-gated ones (``d0`` = 1)."""
    import json
    from pathlib import Path

    from formtwin.tracker import intervals

    signature = intervals.residual_signature(model)
    assert signature is not None
    entry = {"floors": list(floors), "angle_floors": [0.2, 0.3],
             "fit_floors": list(floors / 2), "fit_angle_floors": [0.1, 0.15], "fit_s_max": 50.0}
    cal = {"k_res_diag": list(signature), "model_version": "test", "fit_id": model.fit_id,
           "fit_gate": {"d0": 1.0, "ewma": 0.3}, "no_deviation": entry, "deviation": entry}
    path = Path(str(tmp_path)) / "cal_fit.json"
    path.write_text(json.dumps(cal))
    return path


def test_fit_gated_floors_scale_with_the_excess_running_fit_distance(
        tmp_path: object, monkeypatch: pytest.MonkeyPatch) -> None:
    """``calibrated_fit``: std^2 = cloud std^2 + s_i b_fit^2 with s_i = clip(E_i - d0, 0,
    s_max), E_i the running mean of the steps' fit distances (recomputed here by its
    definition); particles, means, ESS, fit as with the cloud's intervals; a tracker
    restored from its state continues with the same running mean."""
    from formtwin.tracker import intervals

    model = _ModelWithError()
    floors = np.linspace(0.01, 0.18, 18)
    monkeypatch.setattr(intervals, "CALIBRATION_PATH",
                        _calibration_file(tmp_path, model, floors))
    cloud, ec = _run("cloud", True)
    gated, eg = _run("calibrated_fit", True)
    np.testing.assert_array_equal(gated.particles, cloud.particles)
    num = den = 0.0
    scales = []
    for a, b in zip(ec, eg, strict=True):
        np.testing.assert_array_equal(b.mean, a.mean)
        assert (b.ess, b.loglik, b.fit) == (a.ess, a.loglik, a.fit)
        num, den = 0.7 * num + 0.3 * a.fit.distance2, 0.7 * den + 0.3
        s = min(max(num / den - 1.0, 0.0), 50.0)
        scales.append(s)
        np.testing.assert_allclose(b.std, np.sqrt(a.std**2 + s * (floors / 2) ** 2),
                                   rtol=1e-12)
        np.testing.assert_allclose(b.angles_std**2, a.angles_std**2 + s * np.array(
            [0.01, 0.0225]), rtol=1e-12)
    assert max(scales) > 0  # the test's curves are not the model's: the gate opens
    back = Tracker.from_state_bytes(gated.state_bytes(), model, gated.measurement)  # type: ignore[arg-type]
    for c in interior_curves(model._m, n=4, seed=2):
        x, y = gated.step(c), back.step(c)
        np.testing.assert_array_equal(x.std, y.std)


def test_fit_gated_floors_without_a_gate_in_the_calibration_use_the_constant_floors(
        tmp_path: object, monkeypatch: pytest.MonkeyPatch) -> None:
    """A calibration without a fit gate (from before the gate, or where the gate was 0 on
    rows that need floors): ``calibrated_fit`` adds the constant floors, ungated."""
    import json

    from formtwin.tracker import intervals

    model = _ModelWithError()
    path = _calibration_file(tmp_path, model, np.full(18, 0.1))
    cal = json.loads(path.read_text())  # type: ignore[attr-defined]
    del cal["fit_gate"]
    path.write_text(json.dumps(cal))  # type: ignore[attr-defined]
    monkeypatch.setattr(intervals, "CALIBRATION_PATH", path)
    _, ec = _run("cloud", True)
    _, eg = _run("calibrated_fit", True)
    np.testing.assert_allclose(eg[-1].std, np.sqrt(ec[-1].std ** 2 + 0.1**2), rtol=1e-12)
    np.testing.assert_allclose(eg[-1].angles_std**2, ec[-1].angles_std**2 + [0.04, 0.09],
                               rtol=1e-12)


def test_floors_for_another_deviation_layout_report_the_cloud_with_a_warning(
        tmp_path: object, monkeypatch: pytest.MonkeyPatch,
        caplog: pytest.LogCaptureFixture) -> None:
    """A calibration learned for another number of deviation knots (floors for 14
    estimated variables, this tracker has 18): the default tracker still runs, reports the
    cloud's std and says why (it raised a ValueError before)."""
    from formtwin.tracker import intervals

    model = _ModelWithError()
    monkeypatch.setattr(intervals, "CALIBRATION_PATH",
                        _calibration_file(tmp_path, model, np.full(14, 0.1)))
    _, ec = _run("cloud", True)
    with caplog.at_level("WARNING", logger=intervals.__name__):
        for setting in ("calibrated", "calibrated_fit"):
            _, eo = _run(setting, True)
            np.testing.assert_array_equal(eo[-1].std, ec[-1].std)
    assert "floors for 14 estimated variables, this tracker estimates 18" in caplog.text


def test_gated_floors_give_the_target_coverage_on_their_data() -> None:
    """Errors whose bias grows like sqrt(s): floors per unit of s hold 90 % of the errors;
    rows with s = 0 need none (their errors are within the cloud's std)."""
    from formtwin.study.calibrate import learn_floors
    from formtwin.study.metrics import Z90

    rng = np.random.default_rng(1)
    s = np.r_[np.zeros(1000), rng.uniform(1.0, 9.0, 3000)]
    std = np.ones((4000, 1))
    err = (np.sqrt(s) * 2.0 * rng.standard_normal(4000) + 0.3 * rng.standard_normal(4000))[:, None]
    b = learn_floors(err, std, scale=s)
    inside = np.abs(err[:, 0]) <= Z90 * np.sqrt(1.0 + s * b[0] ** 2)
    assert inside.mean() == pytest.approx(0.9, abs=1e-3)
    assert inside[:1000].all()  # no floor needed where the gate is shut


def test_gated_floors_follow_fit_ewma_and_gate_scale_through_gaps() -> None:
    """The floors' gate, updated one distance at a time, is :func:`fit_ewma` and
    :func:`gate_scale` of the whole sequence: non-finite distances (a collapsed step) leave
    the running mean as it was, before the first finite one the gate is shut."""
    from formtwin.tracker.intervals import Floors, fit_ewma, gate_scale

    fl = Floors.__new__(Floors)
    fl.gated, fl.ewma, fl.d0, fl.a, fl.s_max = True, (0.0, 0.0), 1.5, 0.3, 4.0
    fl.b, fl.b_angles = np.full(3, 0.5), np.full(2, 0.25)
    d2 = np.array([np.inf, np.nan, 1.0, 2.5, np.inf, 9.0, 40.0, 0.2, 1e300, 3.0])
    E, end = fit_ewma(d2, fl.a)
    s_ref = np.asarray(gate_scale(E, fl.d0, fl.s_max))
    for d, s in zip(d2, s_ref, strict=True):
        std, astd = fl.apply(np.full(3, 0.1), np.full(2, 0.2), float(d))
        np.testing.assert_allclose(std, np.sqrt(0.01 + s * 0.25), rtol=1e-15)
        np.testing.assert_allclose(astd, np.sqrt(0.04 + s * 0.0625), rtol=1e-15)
    assert fl.ewma == pytest.approx(end, rel=1e-15)
    assert s_ref[0] == 0.0 and s_ref[-2] == fl.s_max  # shut at first, capped far out


def test_calibrations_are_found_only_for_their_learn_residuals_setting(
        tmp_path: object, monkeypatch: pytest.MonkeyPatch) -> None:
    """One calibration per ``learn_residuals`` setting, keyed by the setting it was learned
    for (``settings.tracker.learn_residuals``; none said: off): each setting gets its own
    file's floors, never the other's, also when the other's file is the only one."""
    import json
    from pathlib import Path

    from formtwin.tracker import intervals

    model = _ModelWithError()
    base = json.loads(Path(str(_calibration_file(tmp_path, model, np.full(18, 0.1))))
                      .read_text())
    off, on = Path(str(tmp_path)) / "off.json", Path(str(tmp_path)) / "on.json"
    off.write_text(json.dumps(base))  # no settings: learned without learn_residuals
    on.write_text(json.dumps(base | {"settings": {"tracker": {"learn_residuals": True}},
                                     "no_deviation": base["no_deviation"]
                                     | {"floors": list(np.full(18, 0.3))}}))
    monkeypatch.setattr(intervals, "CALIBRATION_PATH", off)
    monkeypatch.setattr(intervals, "LEARN_RESIDUALS_CALIBRATION_PATH", on)
    assert intervals.calibration_path(False) == off and intervals.calibration_path(True) == on
    b_off, _ = intervals.calibration_floors(model, False)
    b_on, _ = intervals.calibration_floors(model, False, learn_residuals=True)
    np.testing.assert_array_equal(b_off, 0.1)
    np.testing.assert_array_equal(b_on, 0.3)
    assert intervals.Floors(model, False, False, learn_residuals=True).b[0] == 0.3
    found = intervals.find_calibration(model, learn_residuals=True)
    assert found.source == "on.json" and intervals.learned_for(found.data or {})
    # each file holding the other setting's calibration: neither setting finds one
    monkeypatch.setattr(intervals, "CALIBRATION_PATH", on)
    monkeypatch.setattr(intervals, "LEARN_RESIDUALS_CALIBRATION_PATH", off)
    for learn in (False, True):
        cal = intervals.find_calibration(model, learn_residuals=learn)
        assert cal.data is None and "no interval calibration for fit" in cal.reason
        np.testing.assert_array_equal(intervals.Floors(model, False, False, learn).b, 0.0)
    assert "with learn_residuals" in intervals.find_calibration(model, True).reason


def test_gains_from_one_solve_are_the_two_inverses_of_the_formulas() -> None:
    """``_gains`` solves ``(I + P_pred J^T S^-1 J)`` once instead of inverting ``P_pred``
    and ``P_pred^-1 + J^T S^-1 J``: the same ``P_lin P_pred^-1`` and ``K`` to rounding,
    on covariances whose variances span six decades (as the tracker's state and theta_d)."""
    from formtwin.tracker.sandwich import _gains

    rng = np.random.default_rng(11)
    m, n_t = 6, 9
    scales = np.logspace(-3, 0, m)  # std: variances 1e-6 .. 1
    a = rng.standard_normal((m, m))
    P_prev = scales[:, None] * (a @ a.T / m + np.eye(m)) * scales[None, :]
    F, Q = rng.uniform(0.0, 1.0, m), (0.1 * scales) ** 2
    J = rng.standard_normal((n_t, m)) / scales
    S_inv_J = np.linalg.solve(np.diag(rng.uniform(0.5, 2.0, n_t)), J)
    info = J.T @ S_inv_J
    P_pred = np.diag(F) @ P_prev @ np.diag(F) + np.diag(Q)
    P_lin = np.linalg.inv(np.linalg.inv(P_pred) + info)
    M, K = _gains(P_prev, info, S_inv_J, F, Q)
    cond = np.linalg.cond(np.eye(m) + P_pred @ info)
    tol = 1e3 * cond * np.finfo(float).eps
    np.testing.assert_allclose(M, P_lin @ np.linalg.inv(P_pred), rtol=tol,
                               atol=tol * np.abs(M).max())
    assert K is not None
    np.testing.assert_allclose(K, P_lin @ S_inv_J.T, rtol=tol, atol=tol * np.abs(K).max())
    assert _gains(P_prev, info, None, F, Q)[1] is None
