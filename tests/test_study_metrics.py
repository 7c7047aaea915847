"""Honest study metrics: skill against the prior-only guess, coverage of 90 % intervals."""

from __future__ import annotations

import numpy as np

from formtwin.spec import ProcessSpec
from formtwin.study.metrics import Z90, coverage, prior_estimate, run_scores, skill


def test_coverage_of_an_honest_gaussian_is_90_percent() -> None:
    rng = np.random.default_rng(0)
    n = 200_000
    std = rng.uniform(0.5, 2.0, (n, 3))
    truth = rng.standard_normal((n, 3)) * std
    cov = coverage(np.zeros((n, 3)), std, truth, window=n)
    np.testing.assert_allclose(cov, 0.90, atol=0.004)
    # half the std: P(|Z| < Z90 / 2) = 0.590
    np.testing.assert_allclose(coverage(np.zeros((n, 3)), std / 2, truth, window=n), 0.590,
                               atol=0.005)
    assert Z90 == np.float64(1.6448536269514722)
    # NaN rows do not count
    m = np.zeros((4, 1))
    m[0] = np.nan
    assert coverage(m, np.ones((4, 1)), np.array([[0.0], [0.0], [5.0], [0.0]]), 4)[0] == 2 / 3


def test_skill_is_zero_for_the_prior_guess_and_one_for_the_truth(spec: ProcessSpec) -> None:
    rng = np.random.default_rng(1)
    n = 300
    lo, hi = spec.augmented.lo, spec.augmented.hi
    truth = lo + (hi - lo) * rng.random((n, len(lo)))
    angles = rng.standard_normal((n, 2)) + [90.0, 80.0]
    mu = spec.state.mu_mid
    prior_ang = np.array([90.2, 79.9])
    guess = np.tile(prior_estimate(spec, mu), (n, 1))
    s0 = skill(spec, guess, truth, np.tile(prior_ang, (n, 1)), angles, mu, prior_ang, n)
    np.testing.assert_allclose(s0, 0.0, atol=1e-12)
    s1 = skill(spec, truth, truth, angles, angles, mu, prior_ang, n)
    np.testing.assert_allclose(s1, 1.0)
    # halfway between guess and truth: RMSE halves, skill 1/2
    half = skill(spec, 0.5 * (guess + truth), truth, angles, angles, mu, prior_ang, n)
    np.testing.assert_allclose(half[:18], 0.5, atol=1e-12)
    run = {"mean": truth, "std": np.ones_like(truth), "angles_mean": angles,
           "angles_std": np.ones((n, 2)), "ess": np.full(n, 7.0), "loglik": np.full(n, -2.0)}
    sc = run_scores(spec, run, truth, angles, mu, prior_ang, deviation=False, window=n)
    assert np.isnan(sc["skill"][10:18]).all() and np.isnan(sc["coverage"][10:18]).all()
    assert np.all(sc["coverage"][:10] == 1.0) and float(sc["ess"]) == 7.0
    assert float(sc["log_evidence"]) == -2.0 * n
