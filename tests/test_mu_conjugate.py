"""Conjugate learning of mu: the per-particle Normal update against its closed form."""

from __future__ import annotations

import numpy as np
import pytest

from formtwin.defaults import AnalyticModel
from formtwin.evolution import mu_predictive, mu_update, truncated_moments, truncated_normal
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


@pytest.mark.parametrize("prior", ["normal", "uniform"])
def test_bending_ssm_carries_the_closed_form_posterior_per_particle(
        model: AnalyticModel, prior: str) -> None:
    """Each particle's (m, P) columns are the closed-form posterior of mu given its own
    state path, x_0 included: with the Normal prior of U(mu_min, mu_max)'s mean and
    variance, or (uniform prior) the flat-prior Normal that the range truncates."""
    mm = MeasurementModel.from_monte_carlo(model, n=300, rng=np.random.default_rng(1))
    ssm = BendingSSM(model, mm, TrackerConfig(learn_mu=True, estimate_deviation=False,
                                              mu_prior=prior))
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
    if prior == "uniform":
        m0, P0 = np.zeros(nx), np.full(nx, np.inf)  # flat: 1/P0 = 0
    for k in range(4):
        ref_m, ref_P = _closed_form(m0, P0, path[:, k], st.sigma, st.rho, x0_is_data=True)
        np.testing.assert_allclose(x[k, na:na + nx], ref_m, rtol=1e-9)
        np.testing.assert_allclose(x[k, na + nx:], ref_P, rtol=1e-9)
    # the estimate's moments: mixture mean and total variance of the posteriors
    w = np.array([0.1, 0.2, 0.3, 0.4])
    mean, std = ssm.mu_moments(x, w)
    m, P = x[:, na:na + nx], x[:, na + nx:]
    if prior == "uniform":
        m, P = truncated_moments(m, P, st.mu_min, st.mu_max)
        assert np.all((mean >= st.mu_min) & (mean <= st.mu_max))
    np.testing.assert_allclose(mean, w @ m)
    np.testing.assert_allclose(std**2, w @ P + w @ (m - w @ m) ** 2)
    assert np.all(std > 0) and std == pytest.approx(np.sqrt(std**2))


def test_uniform_prior_posterior_is_the_truncated_normal_by_quadrature() -> None:
    """Prior U(lo, hi) times the AR(1) likelihood of a path, normalised on a fine grid:
    its mean and variance are truncated_moments of the flat-prior (m, P), also when the
    path's evidence lies far outside the range (the posterior piles up at a bound)."""
    rng = np.random.default_rng(3)
    sigma, rho = np.array([1.0]), np.array([0.8])
    lo, hi = np.array([0.0]), np.array([2.0])
    grid = np.linspace(lo[0], hi[0], 200_001)
    for mu_true, n in ((1.0, 30), (2.6, 200), (-0.5, 400)):
        path = np.empty((n, 1))
        path[0] = mu_true + sigma * rng.standard_normal(1)
        for i in range(1, n):
            path[i] = ((1 - rho) * mu_true + rho * path[i - 1]
                       + np.sqrt(1 - rho**2) * sigma * rng.standard_normal(1))
        m, P = _closed_form(np.zeros(1), np.full(1, np.inf), path, sigma, rho, True)
        a, q = 1 - rho, (1 - rho**2) * sigma**2
        y = path[1:, 0] - rho[0] * path[:-1, 0]
        logp = (-0.5 * ((y[None, :] - a[0] * grid[:, None]) ** 2).sum(1) / q[0]
                - 0.5 * (path[0, 0] - grid) ** 2 / sigma[0] ** 2)
        p = np.exp(logp - logp.max())
        p[[0, -1]] *= 0.5  # trapezoidal rule
        p /= p.sum()
        ref_mean = p @ grid
        ref_var = p @ (grid - ref_mean) ** 2
        mean, var = truncated_moments(m, P, lo, hi)
        assert mean[0] == pytest.approx(ref_mean, abs=1e-6 * (hi[0] - lo[0]))
        assert var[0] == pytest.approx(ref_var, rel=1e-3)
        draws = truncated_normal(np.full((100_000, 1), m[0]), np.full((100_000, 1), P[0]),
                                 lo, hi, rng)
        assert np.all((draws >= lo) & (draws <= hi))
        assert abs(draws.mean() - ref_mean) < 5 * np.sqrt(ref_var / 100_000)
        assert draws.var() == pytest.approx(ref_var, rel=0.03)
