"""Conjugate learning of mu: the per-particle Normal update against its closed form."""

from __future__ import annotations

import numpy as np
import pytest

from formtwin.defaults import AnalyticModel
from formtwin.evolution import mu_predictive, mu_update
from formtwin.measurement import MeasurementModel
from formtwin.tracker import BendingSSM, TrackerConfig


def _closed_form(m0: np.ndarray, P0: np.ndarray, path: np.ndarray, sigma: np.ndarray,
                 rho: np.ndarray, x0_is_data: bool) -> tuple[np.ndarray, np.ndarray]:
    """Posterior of mu given a whole AR(1) path (n, d) in one batch: Normal prior times
    prod_i N(x_i - rho x_{i-1}; (1 - rho) mu, (1 - rho^2) sigma^2) [times N(x_0; mu, sigma^2)]."""
    a, q = 1.0 - rho, (1.0 - rho**2) * sigma**2
    y = path[1:] - rho * path[:-1]
    prec = 1.0 / P0 + len(y) * a**2 / q
    num = m0 / P0 + a * y.sum(axis=0) / q
    if x0_is_data:
        prec, num = prec + 1.0 / sigma**2, num + path[0] / sigma**2
    return num / prec, 1.0 / prec


def test_sequential_updates_equal_the_batch_posterior() -> None:
    rng = np.random.default_rng(0)
    d, n = 3, 60
    sigma, rho = np.array([1.0, 2.0, 0.5]), np.array([0.8, 0.95, 0.0])
    mu_true = np.array([1.0, -2.0, 3.0])
    path = np.empty((n, d))
    path[0] = mu_true + sigma * rng.standard_normal(d)
    for i in range(1, n):
        path[i] = ((1 - rho) * mu_true + rho * path[i - 1]
                   + np.sqrt(1 - rho**2) * sigma * rng.standard_normal(d))
    m0, P0 = np.zeros(d), np.full(d, 4.0)
    m, P = m0.copy(), P0.copy()
    for i in range(1, n):
        m, P = mu_update(m, P, path[i - 1], path[i], sigma, rho)
    ref_m, ref_P = _closed_form(m0, P0, path, sigma, rho, x0_is_data=False)
    np.testing.assert_allclose(m, ref_m, rtol=1e-12)
    np.testing.assert_allclose(P, ref_P, rtol=1e-12)
    # the predictive is the AR(1) step with mu integrated out: check by simulation
    x = np.tile(path[-1], (200_000, 1))
    mu = m + np.sqrt(P) * rng.standard_normal(x.shape)
    noise = np.sqrt(1 - rho**2) * sigma * rng.standard_normal(x.shape)
    draws = (1 - rho) * mu + rho * x + noise
    mean, var = mu_predictive(m, P, path[-1], sigma, rho)
    assert np.all(np.abs(draws.mean(0) - mean) < 4 * np.sqrt(var / 200_000))
    np.testing.assert_allclose(draws.var(0), var, rtol=0.02)


def test_bending_ssm_carries_the_closed_form_posterior_per_particle(
        model: AnalyticModel) -> None:
    """Each particle's (m, P) columns are the closed-form posterior of mu given its own
    state path, x_0 included, with the prior of U(mu_min, mu_max)'s mean and variance."""
    mm = MeasurementModel.from_monte_carlo(model, n=300, rng=np.random.default_rng(1))
    ssm = BendingSSM(model, mm, TrackerConfig(learn_mu=True, estimate_deviation=False))
    nx, na = ssm.n_x, ssm.n_aug
    rng = np.random.default_rng(2)
    x = ssm.sample_initial(4, rng)
    assert x.shape == (4, na + 2 * nx)
    paths = [x[:, :nx].copy()]
    for _ in range(25):
        x = ssm.sample_transition(x, rng)
        paths.append(x[:, :nx].copy())
    path = np.stack(paths)  # (n, particles, 7)
    st = model.spec.state
    m0, P0 = ssm.mu_prior
    np.testing.assert_allclose(m0, 0.5 * (st.mu_min + st.mu_max))
    np.testing.assert_allclose(P0, (st.mu_max - st.mu_min) ** 2 / 12)
    for k in range(4):
        ref_m, ref_P = _closed_form(m0, P0, path[:, k], st.sigma, st.rho, x0_is_data=True)
        np.testing.assert_allclose(x[k, na:na + nx], ref_m, rtol=1e-9)
        np.testing.assert_allclose(x[k, na + nx:], ref_P, rtol=1e-9)
    # the estimate's moments: mixture mean and total variance
    w = np.array([0.1, 0.2, 0.3, 0.4])
    mean, std = ssm.mu_moments(x, w)
    m, P = x[:, na:na + nx], x[:, na + nx:]
    np.testing.assert_allclose(mean, w @ m)
    np.testing.assert_allclose(std**2, w @ P + w @ (m - w @ m) ** 2)
    assert np.all(std > 0) and std == pytest.approx(np.sqrt(std**2))
