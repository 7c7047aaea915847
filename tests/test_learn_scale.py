"""A factor on the likelihood covariance learned online (TrackerConfig(learn_scale=True))."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy import stats

from formtwin.defaults import AnalyticModel
from formtwin.measurement import MeasurementModel
from formtwin.tracker import Tracker, TrackerConfig
from formtwin.tracker.config import SCALES


@pytest.fixture(scope="module")
def mm(model: AnalyticModel) -> MeasurementModel:
    return MeasurementModel.from_monte_carlo(model, n=2000, rng=np.random.default_rng(3))


def test_scaled_loglik_is_the_gaussian_with_c_sigma(mm: MeasurementModel) -> None:
    rng = np.random.default_rng(0)
    model = rng.standard_normal((3, mm.n_t))
    obs = model[0] + rng.multivariate_normal(np.zeros(mm.n_t), mm.covariance())
    c = np.array([0.5, 2.0])
    got = mm.loglik_scaled(model, obs, c)
    for j, cj in enumerate(c):
        ref = stats.multivariate_normal(np.zeros(mm.n_t), cj * mm.covariance(),
                                        allow_singular=True).logpdf(obs - model)
        np.testing.assert_allclose(got[:, j], ref, rtol=1e-8)


@pytest.mark.parametrize("c_true", [1.0, 4.0])
def test_learned_scale_finds_the_noise_level(model: AnalyticModel, mm: MeasurementModel,
                                             c_true: float) -> None:
    """Curves with noise N(0, c_true Sigma) added: the scale posterior concentrates at c_true."""
    spec = model.spec
    cfg = TrackerConfig(n_particles=300, estimate_deviation=False, learn_scale=True, seed=2,
                        likelihood="paper")
    tr = Tracker(model, mm, cfg)
    run, curves = tr.ssm.simulate(120, np.random.default_rng(5))
    noise = np.random.default_rng(6).multivariate_normal(
        np.zeros(spec.n_t), c_true * mm.covariance(), len(curves))
    tr.run(curves + noise)
    post = np.exp(tr.ssm.scale_logpost)
    assert post.sum() == pytest.approx(1.0)
    assert tr.scale is not None and c_true / 1.5 < tr.scale < 1.5 * c_true, (tr.scale, post)
    assert SCALES[int(np.argmax(post))] == pytest.approx(c_true)


def test_checkpoint_with_learned_scale_is_bit_for_bit(tmp_path: Path, model: AnalyticModel,
                                                      mm: MeasurementModel) -> None:
    cfg = TrackerConfig(n_particles=80, estimate_deviation=False, learn_scale=True, seed=1,
                        likelihood="calibrated")
    a = Tracker(model, mm, cfg)
    _, curves = a.ssm.simulate(10, np.random.default_rng(1))
    a.run(curves[:5])
    b = Tracker.from_state_bytes(a.state_bytes(), model, mm)
    c = Tracker.restore(a.checkpoint(tmp_path / "ck.npz"), model, mm)
    np.testing.assert_array_equal(b.ssm.scale_logpost, a.ssm.scale_logpost)
    ra, rb, rc = a.run(curves[5:]), b.run(curves[5:]), c.run(curves[5:])
    np.testing.assert_array_equal(ra.mean, rb.mean)
    np.testing.assert_array_equal(ra.mean, rc.mean)
    np.testing.assert_array_equal(a.ssm.scale_logpost, c.ssm.scale_logpost)
    with pytest.raises(ValueError, match="Gaussian"):
        TrackerConfig(learn_scale=True, nu=5.0, likelihood="calibrated")
