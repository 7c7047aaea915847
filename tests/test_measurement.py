"""Measurement model: PPCA covariance, exact densities, rank deficiency, files."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from scipy import stats

from formtwin.defaults import AnalyticModel
from formtwin.measurement import MeasurementModel, ProcessModel
from formtwin.spec import load_spec


def low_rank_curves(n: int = 400, n_t: int = 20, r: int = 3, seed: int = 0) -> np.ndarray:
    """Curves in an r-dimensional affine span (like metamodel curves)."""
    rng = np.random.default_rng(seed)
    modes = np.linalg.qr(rng.standard_normal((n_t, r)))[0]
    coef = rng.standard_normal((n, r)) * np.array([10.0, 3.0, 1.0])[:r]
    return 50.0 + coef @ modes.T


def full_cov(mm: MeasurementModel) -> np.ndarray:
    u = mm.basis
    return (u * mm.lam) @ u.T + mm.s2 * (np.eye(mm.n_t) - u @ u.T)


def test_gaussian_matches_scipy_with_the_documented_covariance() -> None:
    rng = np.random.default_rng(1)
    z = rng.standard_normal((500, 12)) @ rng.standard_normal((12, 12))
    mm = MeasurementModel.from_curves(z, fraction=0.5, rel_tol=0.05, sensor_noise=0.3)
    assert 0 < mm.rank < 12
    model = rng.standard_normal((7, 12))
    obs = rng.standard_normal(12)
    ref = stats.multivariate_normal(np.zeros(12), full_cov(mm)).logpdf(obs - model)
    np.testing.assert_allclose(mm.loglik(model, obs), ref, rtol=1e-10)
    # (n_t,) and (N, n_t) observations agree
    np.testing.assert_allclose(mm.loglik(model, np.tile(obs, (7, 1))), ref, rtol=1e-10)


def test_full_rank_data_keeps_the_paper_covariance() -> None:
    rng = np.random.default_rng(2)
    z = rng.standard_normal((2000, 6)) * np.arange(1.0, 7.0)
    mm = MeasurementModel.from_curves(z, fraction=0.5, rel_floor=1e-3)
    assert mm.rank == 6  # nothing discarded: Sigma = K_MC / 4 + sigma_n^2 I
    k = 0.25 * np.cov(z.T)
    noise = 1e-3 * np.linalg.eigvalsh(k).max()
    np.testing.assert_allclose(full_cov(mm), k + noise * np.eye(6), rtol=1e-10, atol=1e-12)


def test_student_t_matches_scipy() -> None:
    rng = np.random.default_rng(3)
    z = rng.standard_normal((300, 8)) * np.arange(1.0, 9.0)
    mm = MeasurementModel.from_curves(z, nu=4.0)
    d = rng.standard_normal((5, 8)) * 3
    ref = stats.multivariate_t(np.zeros(8), full_cov(mm), df=4.0).logpdf(d)
    np.testing.assert_allclose(mm.loglik(np.zeros((5, 8)), d), ref, rtol=1e-10)
    # heavy tails: a far outlier costs much less than under the Gaussian
    g = MeasurementModel.from_curves(z)
    far = np.full((1, 8), 100.0)
    assert mm.loglik(np.zeros((1, 8)), far)[0] > g.loglik(np.zeros((1, 8)), far)[0] + 1e3


def test_rank_deficient_k_mc_gives_a_well_conditioned_likelihood() -> None:
    z = low_rank_curves()
    assert np.linalg.matrix_rank(np.cov(z.T)) == 3  # K_MC itself is singular
    mm = MeasurementModel.from_curves(z, sensor_noise=0.5)
    assert mm.rank == 3
    assert mm.s2 == pytest.approx(0.25)  # PPCA residual ~0, so the sensor floor rules
    cond = np.linalg.cond(full_cov(mm))
    assert cond < 1e6
    # an off-span curve (physics-model or deviated data) has a finite likelihood that
    # falls with its distance from the span, at the sensor-noise rate
    rng = np.random.default_rng(4)
    normal = rng.standard_normal(20)
    normal -= mm.basis @ (mm.basis.T @ normal)
    normal /= np.linalg.norm(normal)
    model = z[:1]
    ll = mm.loglik(model, model[0] + np.outer([0.0, 0.5, 1.0], normal))
    assert np.all(np.isfinite(ll))
    np.testing.assert_allclose(ll[0] - ll[1:], np.array([0.5, 1.0]) ** 2 / (2 * 0.25))
    # and an in-span offset is judged by the whitened principal-component term
    in_span = mm.basis[:, 0] * math.sqrt(mm.lam[0])
    assert mm.mahalanobis2(model, model[0] + in_span)[0] == pytest.approx(1.0)


def test_without_sensor_noise_the_floor_bounds_the_condition_number() -> None:
    mm = MeasurementModel.from_curves(low_rank_curves(), rel_floor=1e-6)
    assert np.linalg.cond(full_cov(mm)) <= 1e6 + 1.0001


def test_nan_model_rows_give_minus_inf_and_bad_shapes_raise() -> None:
    mm = MeasurementModel.from_curves(low_rank_curves())
    model = low_rank_curves(n=3)
    model[1, 4] = np.nan
    ll = mm.loglik(model, model[0])
    assert np.isneginf(ll[1]) and np.all(np.isfinite(ll[[0, 2]]))
    with pytest.raises(ValueError, match="expected"):
        mm.loglik(model, np.zeros(7))
    with pytest.raises(ValueError, match="do not vary"):
        MeasurementModel.from_curves(np.ones((10, 5)))


def test_save_load_round_trip(tmp_path: Path) -> None:
    mm = MeasurementModel.from_curves(low_rank_curves(), nu=5.0, sensor_noise=0.1)
    p = mm.save(tmp_path / "mm.npz")
    back = MeasurementModel.load(p)
    np.testing.assert_array_equal(back.basis, mm.basis)
    assert (back.s2, back.nu) == (mm.s2, mm.nu)
    z = low_rank_curves(n=4, seed=9)
    np.testing.assert_array_equal(back.loglik(z, z[0]), mm.loglik(z, z[0]))
    np.savez(tmp_path / "other.npz", a=np.zeros(3))
    with pytest.raises(ValueError, match="not a measurement-model file"):
        MeasurementModel.load(tmp_path / "other.npz")


def test_from_monte_carlo_on_the_analytic_model() -> None:
    spec = load_spec()
    model = AnalyticModel(spec)
    assert isinstance(model, ProcessModel)
    mm = MeasurementModel.from_monte_carlo(model, n=1500, rng=np.random.default_rng(0))
    assert mm.n_t == spec.n_t and 1 <= mm.rank < spec.n_t
    # the curve std is half the Monte-Carlo std along the top direction
    X = np.tile(spec.inputs.lo + 0.5 * (spec.inputs.hi - spec.inputs.lo), (2, 1))
    c = model.predict_curves(X)
    assert np.all(np.isfinite(mm.loglik(c, c[0])))
    with pytest.raises(ValueError, match="mu has shape"):
        MeasurementModel.from_monte_carlo(model, mu=np.zeros(3), n=10)
