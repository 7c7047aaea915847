"""The calibrated likelihood: residual covariance added to fraction^2 K_MC, checked against
closed forms, a linear-Gaussian model with an exact (Kalman) posterior, and the metamodel's
k-fold residuals stored with it."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest
from filter_refs import kalman_filter
from scipy import stats

from formtwin.defaults import analytic_dataset
from formtwin.filters import SIR
from formtwin.measurement import MeasurementModel
from formtwin.metamodel import (
    POD,
    RBF,
    RESIDUAL_RULE,
    Metamodel,
    ResidualModel,
    calibrate,
    cross_validate,
)
from formtwin.tracker import TrackerConfig, build_measurement, build_tracker


def _spd(n: int, rng: np.random.Generator, scale: float) -> np.ndarray:
    a = rng.standard_normal((n, n))
    return scale * (a @ a.T / n + 0.1 * np.eye(n))


def test_covariance_is_fraction_squared_k_mc_plus_k_res_plus_sensor_noise() -> None:
    rng = np.random.default_rng(3)
    n_t = 15
    z = rng.standard_normal((800, 4)) @ rng.standard_normal((4, n_t)) * 5.0  # rank 4 K_MC
    k_res = _spd(n_t, rng, 0.7)
    mm = MeasurementModel.from_curves(z, fraction=0.5, extra_cov=k_res, sensor_noise=0.2,
                                      rel_tol=0.0, rel_floor=1e-12)
    k_mc = np.cov(z, rowvar=False)
    expected = 0.25 * k_mc + k_res + 0.04 * np.eye(n_t)
    np.testing.assert_allclose(mm.covariance(), expected, rtol=1e-9, atol=1e-9)
    model, obs = rng.standard_normal((6, n_t)), rng.standard_normal(n_t)
    ref = stats.multivariate_normal(np.zeros(n_t), expected).logpdf(obs - model)
    np.testing.assert_allclose(mm.loglik(model, obs), ref, rtol=1e-9)


def test_bad_extra_covariance_is_refused() -> None:
    z = np.random.default_rng(0).standard_normal((50, 6))
    with pytest.raises(ValueError, match="shape"):
        MeasurementModel.from_curves(z, extra_cov=np.eye(5))
    with pytest.raises(ValueError, match="symmetric"):
        MeasurementModel.from_curves(z, extra_cov=np.triu(np.ones((6, 6))))


class LinearGaussian:
    """x_i = A x_{i-1} + v, v ~ N(0, Q); observed curve y = H x + w, w ~ N(0, Sigma)."""

    def __init__(self, mm: MeasurementModel, H: np.ndarray, A: np.ndarray, Q: np.ndarray,
                 m0: np.ndarray, P0: np.ndarray) -> None:
        self.mm, self.H, self.A, self.Q, self.m0, self.P0 = mm, H, A, Q, m0, P0

    def sample_initial(self, n: int, rng: np.random.Generator) -> np.ndarray:
        return rng.multivariate_normal(self.m0, self.P0, n)

    def sample_transition(self, x: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        return x @ self.A.T + rng.multivariate_normal(np.zeros(len(self.m0)), self.Q, len(x))

    def loglik(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        return self.mm.loglik(x @ self.H.T, y)


def test_particle_posterior_and_evidence_match_the_kalman_filter() -> None:
    """With the calibrated covariance as the noise of a linear-Gaussian model, the SIR
    posterior mean/std and log-evidence match the exact Kalman filter."""
    rng = np.random.default_rng(11)
    n_t, d = 12, 2
    H = rng.standard_normal((n_t, d))  # ESS >= 3000 of 40000 at every step
    z = rng.standard_normal((600, 3)) @ rng.standard_normal((3, n_t))
    mm = MeasurementModel.from_curves(z, fraction=0.5, extra_cov=_spd(n_t, rng, 2.0),
                                      sensor_noise=0.5)
    R = mm.covariance()
    A, Q = np.diag([0.8, 0.9]), np.diag([0.3, 0.2])
    m0, P0 = np.zeros(d), np.eye(d)
    lg = LinearGaussian(mm, H, A, Q, m0, P0)
    x = rng.multivariate_normal(m0, P0)
    ys = []
    for _ in range(4):
        x = A @ x + rng.multivariate_normal(np.zeros(d), Q)
        ys.append(H @ x + rng.multivariate_normal(np.zeros(n_t), R))
    f = SIR(lg, 40_000, np.random.default_rng(5))
    f.initialise()  # the first step then moves the initial draw once, like the Kalman filter
    evidence_kf = evidence_pf = 0.0
    for y, (m, P, ev) in zip(ys, kalman_filter(A, Q, H, R, m0, P0, ys), strict=True):
        evidence_kf += ev
        s = f.step(y)
        evidence_pf += s.loglik
        sd = np.sqrt(np.diag(P))
        np.testing.assert_allclose(s.mean(), m, atol=0.05 * sd.max() + 0.02)
        np.testing.assert_allclose(s.std(), sd, rtol=0.05)
    assert evidence_pf == pytest.approx(evidence_kf, abs=0.1)


@pytest.fixture(scope="module")
def small_metamodel() -> tuple[Metamodel, object]:
    data = analytic_dataset(240, seed=2)
    return Metamodel(POD(n_modes=8), RBF(length_scales="box")).fit(data), data


def test_calibrate_stores_the_second_moment_of_held_out_residuals(
        small_metamodel: tuple[Metamodel, object], tmp_path: Path) -> None:
    mm, data = small_metamodel
    cv = cross_validate(mm, data, k=4, seed=1)  # type: ignore[arg-type]
    calibrate(mm, data, k=4, seed=1)  # type: ignore[arg-type]
    res = mm.residuals
    assert isinstance(res, ResidualModel) and res.k == 4 and res.n == 240
    r = cv.curves - cv.predicted_curves
    np.testing.assert_allclose(res.curve_cov, r.T @ r / len(r), rtol=1e-10)
    np.testing.assert_allclose(res.angle_mean, (cv.angles - cv.predicted_angles).mean(0))
    assert np.all(np.linalg.eigvalsh(res.curve_cov) > -1e-9)
    back = Metamodel.load(mm.save(tmp_path / "mm.npz"))
    assert back.residuals is not None
    np.testing.assert_array_equal(back.residuals.curve_cov, res.curve_cov)
    np.testing.assert_array_equal(back.residuals.angle_cov, res.angle_cov)
    assert back.residuals.rows == res.rows == RESIDUAL_RULE
    with np.load(tmp_path / "mm.npz", allow_pickle=False) as f:  # no pickles
        assert "residuals.curve_cov" in f.files


def test_calibrated_measurement_adds_k_res_to_the_papers(
        small_metamodel: tuple[Metamodel, object]) -> None:
    mm, data = small_metamodel
    if mm.residuals is None:
        calibrate(mm, data, k=4, seed=1)  # type: ignore[arg-type]
    assert mm.residuals is not None
    cfg = TrackerConfig(n_mc=500, n_particles=50, estimate_deviation=False,
                        likelihood="calibrated")
    paper = build_measurement(mm, dataclasses.replace(cfg, likelihood="paper"))
    cal = build_measurement(mm, cfg)
    assert TrackerConfig().likelihood == "adaptive"  # builds on the paper's (K_res apart)
    np.testing.assert_array_equal(
        build_measurement(mm, dataclasses.replace(cfg, likelihood="adaptive")).covariance(),
        paper.covariance())
    # the same Monte-Carlo curves: the difference is K_res up to the noise floors
    diff = cal.covariance() - paper.covariance() - mm.residuals.curve_cov
    floor = max(paper.s2, cal.s2)
    assert np.abs(diff).max() < 2 * floor
    # the predicted angle std includes the metamodel's angle error
    tr = build_tracker(mm, cfg, cal)
    np.testing.assert_allclose(tr.ssm.angle_error_var, np.diag(mm.residuals.angle_cov))
    e = tr.step(mm.predict_curves(data.inputs[:1])[0])  # type: ignore[attr-defined]
    assert np.all(e.angles_std >= np.sqrt(np.diag(mm.residuals.angle_cov)) - 1e-12)
    tr_paper = build_tracker(mm, dataclasses.replace(cfg, likelihood="paper"), paper)
    assert np.all(tr_paper.ssm.angle_error_var == 0)


def test_unknown_likelihood_is_refused() -> None:
    with pytest.raises(ValueError, match="likelihood"):
        TrackerConfig(likelihood="magic")
    with pytest.raises(ValueError, match="fraction"):
        TrackerConfig(fraction=0.0)
    assert math.isinf(TrackerConfig().nu)


def test_default_metamodel_recomputes_residuals_of_another_rule(
        small_metamodel: tuple[Metamodel, object], tmp_path: Path,
        monkeypatch: pytest.MonkeyPatch) -> None:
    """A cached metamodel whose residual statistics were made by another rule (or before
    the rule was stored) is refitted with the default rule's, and saved with them."""
    import formtwin.defaults as defaults

    mm, data = small_metamodel
    monkeypatch.setattr(defaults, "default_doe", lambda name, cache: data)
    calibrate(mm, data, k=4, seed=1, line=False)  # type: ignore[arg-type]
    assert mm.residuals is not None and mm.residuals.rows == "interior"
    mm.save(tmp_path / "metamodel_analytic.npz")
    again, path = defaults.default_metamodel(tmp_path, "analytic")
    assert again.residuals is not None and again.residuals.rows == RESIDUAL_RULE
    assert Metamodel.load(path).residuals.rows == RESIDUAL_RULE  # type: ignore[union-attr]
