"""The measured final angle as a second measurement (formtwin.tracker.fusion): the reweighting
against the closed form (Gaussian likelihood times the current weights, normalised; the
evidence is the normalising constant), the suggestion predicts with the new weights, bad
inputs leave the tracker untouched."""

from __future__ import annotations

import math

import numpy as np
import pytest

from formtwin.control import Actuator, Feedforward
from formtwin.defaults import analytic_model
from formtwin.tracker import TrackerConfig, build_tracker
from formtwin.tracker.fusion import angle_sd, update_angle


def _tracker():  # type: ignore[no-untyped-def]
    model = analytic_model()
    spec = model.spec
    tr = build_tracker(model, TrackerConfig(n_particles=200, n_mc=1000,
                                            estimate_deviation=False, seed=2))
    tr.step(model.predict_curves((0.5 * (spec.inputs.lo + spec.inputs.hi))[None])[0])
    return tr, model


def test_reweighting_is_the_gaussian_likelihood() -> None:
    tr, _ = _tracker()
    a = tr.final_angle(np.array([0.0]))[:, 0]
    logw0 = tr.filter.logw.copy()
    angle, sd, off = float(a.mean() + a.std()), 0.5 * float(a.std()), 0.1 * float(a.std())
    inc = update_angle(tr, angle, 0.0, sd=sd, offset=off)
    lik = np.exp(-0.5 * ((angle - a - off) / sd) ** 2) / (sd * math.sqrt(2 * math.pi))
    w = np.exp(logw0) * lik
    assert inc == pytest.approx(math.log(w.sum()), rel=1e-10)
    np.testing.assert_allclose(np.exp(tr.filter.logw), w / w.sum(), rtol=1e-9, atol=1e-300)
    # the weight moves to the particles nearer the measurement: the likelihood falls with
    # the distance d, so the posterior's mean d is at most the prior's for any cloud
    # (Chebyshev's sum inequality; the mean angle itself may move away from the
    # measurement when the cloud is multimodal); the spread shrinks
    wn = w / w.sum()
    d = np.abs(angle - off - a)
    w0 = np.exp(logw0) / np.exp(logw0).sum()
    assert wn @ d < w0 @ d
    assert wn @ (a - wn @ a) ** 2 < a.var()
    # suggest() predicts with the new weights
    s = tr.suggest(Feedforward(float(a.mean()), Actuator(-1.0, 1.0)))
    at = tr.final_angle(np.array([s.u]))[:, 0]
    assert s.angle_mean == pytest.approx(wn @ at, rel=1e-12)


def test_bad_inputs_leave_the_tracker_untouched() -> None:
    tr, _ = _tracker()
    before = tr.state_bytes()
    for kw, match in (({"angle": math.nan, "u": 0.0}, "angle"),
                      ({"angle": 70.0, "u": math.inf}, "u"),
                      ({"angle": 70.0, "u": 0.0, "sd": 0.0}, "sd"),
                      ({"angle": 70.0, "u": 0.0, "sd": -1.0}, "sd"),
                      ({"angle": 70.0, "u": 0.0, "offset": math.nan}, "offset"),
                      ({"angle": 70.0, "u": 0.0, "sd": 1.0, "stage": 2}, "stage")):
        with pytest.raises(ValueError, match=match):
            update_angle(tr, **kw)  # type: ignore[arg-type]
    assert tr.state_bytes() == before
    model = analytic_model()
    fresh = build_tracker(model, TrackerConfig(n_particles=20, n_mc=1000))
    with pytest.raises(RuntimeError, match="no particles"):
        update_angle(fresh, 70.0, 0.0, sd=1.0)
    assert angle_sd(tr, noise_sd=0.3) >= 0.3


def test_stage_one_angle_is_the_first_predicted_angle() -> None:
    """stage 0 weighs the particles by their angle after the first bending stage."""
    tr, _ = _tracker()
    a1 = tr.ssm.predict_angles(tr.filter.x, 0.0)[:, 0]
    logw0 = tr.filter.logw.copy()
    angle, sd = float(a1.mean() - a1.std()), float(a1.std())
    update_angle(tr, angle, 0.0, sd=sd, stage=0)
    w = np.exp(logw0) * np.exp(-0.5 * ((angle - a1) / sd) ** 2)
    np.testing.assert_allclose(np.exp(tr.filter.logw), w / w.sum(), rtol=1e-9, atol=1e-300)
