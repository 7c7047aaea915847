"""The line's own residual moment learned online (``TrackerConfig.learn_residuals``): the
running moment against its closed form, the likelihood's base covariance ``Sigma + M``,
what it learns on curves with and without an error, state round trips and rollback."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from filter_refs import analytic_tracker, assert_continues_bit_for_bit, interior_curves
from scipy.special import logsumexp

from formtwin.tracker import Tracker, TrackerConfig
from formtwin.tracker.learned import EVERY, ResidualMoment


def test_moment_is_the_mean_outer_product_of_the_posterior_mean_residuals() -> None:
    rng = np.random.default_rng(0)
    n, n_t, steps = 40, 6, EVERY
    m = ResidualMoment(n_t)
    ref = np.zeros((n_t, n_t))
    for i in range(steps):
        r, ll, lw = rng.normal(size=(n, n_t)), rng.normal(size=n), rng.normal(size=n)
        r[3, 2], ll[[3, 5]] = np.nan, -np.inf  # particles without a likelihood do not count
        good = np.ones(n, bool)
        good[[3, 5]] = False
        w = np.exp(lw[good] + ll[good] - logsumexp(lw[good] + ll[good]))
        ref += np.outer(w @ r[good], w @ r[good])
        w_filter = np.exp(lw + ll - logsumexp(lw + ll))  # the filter's posterior weights
        assert m.add(r, w_filter) == (i + 1 == EVERY)  # folded every EVERY products
        if i + 1 < EVERY:
            assert not m.moment.any()  # the likelihood's M: as of the last fold
    np.testing.assert_allclose(m.moment, ref / steps, rtol=1e-12)
    assert not m.add(np.full((n, n_t), np.nan), w_filter) and m.n == steps  # nothing counts
    back = ResidualMoment(n_t)
    back.set_state(m.state())
    np.testing.assert_array_equal(back.moment, m.moment)
    with pytest.raises(ValueError, match="residual_total has 4 values"):
        back.set_state({"residual_total": [0.0] * 4, "residual_n": [1.0]})


def test_learns_the_error_the_model_cannot_explain_and_little_else() -> None:
    """On the stand-in model's own curves ``M`` stays a small part of ``Sigma``; with an
    independent error ``N(0, 4 Sigma)`` added to each curve it learns about that error
    (the filter absorbs little of it), and the likelihood's base covariance is
    ``Sigma + M`` after each refresh."""
    model, tr = analytic_tracker(learn_residuals=True)
    sigma = tr.measurement.covariance()
    curves = interior_curves(model, 4 * EVERY, seed=2)
    for c in curves[: 2 * EVERY]:
        tr.step(c)
    assert tr.ssm.learned.n == 2 * EVERY
    assert np.trace(tr.ssm.learned.moment) < 0.3 * np.trace(sigma)
    model, tr = analytic_tracker(learn_residuals=True)
    err = np.random.default_rng(5).multivariate_normal(np.zeros(len(sigma)), 4 * sigma,
                                                       len(curves))
    for c, e in zip(curves, err, strict=True):
        tr.step(c + e)
    ratio = np.trace(tr.ssm.learned.moment) / np.trace(4 * sigma)
    assert 0.8 < ratio < 1.5
    d = tr.ssm.discrepancy
    np.testing.assert_allclose(d.inverse @ d.inverse.T, sigma + tr.ssm.learned.moment,
                               rtol=1e-8, atol=1e-8 * np.abs(sigma).max())


def test_state_round_trip_and_rollback_keep_the_moment(monkeypatch: pytest.MonkeyPatch) -> None:
    model, tr = analytic_tracker(learn_residuals=True)
    curves = interior_curves(model, EVERY + 20, seed=3)
    for c in curves[: EVERY - 10]:
        tr.step(c)
    assert_continues_bit_for_bit(model, tr, curves[EVERY - 10:])  # across a refresh
    back = Tracker.from_state_bytes(tr.state_bytes(), model, tr.measurement)
    np.testing.assert_array_equal(back.ssm.learned.moment, tr.ssm.learned.moment)
    total, n, disc = tr.ssm.learned.total.copy(), tr.ssm.learned.n, tr.ssm.discrepancy
    recent = len(tr.ssm.learned.recent)

    def fail(*_: object) -> None:
        raise RuntimeError("model down")

    # the angles are predicted after the likelihood's update: a step failing there
    monkeypatch.setattr(type(model), "predict_angles", fail)
    with pytest.raises(RuntimeError, match="model down"):
        tr.step(curves[0])
    np.testing.assert_array_equal(tr.ssm.learned.total, total)
    assert tr.ssm.learned.n == n == EVERY and tr.ssm.discrepancy is disc
    assert len(tr.ssm.learned.recent) == recent == 20


def test_off_by_default_and_only_with_the_adaptive_likelihood() -> None:
    assert TrackerConfig().learn_residuals is False
    _, tr = analytic_tracker()
    assert tr.ssm.learned is None and "residual_total" not in tr.state().model
    with pytest.raises(ValueError, match="learn_residuals needs the adaptive likelihood"):
        dataclasses.replace(TrackerConfig(), likelihood="paper", learn_residuals=True)
