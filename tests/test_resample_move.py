"""The resample-move hooks of the bending model: the reflected transition density, a
likelihood without side effects, and a tracker with the move filter that checkpoints."""

from __future__ import annotations

import math

import numpy as np
import pytest

from formtwin.defaults import AnalyticModel
from formtwin.evolution import reflect
from formtwin.measurement import MeasurementModel
from formtwin.tracker import BendingSSM, Tracker, TrackerConfig
from formtwin.tracker.moves import _reflected_logpdf


def test_reflected_density_is_normalised_and_matches_reflected_draws() -> None:
    """exp(_reflected_logpdf) / (std sqrt(2 pi)) is the density of reflect(mean + std eps):
    it integrates to 1 over the box and matches a histogram of draws, near a bound too."""
    lo, hi = np.zeros(1), np.ones(1)
    for mean, std in ((0.05, 0.2), (0.5, 0.1), (0.97, 0.3)):
        grid = np.linspace(0.0, 1.0, 20_001)[:, None]
        dens = np.exp(_reflected_logpdf(grid, np.array([mean]), np.array([std]), lo, hi)) \
            / (std * math.sqrt(2 * math.pi))
        assert np.trapezoid(dens, grid[:, 0]) == pytest.approx(1.0, abs=2e-3)
        draws = reflect(mean + std * np.random.default_rng(0).standard_normal(400_000),
                        lo, hi)
        hist, edges = np.histogram(draws, bins=20, range=(0.0, 1.0), density=True)
        centre = 0.5 * (edges[:-1] + edges[1:])
        ref = np.interp(centre, grid[:, 0], dens)
        np.testing.assert_allclose(hist, ref, rtol=0.03, atol=0.02)


def test_loglik_fixed_is_loglik_without_side_effects(model: AnalyticModel) -> None:
    mm = MeasurementModel.from_monte_carlo(model, n=300, rng=np.random.default_rng(1))
    ssm = BendingSSM(model, mm, TrackerConfig(estimate_deviation=True))
    rng = np.random.default_rng(2)
    x = ssm.sample_initial(50, rng)
    y = model.predict_curves(x[:1, : ssm.n_in])[0]
    ll = ssm.loglik(x, y)
    r = ssm.last_residuals().copy()
    x2 = ssm.sample_transition(x, rng)
    np.testing.assert_allclose(ssm.loglik_fixed(x, y), ll, rtol=1e-12)
    ssm.loglik_fixed(x2, y)
    np.testing.assert_array_equal(ssm.last_residuals(), r)  # untouched
    # the transition density is highest at the parent's own AR(1) mean
    assert ssm.move_mask[: ssm.n_aug].all() and not ssm.move_mask[ssm.n_aug:].any()
    lt = ssm.log_transition(x, x2)
    assert lt.shape == (50,) and np.all(np.isfinite(lt))


def test_tracker_with_the_move_filter_restores_bit_for_bit(model: AnalyticModel) -> None:
    mm = MeasurementModel.from_monte_carlo(model, n=500, rng=np.random.default_rng(1))
    cfg = TrackerConfig(n_particles=200, filter="move", estimate_deviation=False, seed=3)
    tr = Tracker(model, mm, cfg)
    ssm = tr.ssm
    run, curves = ssm.simulate(30, np.random.default_rng(4))
    tr.run(curves[:15])
    assert 0.0 < tr.filter.acceptance <= 1.0  # type: ignore[attr-defined]
    copy = Tracker.from_state_bytes(tr.state_bytes(), model, mm)
    a, b = tr.run(curves[15:]), copy.run(curves[15:])
    np.testing.assert_array_equal(a.mean, b.mean)
    np.testing.assert_array_equal(a.std, b.std)
    err = np.abs(a.mean[-5:, : ssm.n_x] - run.x[-5:]) / model.spec.state.sigma
    assert float(np.median(err)) < 3.0  # it tracks (the prior's spread is ~1 sigma)
