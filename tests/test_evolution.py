"""State evolution (eq. 4-5), stationary law, jitter (eq. 10) and the box reflection."""

from __future__ import annotations

import numpy as np
import pytest

from formtwin.evolution import evolve, jitter, reflect, simulate, stationary
from formtwin.spec import load_spec


def test_long_ar1_sequence_reproduces_mu_sigma_rho() -> None:
    rng = np.random.default_rng(1)
    mu, sigma, rho = np.array([5.0, -1.0, 0.0]), np.array([2.0, 0.1, 1.0]), np.array(
        [0.8, 0.95, 0.0])
    n = 200_000
    xs = simulate(n, mu, sigma, rho, rng)
    # standard errors of an AR(1): var(mean) ~ sigma^2/n (1+rho)/(1-rho)
    se_mu = sigma * np.sqrt((1 + rho) / (1 - rho) / n)
    assert np.all(np.abs(xs.mean(0) - mu) < 5 * se_mu)
    np.testing.assert_allclose(xs.std(0), sigma, rtol=0.02)
    lag1 = np.array([np.corrcoef(xs[1:, j], xs[:-1, j])[0, 1] for j in range(3)])
    np.testing.assert_allclose(lag1, rho, atol=0.01)


def test_evolve_keeps_the_stationary_law_and_is_vectorised() -> None:
    rng = np.random.default_rng(2)
    mu, sigma, rho = np.array([1.0, 10.0]), np.array([0.5, 3.0]), np.array([0.9, 0.3])
    x = stationary(100_000, mu, sigma, rng)
    x1 = evolve(x, mu, sigma, rho, rng)
    assert x1.shape == (100_000, 2)
    assert np.all(np.abs(x1.mean(0) - mu) < 0.02 * sigma)
    np.testing.assert_allclose(x1.std(0), sigma, rtol=0.02)
    corr = [np.corrcoef(x[:, j], x1[:, j])[0, 1] for j in range(2)]
    np.testing.assert_allclose(corr, rho, atol=0.01)


def test_reflection_folds_into_the_box_and_is_identity_inside() -> None:
    lo, hi = np.array([0.0, -1.0]), np.array([1.0, 1.0])
    v = np.array([[0.3, 0.5], [1.25, -1.5], [-0.25, 3.5], [2.5, 1.0]])
    np.testing.assert_allclose(reflect(v, lo, hi), [[0.3, 0.5], [0.75, -0.5], [0.25, -0.5],
                                                    [0.5, 1.0]])
    rng = np.random.default_rng(3)
    w = reflect(rng.normal(0, 10, (10_000, 2)), lo, hi)
    assert np.all((w >= lo) & (w <= hi))


def test_truth_sequence_stays_in_table1_box() -> None:
    spec = load_spec()
    s = spec.state
    xs = simulate(5000, s.mu_max, s.sigma * 3, s.rho, np.random.default_rng(4), s.lo, s.hi)
    assert np.all((xs >= s.lo) & (xs <= s.hi))


def test_jitter_has_std_alpha_times_range_and_stays_in_box() -> None:
    spec = load_spec()
    p = spec.params
    rng = np.random.default_rng(5)
    theta = np.tile((p.lo + p.hi) / 2, (200_000, 1))
    moved = jitter(theta, p.lo, p.hi, rng, alpha=0.01)
    np.testing.assert_allclose((moved - theta).std(0), 0.01 * (p.hi - p.lo), rtol=0.01)
    assert np.all(np.abs((moved - theta).mean(0)) < 1e-4 * (p.hi - p.lo))
    edge = jitter(np.tile(p.hi, (1000, 1)), p.lo, p.hi, rng, alpha=0.05)
    assert np.all(edge <= p.hi) and np.all(edge >= p.lo)
    with pytest.raises(ValueError, match="alpha"):
        jitter(theta[:2], p.lo, p.hi, rng, alpha=-1)


def test_same_seed_same_sequence() -> None:
    a = simulate(50, np.zeros(2), np.ones(2), np.full(2, 0.5), np.random.default_rng(7))
    b = simulate(50, np.zeros(2), np.ones(2), np.full(2, 0.5), np.random.default_rng(7))
    np.testing.assert_array_equal(a, b)


def test_into_box_reflects_only_the_rows_that_left() -> None:
    """Rows inside the box are kept bit for bit (``reflect`` would round them through
    ``lo + (x - lo)``), rows with an entry outside are ``reflect``'s."""
    from formtwin.evolution import into_box

    rng = np.random.default_rng(3)
    lo, hi = np.array([0.1, -2.0, 3.0]), np.array([0.7, 5.0, 3.3])
    v = lo + (hi - lo) * rng.uniform(-0.3, 1.3, (2000, 3))
    out = into_box(v.copy(), lo, hi)
    left = np.any((v < lo) | (v > hi), axis=1)
    assert 0 < left.sum() < v.shape[0]
    np.testing.assert_array_equal(out[~left], v[~left])
    np.testing.assert_array_equal(out[left], reflect(v[left], lo, hi))
    assert np.all((out >= lo) & (out <= hi))


def test_tracker_transition_is_eq4_ar1_and_eq10_jitter_in_one_pass() -> None:
    """The tracker's transition draws ``x`` and ``theta, theta_d`` in one block: from one
    parent, ``x`` has the AR(1)'s mean ``(1 - rho) mu + rho x`` and std
    ``sqrt(1 - rho^2) sigma`` and theta the parent's value and ``alpha (hi - lo)`` (the
    parent in the box's middle: no reflection), each column independent."""
    from formtwin.defaults import analytic_model
    from formtwin.measurement import MeasurementModel
    from formtwin.tracker import TrackerConfig
    from formtwin.tracker.ssm import BendingSSM

    model = analytic_model()
    mm = MeasurementModel.from_monte_carlo(model, n=200, rng=np.random.default_rng(1))
    ssm = BendingSSM(model, mm, TrackerConfig(alpha=0.01))
    nx, na = ssm.n_x, ssm.n_aug
    parent = 0.5 * (ssm._lo + ssm._hi)
    parent[:nx] = ssm._mu + 0.3 * ssm._sigma
    n = 200_000
    x = ssm.sample_transition(np.repeat(parent[None, :], n, axis=0), np.random.default_rng(5))
    mean = np.r_[(1 - ssm._rho) * ssm._mu + ssm._rho * parent[:nx], parent[nx:na]]
    std = np.r_[np.sqrt(1 - ssm._rho**2) * ssm._sigma, 0.01 * (ssm._hi - ssm._lo)[nx:na]]
    assert np.all(np.abs(x[:, :na].mean(axis=0) - mean) <= 5 * std / np.sqrt(n))
    np.testing.assert_allclose(x[:, :na].std(axis=0), std, rtol=5 / np.sqrt(2 * n))
    corr = np.corrcoef(x[:, :na].T) - np.eye(na)
    assert np.abs(corr).max() < 5 / np.sqrt(n)
